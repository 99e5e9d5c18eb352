"""Held-out metrics per GPU-minute of bf16 training: the base recipe's DiT stage on a GPU (issue 26).

``train_base_dit`` (flow matching of the video latents, the base model's data) continues from the shipped weights on
the device with the trainer's defaults there (bf16 autocast and TF32 on CUDA), a checkpoint every ``--every`` steps,
all kept; the shipped model and each checkpoint's DiT (the VAE, text encoder and LDRM shipped) then go through
``diff4splat evaluate`` on the held-out set. The table: steps, minutes of training (the summed step times of
metrics.csv), the flow loss over the last interval, novel-view PSNR over all frames and per view-angle bin, and the
gap over repeating frame 0. Three parts share ``--work`` (``all`` runs them in turn; a lent GPU session runs ``data``
and ``train`` in one 10-minute command, ``eval`` in the next: benchmarks/gpu_session.sh). ``data`` uses every core;
``eval`` runs ``--jobs`` evaluations at once; a SIGINT (Ctrl-C, the session's deadline) reaches the trainer, which
saves the step it stopped at, and ``eval`` then takes every checkpoint there is:

    python benchmarks/gpu_training.py --part data  --work runs/gpu_training    # the base data: seeds 1 and 777
    python benchmarks/gpu_training.py --part train --work runs/gpu_training --steps 6000 --every 1000
    python benchmarks/gpu_training.py --part eval  --work runs/gpu_training --write
    python benchmarks/gpu_training.py --device cpu --quick --work /tmp/gt   # a dry run of the code paths, no figures

``--write`` replaces the section ``gpu_training`` of docs/benchmarks.md (CUDA and no ``--quick`` only). The data
are the model card's ("Data": 300 training scenes of seed 1, 24 held-out scenes of seed 777, 40 % static).
"""
from __future__ import annotations

import argparse
import csv
import os
import shutil
import signal
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import torch
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import markdown_table, write_section  # noqa: E402
from gpu import add_gpu_arguments, device_name, gpu_device  # noqa: E402

from models.bundle import Diff4SplatModel  # noqa: E402
from models.pretrained import load_weights  # noqa: E402
from training.stage_config import STAGE_CONFIG_DIR  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
SHIPPED = ROOT / "models" / "weights" / "base"
STAGE = "train_base_dit"
DATA = {"train": ("300", "1"), "heldout": ("24", "777")}
"""Folder → (scenes, seed) of ``data_prep synth`` (the model card's "Data")."""
BINS = ("0_15", "15_45", "45_90")
WALL = "train_wall_seconds.txt"
"""The training process's wall time in ``--work`` (start-up, data loading and checkpoints with the steps)."""


def _run(cmd: list[str], log: Path | None = None, env: dict[str, str] | None = None) -> None:
    """``cmd`` in the repository, its output here or in ``log``; raises CalledProcessError when it fails.

    On SIGINT (Ctrl-C, or ``gpu_session.sh``'s deadline) the child is sent SIGINT too and waited for: the trainer
    finishes its step and saves its checkpoint (``subprocess.run`` would kill it 0.25 s later, mid-step)."""
    print("$", " ".join(cmd) + (f" > {log}" if log else ""), flush=True)
    out = open(log, "w") if log else None  # noqa: SIM115 (closed below, after the child)
    try:
        with subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=out, stderr=subprocess.STDOUT if out else None) as proc:
            try:
                code = proc.wait()
            except KeyboardInterrupt:
                proc.send_signal(signal.SIGINT)  # a second one is harmless: the trainer's handler only sets a flag
                proc.wait()
                raise
    finally:
        if out:
            out.close()
    if code:
        raise subprocess.CalledProcessError(code, cmd)


def part_data(work: Path, quick: bool) -> None:
    """The training and held-out scenes (``data_prep synth``), skipped where the folder is already there."""
    for name, (scenes, seed) in DATA.items():
        out = work / name
        if out.is_dir():
            print(f"{out}: there already", flush=True)
            continue
        _run([sys.executable, "-m", "data_prep.cli", "synth", "--scenes", "4" if quick else scenes, "--seed", seed,
              "--static-ratio", "0.4", "--workers", str(os.cpu_count() or 1), "--quiet", "--out", str(out)])


