"""Issue 58's motion stages trained on a GPU from the shipped base model: ``train_base_motion`` (the LDRM's motion
path, the default) or ``train_base_text_mover`` (the DiT and the text encoder on one-mover clips, the moving cells
weighted: does the DiT learn to follow the caption's direction word?).

For ``train_base_motion`` the starting model is the shipped networks with the motion network at its
zero-initialised identity (``training.compose``), trained on the base data (``gpu_training.py --part data`` makes it:
300 scenes of seed 1); ``train_base_text_mover`` starts from the shipped model itself, on ``--mover-scenes``
one-mover scenes made here when ``--data`` is missing (``data_prep synth --static-ratio 0 --motions translate
--max-movers 1``, seed 20261206, on every core). The trainer runs with its defaults for the device; the last
checkpoint's weights and the run's metrics.csv are copied to ``--out``. A SIGINT (``gpu_session.sh``'s deadline)
reaches the trainer, which saves the step it is at; the copy is made from it:

    python benchmarks/gpu_motion.py --work runs/gpu_training --out $OUT --steps 4000
    python benchmarks/gpu_motion.py --stage train_base_text_mover --data runs/gpu_training/train_mover \
        --mover-scenes 3000 --batch-size 16 --work runs/gpu_training --out $OUT --steps 8000
    python benchmarks/gpu_motion.py --work /tmp/gm --device cpu --steps 2 --data data/synth_heldout   # a dry run

The model this trains is rebuilt here from the copied weights with ``--unpack DIR`` (``DIR/model``: a model folder
for ``diff4splat evaluate --checkpoint`` and ``generate --checkpoint``; the same ``--stage``). Score
``train_base_text_mover`` with ``benchmarks/motion_path.py --data <a one-mover set> --checkpoint DIR/model
--direction --latents ''`` (its last line: whether the DiT reads the direction word).
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import shutil
import sys
import time
from pathlib import Path

import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
from gpu_training import SHIPPED, _run  # noqa: E402

from diff4splat.io.structured import read_yaml  # noqa: E402
from models.bundle import Diff4SplatModel, config_path  # noqa: E402
from models.motion import MotionConfig  # noqa: E402
from models.pretrained import load_weights  # noqa: E402
from training.compose import compose  # noqa: E402
from training.stage_config import STAGE_CONFIG_DIR  # noqa: E402

STAGES = ("train_base_motion", "train_base_text_mover")
MOVER_SEED = "20261206"
"""Seed of the one-mover training scenes (the CPU run of the model card's "This release" took its first 300)."""


def motion_config(work: Path) -> Path:
    """The base model config with a motion network of :class:`models.motion.MotionConfig`'s defaults, as a YAML in
    ``work`` (the shipped base has none until one is trained)."""
    data = read_yaml(config_path("base"), "model config")
    data["name"] = "base_motion"
    data["ldrm"]["motion"] = dataclasses.asdict(MotionConfig())
    path = work / "base_motion.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def start_model(work: Path, stage: str = STAGES[0]) -> Diff4SplatModel:
    """``stage``'s starting model: for ``train_base_motion`` the shipped base networks and a zero-initialised motion
    network (the identity: no motion); otherwise the shipped base model."""
    if stage == "train_base_motion":
        return compose(motion_config(work), {name: SHIPPED for name in ("vae", "text_encoder", "dit", "ldrm")})
    return Diff4SplatModel.from_pretrained(SHIPPED)


def mover_data(data: Path, scenes: int) -> None:
    """``scenes`` one-mover training scenes in ``data`` (module docstring), unless the folder is there."""
    if data.is_dir():
        print(f"{data}: there already", flush=True)
        return
    _run([sys.executable, "-m", "data_prep.cli", "synth", "--scenes", str(scenes), "--seed", MOVER_SEED,
          "--static-ratio", "0", "--motions", "translate", "--max-movers", "1", "--workers",
          str(os.cpu_count() or 1), "--quiet", "--out", str(data)])


def train(work: Path, data: Path, device: str, steps: int, every: int, stage_name: str = STAGES[0],
          batch_size: int | None = None) -> Path:
    """``stage_name`` for ``steps`` steps from :func:`start_model` in ``work`` (``batch_size``: the stage's when
    None); returns the run folder."""
    short = stage_name.removeprefix("train_")
    run = work / short
    stage = yaml.safe_load((STAGE_CONFIG_DIR / f"{stage_name}.yaml").read_text())
    stage["trainer"].update(total_steps=steps, checkpoint_every=every, run_dir=str(run), device=device,
                            progress=False, **({} if batch_size is None else {"batch_size": batch_size}))
    init = work / f"init_{short}"
    if not (init / "config.json").is_file():
        start_model(work, stage_name).save_pretrained(init, overwrite=True)
    stage.update(init_from=str(init), data=str(data))
    config = work / f"{stage_name}.yaml"
    config.write_text(yaml.safe_dump(stage, sort_keys=False))
    if run.exists():
        if not (run / "metrics.csv").is_file():
            raise SystemExit(f"gpu_motion.py: error: {run} exists and is not a training run; not replacing it")
        shutil.rmtree(run)
    t0 = time.perf_counter()
    try:
        _run([sys.executable, "-m", "training.train", "--config", str(config), "--quiet"])
    except KeyboardInterrupt:
        print("gpu_motion.py: stopped at the deadline; the trainer saved the step it was at", flush=True)
    print(f"gpu_motion.py: training wall {time.perf_counter() - t0:.1f} s", flush=True)
    return run


def copy_out(run: Path, out: Path) -> None:
    """The last checkpoint's weights (``model.safetensors``) and ``metrics.csv`` of ``run`` into ``out``."""
    ckpts = sorted((run / "checkpoints").glob("step_*"), key=lambda p: int(p.name.split("_")[1]))
    out.mkdir(parents=True, exist_ok=True)
    if ckpts:
        shutil.copy(ckpts[-1] / "model.safetensors", out / "model.safetensors")
        (out / "step.txt").write_text(ckpts[-1].name + "\n")
    shutil.copy(run / "metrics.csv", out / "metrics.csv")


def unpack(weights: Path, out: Path, stage: str = STAGES[0]) -> Path:
    """A model folder ``out`` from ``stage``'s :func:`start_model` and a checkpoint's ``model.safetensors``."""
    out.parent.mkdir(parents=True, exist_ok=True)
    model = start_model(out.parent, stage)
    state = {k[len("model."):]: v for k, v in load_weights(weights).items() if k.startswith("model.")}
    model.load_state_dict(state, strict=True)
    return model.save_pretrained(out, overwrite=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, default=Path("runs/gpu_training"))
    ap.add_argument("--data", type=Path, default=None, help="training scenes (default: WORK/train)")
    ap.add_argument("--out", type=Path, default=None, help="where the weights and metrics.csv go")
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--steps", type=int, default=4000)
    ap.add_argument("--every", type=int, default=250, help="steps between checkpoints (default 250)")
    ap.add_argument("--unpack", type=Path, default=None, help="make DIR/model from --out's weights, no training")
    ap.add_argument("--stage", choices=STAGES, default=STAGES[0])
    ap.add_argument("--mover-scenes", type=int, default=None,
                    help="make this many one-mover scenes in --data first where it is missing")
    ap.add_argument("--batch-size", type=int, default=None, help="clips a step (default: the stage config's)")
    args = ap.parse_args()
    if args.unpack is not None:
        print("wrote", unpack(args.out / "model.safetensors", args.unpack / "model", args.stage))
        return
    args.work.mkdir(parents=True, exist_ok=True)
    data = args.data or args.work / "train"
    if args.mover_scenes is not None:
        mover_data(data, args.mover_scenes)
    run = train(args.work, data, args.device, args.steps, args.every, args.stage, args.batch_size)
    if args.out is not None:
        copy_out(run, args.out)


if __name__ == "__main__":
    main()
