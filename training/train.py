"""Train one stage: ``python -m training.train --config train_stage1 [--resume]``.

Distributed: ``torchrun --nproc_per_node N -m training.train --config ...`` (DDP, gloo on CPU and nccl on
CUDA; ``--strategy fsdp`` for paper-size models). At the end rank 0 writes the trained model to
``<run_dir>/model`` (``Diff4SplatModel.save_pretrained``; EMA weights when EMA is on), the
``init_from`` of the next stage; after a VAE stage the latent scaling is calibrated first
(:func:`calibrate_latent_scaling`). Bad input: one line on stderr, exit code 2.
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import torch

from diff4splat.errors import run_cli

__all__ = ["main", "build_training", "calibrate_latent_scaling"]

LATENT_SCALING_CLIPS = 64
"""Training clips whose posterior means set the VAE's latent scaling after its stage."""


def build_training(stage, seed: int | None = None):
    """Model (+ freezing), dataset and :class:`Trainer` for a :class:`StageConfig`."""
    from data_prep.clips import ClipConfig, ClipDataset
    from models.bundle import Diff4SplatModel, load_config

    from .objectives import TrainingModule
    from .stages import apply_freezing
    from .trainer import Trainer

    if stage.init_from:
        if not (Path(stage.init_from) / "config.json").is_file():
            raise FileNotFoundError(f"init_from: {stage.init_from} is not a model folder (no config.json)")
        model = Diff4SplatModel.from_pretrained(stage.init_from)
    else:
        model = Diff4SplatModel.random(load_config(stage.model_config), seed=stage.trainer.seed)
    unit = model.config.pixel_multiple
    for name in ("height", "width"):  # a stage may train below the model resolution, on the same grid
        if getattr(stage, name) % unit:
            raise ValueError(f"{name} must be a multiple of {unit} pixels for this model, got {getattr(stage, name)}")
    counts = apply_freezing(model, stage.train)
    if not Path(stage.data).is_dir():
        raise FileNotFoundError(f"data: {stage.data} is not a folder")
    dataset = ClipDataset(stage.data, ClipConfig(num_frames=stage.num_frames, height=stage.height, width=stage.width,
                                                 scenes=stage.scenes, plucker="packed", seed=stage.trainer.seed))
    if len(dataset) == 0:
        raise ValueError(f"data: no {stage.scenes} clips of {stage.num_frames} frames in {stage.data}")
    module = TrainingModule(model, stage)
    trainer = Trainer(module, dataset, lambda mod, batch, gen: mod(batch, gen), stage.trainer,
                      extra_meta={"stage": dataclasses.asdict(stage), "trainable": counts})
    return trainer, model, counts


@torch.no_grad()
def calibrate_latent_scaling(model, dataset, num_clips: int = LATENT_SCALING_CLIPS) -> tuple[float, float]:
    """Set the VAE's ``scaling_factor``/``shift_factor`` so that the DiT sees zero-mean, unit-variance
    latents a·(z − b) (:func:`models.vae.estimate_latent_scaling`; Rombach et al. 2022 §4.3.2).

    Uses the posterior means of the first ``num_clips`` clips of ``dataset`` (deterministic). Run once
    after the VAE stage, before any stage that trains the DiT on latents.

    Returns:
        (scaling_factor, shift_factor), also written into ``model.config.vae``.

    Raises:
        ValueError: an empty dataset.
    """
    from models.vae import estimate_latent_scaling

    if len(dataset) == 0:
        raise ValueError("dataset: no clips to estimate the latent scaling from")
    vae = model.vae
    was_training = vae.training
    vae.eval()
    means = [vae.encode(dataset[i]["video"][None] * 2 - 1)[0] for i in range(min(num_clips, len(dataset)))]
    vae.train(was_training)
    a, b = estimate_latent_scaling(torch.cat([m.flatten() for m in means]))
    vae.config.scaling_factor, vae.config.shift_factor = a, b  # the same object as model.config.vae
    return a, b


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``python -m training.train``. Returns the exit code: 0, 2 after an expected failure
    (one ``train: error: …`` line: bad config, corrupt checkpoint, OS error on the run folder), 130 after
    Ctrl-C (:func:`diff4splat.errors.run_cli`); a bug keeps its traceback."""
    return run_cli("train", lambda: _main(argv))


def _main(argv: list[str] | None) -> int:
    ap = argparse.ArgumentParser(prog="python -m training.train", description=__doc__.splitlines()[0])
    ap.add_argument("--config", required=True,
                    help="stage config: a shipped name (train_vae, train_stage1..3) or a YAML path")
    ap.add_argument("--data", default=None, help="dataset root (overrides the YAML)")
    ap.add_argument("--run-dir", default=None, help="run folder (overrides trainer.run_dir)")
    ap.add_argument("--init-from", default=None, help="model folder to start from (overrides the YAML)")
    ap.add_argument("--steps", type=int, default=None, help="total optimizer steps (overrides the YAML)")
    ap.add_argument("--strategy", choices=("ddp", "fsdp"), default=None, help="distributed strategy")
    ap.add_argument("--resume", action="store_true", help="continue from the run's latest checkpoint")
    ap.add_argument("--quiet", action="store_true", help="no progress bar")
    args = ap.parse_args(argv)
    from .stages import load_stage

    trainer_over = {k: v for k, v in {"run_dir": args.run_dir, "total_steps": args.steps,
                                      "strategy": args.strategy}.items() if v is not None}
    if args.quiet:
        trainer_over["progress"] = False
    stage = load_stage(args.config, data=args.data, init_from=args.init_from, trainer=trainer_over or None)
    trainer, model, counts = build_training(stage)
    if trainer.rank == 0:
        print(f"train: stage {stage.name}, trainable {counts}, {len(trainer.dataset)} clips, "
              f"{stage.trainer.total_steps} steps → {trainer.run_dir}", file=sys.stderr)
    summary = trainer.fit(resume=args.resume)
    if trainer.rank == 0 and not summary["stopped"]:
        ema = trainer.ema_state_dict()
        if ema is not None:  # keys of the TrainingModule: "model.<network>..."
            model.load_state_dict({k[len("model."):]: v for k, v in ema.items()})
        if "vae" in stage.objectives:
            a, b = calibrate_latent_scaling(model, trainer.dataset)
            print(f"train: VAE latent scaling_factor {a:.6g}, shift_factor {b:.6g}", file=sys.stderr)
        model.save_pretrained(Path(trainer.run_dir) / "model")
        print(f"train: wrote {Path(trainer.run_dir) / 'model'}", file=sys.stderr)
    if torch.distributed.is_available() and torch.distributed.is_initialized():
        torch.distributed.destroy_process_group()
    return 0


if __name__ == "__main__":
    sys.exit(main())