def part_train(work: Path, device: torch.device, steps: int, every: int) -> None:
    """``train_base_dit`` from the shipped weights, ``steps`` steps, every ``every``-th step's checkpoint kept."""
    run = work / "dit"
    stage = yaml.safe_load((STAGE_CONFIG_DIR / f"{STAGE}.yaml").read_text())
    stage["trainer"].update(total_steps=steps, checkpoint_every=every, keep_checkpoints=steps // every + 1,
                            run_dir=str(run), device=str(device), progress=False)
    stage.update(init_from=str(SHIPPED), data=str(work / "train"))
    config = work / f"{STAGE}.yaml"
    config.write_text(yaml.safe_dump(stage, sort_keys=False))
    if run.exists():  # replaced only when it is a training run (this script's own earlier one), never other files
        if not (run / "metrics.csv").is_file():
            print(f"gpu_training.py: error: {run} exists and is not a training run; not replacing it", file=sys.stderr)
            raise SystemExit(2)
        shutil.rmtree(run)
    t0 = time.perf_counter()
    try:
        _run([sys.executable, "-m", "training.train", "--config", str(config), "--quiet"])
    finally:  # also after a SIGINT: the steps the run made took this long
        (work / WALL).write_text(f"{time.perf_counter() - t0:.1f}\n")


def _model_at(checkpoint: Path, out: Path) -> Path:
    """The shipped model with the checkpoint's weights (the trainer saves the whole model as ``model.…``)."""
    model = Diff4SplatModel.from_pretrained(SHIPPED)
    state = {k[len("model."):]: v for k, v in load_weights(checkpoint / "model.safetensors").items()}
    model.load_state_dict(state)  # strict: every weight of the model, nothing else
    model.save_pretrained(out)
    return out


def _metrics(run: Path) -> list[dict]:
    with open(run / "metrics.csv") as f:
        return [r for r in csv.DictReader(f) if r["skipped"] == "0"]


