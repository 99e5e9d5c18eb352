"""The LDRM's motion path trained on a GPU (issue 58): ``train_base_motion`` from the shipped base model.

Builds the starting model (the shipped networks, the motion network at its zero-initialised identity:
``training.compose``), trains the motion network alone on the base data (``gpu_training.py --part data`` makes it:
300 scenes of seed 1) with the trainer's defaults for the device, and copies the last checkpoint's weights and the
run's metrics.csv to ``--out``. A SIGINT (``gpu_session.sh``'s deadline) reaches the trainer, which saves the step it
is at; the copy is made from it:

    python benchmarks/gpu_motion.py --work runs/gpu_training --out $OUT --steps 4000
    python benchmarks/gpu_motion.py --work /tmp/gm --device cpu --steps 2 --data data/synth_heldout   # a dry run

The model this trains is rebuilt here from the copied weights with ``--unpack DIR`` (``DIR/model``: a model folder
for ``diff4splat evaluate --checkpoint`` and ``generate --checkpoint``).
"""
from __future__ import annotations

import argparse
import dataclasses
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

STAGE = "train_base_motion"


def motion_config(work: Path) -> Path:
    """The base model config with a motion network of :class:`models.motion.MotionConfig`'s defaults, as a YAML in
    ``work`` (the shipped base has none until one is trained)."""
    data = read_yaml(config_path("base"), "model config")
    data["name"] = "base_motion"
    data["ldrm"]["motion"] = dataclasses.asdict(MotionConfig())
    path = work / "base_motion.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def start_model(work: Path) -> Diff4SplatModel:
    """The shipped base networks and a zero-initialised motion network (the identity: no motion)."""
    return compose(motion_config(work), {name: SHIPPED for name in ("vae", "text_encoder", "dit", "ldrm")})


def train(work: Path, data: Path, device: str, steps: int, every: int) -> Path:
    """``train_base_motion`` for ``steps`` steps from :func:`start_model` in ``work``; returns the run folder."""
    run = work / "base_motion"
    stage = yaml.safe_load((STAGE_CONFIG_DIR / f"{STAGE}.yaml").read_text())
    stage["trainer"].update(total_steps=steps, checkpoint_every=every, run_dir=str(run), device=device,
                            progress=False)
    init = work / "init_motion"
    if not (init / "config.json").is_file():
        start_model(work).save_pretrained(init, overwrite=True)
    stage.update(init_from=str(init), data=str(data))
    config = work / f"{STAGE}.yaml"
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


def unpack(weights: Path, out: Path) -> Path:
    """A model folder ``out`` from :func:`start_model` and a checkpoint's ``model.safetensors``."""
    out.parent.mkdir(parents=True, exist_ok=True)
    model = start_model(out.parent)
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
    args = ap.parse_args()
    if args.unpack is not None:
        print("wrote", unpack(args.out / "model.safetensors", args.unpack / "model"))
        return
    args.work.mkdir(parents=True, exist_ok=True)
    run = train(args.work, args.data or args.work / "train", args.device, args.steps, args.every)
    if args.out is not None:
        copy_out(run, args.out)


if __name__ == "__main__":
    main()