def _evaluate(points: list[tuple[int, Path]], work: Path, device: torch.device, quick: bool,
              jobs: int) -> list[dict]:
    """``diff4splat evaluate`` of each model, ``jobs`` processes at once (the cores shared among them; the base
    model leaves a GPU mostly idle), each one's report in ``eval/step_N.log``: the aggregate rows, in ``points``'
    order."""
    out = work / "eval"
    if out.exists():  # this script's own earlier evaluations, never other files
        if any(f.suffix not in (".csv", ".log") for f in out.iterdir()):
            print(f"gpu_training.py: error: {out} holds files other than evaluations; not replacing it",
                  file=sys.stderr)
            raise SystemExit(2)
        shutil.rmtree(out)
    out.mkdir(parents=True)
    threads = str(max(1, (os.cpu_count() or 1) // jobs))
    env = {**os.environ, "OMP_NUM_THREADS": threads, "NUMBA_NUM_THREADS": threads}

    def one(point: tuple[int, Path]) -> dict:
        step, model = point
        csv_path = out / f"step_{step}.csv"
        _run([sys.executable, "-m", "diff4splat.cli", "evaluate", "--data", str(work / "heldout"), "--checkpoint",
              str(model), "--device", str(device), "--quiet", "--csv", str(csv_path)]
             + (["--limit", "2", "--steps", "2"] if quick else []), log=out / f"step_{step}.log", env=env)
        with open(csv_path) as f:
            (row,) = csv.DictReader(f)
        return row

    with ThreadPoolExecutor(jobs) as pool:
        return list(pool.map(one, points))


def part_eval(work: Path, device: torch.device, quick: bool, jobs: int | None = None) -> str:
    """Each checkpoint (and the shipped model, step 0) through ``diff4splat evaluate`` → the table. ``jobs``:
    evaluations at once (default: one per two cores, at most one per model)."""
    points = [(0, SHIPPED)]
    for ckpt in sorted((work / "dit" / "checkpoints").glob("step_*"), key=lambda p: int(p.name.split("_")[1])):
        points.append((int(ckpt.name.split("_")[1]), _model_at(ckpt, work / "models" / ckpt.name)))
    evals = _evaluate(points, work, device, quick, jobs or min(len(points), max(1, (os.cpu_count() or 1) // 2)))
    log = _metrics(work / "dit")
    rows, last = [], 0
    for (step, _), e in zip(points, evals, strict=True):
        done = [r for r in log if last < int(r["step"]) <= step]
        minutes = sum(float(r["seconds"]) for r in log if int(r["step"]) <= step) / 60
        flow = sum(float(r["flow"]) for r in done) / len(done) if done else float("nan")
        psnr = [float(e["psnr_novel"])] + [float(e[f"psnr_{b}"]) for b in BINS]
        gap = float(e["psnr_novel"]) - float(e["psnr_novel_repeat"])
        rows.append([f"{step:,}", f"{minutes:.1f}", f"{flow:.3f}", *[f"{p:.2f}" for p in psnr], f"{gap:+.2f}",
                     f"{float(e['psnr_novel_noise']):.2f}"])
        last = step
    clips = evals[0]["clips"]
    wall = (f" The training process took {float((work / WALL).read_text()) / 60:.1f} min of wall time for its "
            f"{last:,} steps (start-up, data loading and checkpoints included)." if (work / WALL).is_file() else "")
    return (f"### bf16 training on the GPU: held-out metrics per GPU-minute\n\n"
            f"`python benchmarks/gpu_training.py --part data|train|eval`: `{STAGE}` continued from the shipped "
            f"weights (`models/weights/base`) on the trainer's defaults for the device, a checkpoint every "
            f"{points[1][0] if len(points) > 1 else '–'} steps; each checkpoint's DiT with the shipped VAE, text "
            f"encoder and LDRM through `diff4splat evaluate` on the {clips} held-out clips of seed 777. Minutes: the "
            f"summed step times of metrics.csv; flow: the flow-matching loss's mean since the previous row; PSNR of "
            f"the novel views (dB), all frames and per view-angle bin; gap: over repeating frame 0; noise: the "
            f"noise-latent ablation.{wall} Device: {device_name(device)}.\n\n"
            + markdown_table(["steps", "minutes", "flow", "novel PSNR", "0–15°", "15–45°", "45–90°",
                              "vs repeat frame 0", "noise latents"], rows))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--part", choices=("data", "train", "eval", "all"), default="all")
    ap.add_argument("--work", type=Path, required=True,
                    help="folder the parts share (train/, heldout/, dit/, models/, eval/)")
    ap.add_argument("--steps", type=int, default=6000, help="training steps (default 6000, the recipe's)")
    ap.add_argument("--every", type=int, default=1000, help="steps between evaluated checkpoints (default 1000)")
    ap.add_argument("--jobs", type=int, default=None,
                    help="evaluations at once (default: one per two cores, at most one per model)")
    add_gpu_arguments(ap, "4 scenes, 4 steps, 2 clips: the code paths, no figures")
    args = ap.parse_args()
    device = gpu_device(args)
    if device is None:
        return 2
    steps, every = (4, 2) if args.quick else (args.steps, args.every)
    if steps < 1 or every < 1 or (args.jobs is not None and args.jobs < 1):
        print("gpu_training.py: error: --steps, --every and --jobs must be ≥ 1", file=sys.stderr)
        return 2
    # the deadline's SIGINT must reach part_train even where a non-interactive shell started this in the background,
    # which leaves SIGINT ignored (Python then installs no KeyboardInterrupt, and the trainer would run to its end)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    args.work.mkdir(parents=True, exist_ok=True)
    parts = ("data", "train", "eval") if args.part == "all" else (args.part,)
    for part in parts:
        t0 = time.perf_counter()
        try:
            if part == "data":
                part_data(args.work, args.quick)
            elif part == "train":
                part_train(args.work, device, steps, every)
            else:
                body = part_eval(args.work, device, args.quick, args.jobs)
                print(body, flush=True)
                if args.write:
                    write_section("gpu_training", body)
        except KeyboardInterrupt:
            print(f"gpu_training.py: interrupted in part {part} after {time.perf_counter() - t0:.0f} s (a training "
                  f"run keeps the checkpoint it saved on the signal)", file=sys.stderr)
            return 130
        print(f"({part}: {time.perf_counter() - t0:.0f} s)", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
