"""Train one stage: ``python -m training.train --config train_stage1 [--resume] [--device cuda]``.

Under ``torchrun --nproc_per_node N`` one process per GPU (DDP, or ``--strategy fsdp``); ``--device`` overrides the
stage's ``trainer.device`` (docs/DESIGN.md, "Training"). At the end rank 0 writes ``<run_dir>/model`` (EMA weights
when on; a diffusers backbone with its LoRA merged, :mod:`training.backbone_training`), the next stage's
``init_from``, after calibrating the latent scaling when the VAE's encoder trained. Bad input: one line on stderr,
exit code 2.
"""
from __future__ import annotations

import argparse
import dataclasses
import importlib
import sys
from pathlib import Path

import torch

from data_prep.clips import ClipConfig, ClipDataset
from data_prep.format import list_scenes
from diff4splat.io.output_folders import check_output_dir
from diff4splat.utils.checks import MissingExtraError
from diff4splat.utils.devices import resolve_device
from diff4splat.utils.errors import run_cli
from models.backbone_model import INDEX_FILE, BackboneModel
from models.bundle import Diff4SplatModel, load_config
from models.motion_generator import MotionGenerator, MotionGeneratorConfig
from models.pretrained import CONFIG_NAME
from models.vae import estimate_latent_scaling

from . import stage_config
from .checkpoint import latest_checkpoint
from .objectives import TrainingModule
from .placement import resolve_bf16, training_device
from .stage_config import StageConfig, apply_freezing
from .trainer import Trainer

__all__ = ["main", "build_training", "check_run_dir", "calibrate_latent_scaling", "backbone_training", "RUN_FILES"]

LATENT_SCALING_CLIPS = 64
"""Training clips whose posterior means set the VAE's latent scaling after its stage."""


def build_training(stage: StageConfig, seed: int | None = None
                   ) -> tuple[Trainer, Diff4SplatModel | BackboneModel, dict[str, int]]:
    """(trainer, the model it trains inside a :class:`TrainingModule`, trainable count per module) of a stage, on
    ``stage.trainer.device`` (checked first). ``seed`` is unused: ``trainer.seed`` seeds everything.

    Raises ValueError (unusable device, clip size off the model's pixel grid or length not 1 + t·k, no or too few
    clips, ``init_from`` of the wrong kind, ``backbone_dtype: bfloat16`` without bf16), FileNotFoundError
    (``init_from``, ``data``), MissingExtraError (a diffusers stage without peft/diffusers).
    """
    device = resolve_device(stage.trainer.device, "trainer.device")
    if stage.backbone == "ours":
        model = _ours_model(stage)
        counts, unit, plucker = apply_freezing(model, stage.train), model.config.pixel_multiple, "packed"
    else:
        if stage.backbone_dtype != "float32" and not resolve_bf16(stage.trainer.bf16, training_device(device)):
            raise ValueError(f"stage.backbone_dtype: {stage.backbone_dtype} weights need bf16 autocast "
                             "(trainer.bf16: true, or auto on CUDA)")
        tools = backbone_training()
        model = tools.load_backbone_model(stage)
        counts, unit, plucker = tools.apply_backbone_freezing(model, stage.train), tools.pixel_multiple(model), "raw"
        model.backbone.latent.num_latent_frames(stage.num_frames)  # T = 1 + t·k
    for name in ("height", "width"):  # a stage may train below the model resolution, on the same grid
        if getattr(stage, name) % unit:
            raise ValueError(f"{name} must be a multiple of {unit} pixels for this model, got {getattr(stage, name)}")
    if not Path(stage.data).is_dir():
        raise FileNotFoundError(f"data: {stage.data} is not a folder")
    dataset = ClipDataset(stage.data, ClipConfig(num_frames=stage.num_frames, height=stage.height, width=stage.width,
                                                 scenes=stage.scenes, plucker=plucker, seed=stage.trainer.seed))
    if len(dataset) == 0:
        raise ValueError(f"data: no {stage.scenes} clips of {stage.num_frames} frames in {stage.data}")
    if stage.scenes != "all" and len(dataset) < stage.trainer.batch_size:  # the filter is the likely cause
        ratio = "--static-ratio" if stage.scenes == "static" else "a lower --static-ratio"
        raise ValueError(f"data: {len(dataset)} of the {len(list_scenes(stage.data))} scenes in {stage.data} are "
                         f"{stage.scenes} (stage.scenes: {stage.scenes}), fewer than one batch of "
                         f"{stage.trainer.batch_size}: make more {stage.scenes} scenes (data_prep synth {ratio}) or "
                         "lower trainer.batch_size")
    teacher = None  # the LDRM of the stage.teacher model folder
    if stage.teacher is not None:
        if not (Path(stage.teacher) / CONFIG_NAME).is_file():
            raise FileNotFoundError(f"teacher: {stage.teacher} is not a model folder (no config.json)")
        teacher = Diff4SplatModel.from_pretrained(stage.teacher).ldrm
    module = TrainingModule(model, stage, teacher)
    trainer = Trainer(module, dataset, lambda mod, batch, gen: mod(batch, gen), stage.trainer,
                      extra_meta={"stage": dataclasses.asdict(stage), "trainable": counts})
    return trainer, model, counts


def _ours_model(stage: StageConfig) -> Diff4SplatModel:
    """``init_from`` (a :meth:`Diff4SplatModel.save_pretrained` folder), else a random model of ``model_config``;
    with :func:`_with_motion_generator` where the stage trains one."""
    return _with_motion_generator(_initial_model(stage), stage)


def _with_motion_generator(model: Diff4SplatModel, stage: StageConfig) -> Diff4SplatModel:
    """``model`` with a fresh motion generator (:class:`models.motion_generator.MotionGeneratorConfig` defaults at the
    stage's clip size, seeded by ``trainer.seed``) when the stage trains ``motion_generator`` and it has none; else
    ``model``. ValueError: a clip that is not square."""
    if "motion_generator" not in stage.train or model.motion_generator is not None:
        return model
    if stage.height != stage.width:
        raise ValueError(f"height and width must be equal for a motion generator, got {stage.height}×{stage.width}")
    model.config = dataclasses.replace(model.config, motion_generator=MotionGeneratorConfig(image_size=stage.height))
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(stage.trainer.seed)
        model.motion_generator = MotionGenerator(model.config.motion_generator)
    return model


def _initial_model(stage: StageConfig) -> Diff4SplatModel:
    """``init_from``, else a random model of ``model_config``."""
    if not stage.init_from:
        return Diff4SplatModel.random(load_config(stage.model_config), seed=stage.trainer.seed)
    folder = Path(stage.init_from)
    if (folder / INDEX_FILE).is_file():
        raise ValueError(f"init_from: {folder} is a diffusers backbone folder ({INDEX_FILE}); set stage.backbone "
                         "(wan2.2-ti2v or cogvideox-i2v) and a lora: section to train it")
    if not (folder / CONFIG_NAME).is_file():
        raise FileNotFoundError(f"init_from: {stage.init_from} is not a model folder (no config.json)")
    return Diff4SplatModel.from_pretrained(folder)


def backbone_training():
    """:mod:`training.backbone_training`, imported on demand; MissingExtraError without peft or diffusers."""
    try:
        return importlib.import_module("training.backbone_training")
    except ModuleNotFoundError as e:
        raise MissingExtraError(f"training a diffusers backbone needs {e.name}: pip install 'diff4splat[diffusers]'"
                                ) from None


@torch.no_grad()
def calibrate_latent_scaling(model, dataset, num_clips: int = LATENT_SCALING_CLIPS) -> tuple[float, float]:
    """Set and return the VAE's (``scaling_factor``, ``shift_factor``) so that the DiT sees zero-mean, unit-variance
    latents a·(z − b), from the posterior means of the first ``num_clips`` clips (Rombach et al. 2022 §4.3.2).
    Raises ValueError for an empty dataset."""
    if len(dataset) == 0:
        raise ValueError("dataset: no clips to estimate the latent scaling from")
    vae = model.vae
    device = next(vae.parameters()).device  # the clips come on the CPU; the VAE may be on a GPU
    was_training = vae.training
    vae.eval()
    means = [vae.encode(dataset[i]["video"][None].to(device) * 2 - 1)[0] for i in range(min(num_clips, len(dataset)))]
    vae.train(was_training)
    a, b = estimate_latent_scaling(torch.cat([m.flatten() for m in means]).float().cpu())
    vae.config.scaling_factor, vae.config.shift_factor = a, b  # the same object as model.config.vae
    return a, b


RUN_FILES = ("metrics.csv", "checkpoints", "model")
"""What a training run writes into its folder: an existing folder holding one of them is an earlier run."""


def check_run_dir(stage: StageConfig, resume: bool) -> None:
    """Check the run folder before anything is built or written (docs/DESIGN.md, "Training"): new, empty, or with
    ``resume`` an earlier run with a checkpoint; never an input, a protected place, an ancestor of them, nor inside
    an input. Raises ValueError, one line naming the folder."""
    run = Path(stage.trainer.run_dir)
    inputs = [p for p in (stage.data, stage.init_from) if p]
    check_output_dir(run, inputs=inputs, overwrite=True, kind="training run", parents=True)  # the protected places
    for p in inputs:
        if Path(p).resolve() in run.resolve().parents:
            raise ValueError(f"run folder {run} is inside input {p}; training would write into it (choose a "
                             "--run-dir outside it)")
    earlier = run.is_dir() and any((run / name).exists() for name in RUN_FILES)
    if run.is_dir() and not earlier and next(run.iterdir(), None) is not None:
        raise ValueError(f"run folder {run} is a non-empty folder that is not a training run (no "
                         f"{', '.join(RUN_FILES)}); choose a new --run-dir")
    checkpoint = latest_checkpoint(run)
    if resume and checkpoint is None:
        raise ValueError(f"--resume: no checkpoint in {run / 'checkpoints'}")
    if earlier and not resume:
        hint = ("pass --resume to continue it" if checkpoint is not None else
                "it has no checkpoint to resume from: delete it")
        raise ValueError(f"run folder {run} holds an earlier run; {hint}, or choose a new --run-dir")


def main(argv: list[str] | None = None) -> int:
    """``python -m training.train``; exit code 0, 2 after an expected failure (one line), 130 after Ctrl-C."""
    return run_cli("train", lambda: _main(argv))


def _main(argv: list[str] | None) -> int:
    """Parse, check, train and write the model."""
    ap = argparse.ArgumentParser(prog="python -m training.train", description=__doc__.splitlines()[0])
    ap.add_argument("--config", required=True,
                    help=f"stage config: a shipped name ({', '.join(stage_config.stage_names())}) or a YAML path")
    ap.add_argument("--data", default=None, help="dataset root (overrides the YAML)")
    ap.add_argument("--run-dir", default=None, help="run folder (overrides trainer.run_dir)")
    ap.add_argument("--init-from", default=None, help="model folder to start from (overrides the YAML)")
    ap.add_argument("--steps", type=int, default=None, help="total optimizer steps (overrides the YAML)")
    ap.add_argument("--strategy", choices=("ddp", "fsdp"), default=None, help="distributed strategy")
    ap.add_argument("--device", default=None,
                    help="torch device: auto (CUDA when present, else cpu), cpu, cuda, cuda:N; overrides "
                         "trainer.device (default: the YAML's, auto)")
    ap.add_argument("--resume", action="store_true", help="continue from the run's latest checkpoint")
    ap.add_argument("--quiet", action="store_true", help="no progress bar")
    args = ap.parse_args(argv)
    if args.device is not None:
        resolve_device(args.device, "--device")  # a device this machine lacks: one error naming the flag
    trainer_over = {k: v for k, v in {"run_dir": args.run_dir, "total_steps": args.steps,
                                      "strategy": args.strategy, "device": args.device}.items() if v is not None}
    if args.quiet:
        trainer_over["progress"] = False
    stage = stage_config.load_stage(args.config, data=args.data, init_from=args.init_from, trainer=trainer_over or None)
    check_run_dir(stage, args.resume)
    trainer, model, counts = build_training(stage)
    if trainer.rank == 0:
        print(f"train: stage {stage.name}, trainable {counts}, {len(trainer.dataset)} clips, "
              f"{stage.trainer.total_steps} steps on {trainer.device}{' (bf16)' if trainer.bf16 else ''}"
              f"{f' × {trainer.world} processes' if trainer.distributed else ''} → {trainer.run_dir}",
              file=sys.stderr)
    summary = trainer.fit(resume=args.resume)
    if not summary["stopped"]:
        # EMA weights, or the full weights of the shards (collective under FSDP: every rank takes part)
        state = trainer.final_state_dict() if trainer.ema is not None or trainer.sharded else None
        if trainer.rank == 0:
            _write_model(trainer, model, stage, state)
    if torch.distributed.is_available() and torch.distributed.is_initialized():
        torch.distributed.destroy_process_group()
    return 0


def _write_model(trainer: Trainer, model: Diff4SplatModel | BackboneModel, stage: StageConfig,
                 state: dict | None) -> None:
    """Rank 0: write ``<run_dir>/model`` from ``state`` (TrainingModule keys; None: the model's own weights)."""

    ours = stage.backbone == "ours"
    if trainer.sharded:  # the trained model holds this rank's shards only: a plain one takes the full weights
        model = Diff4SplatModel(model.config) if ours else backbone_training().load_backbone_model(stage)
    if state is not None:
        model.load_state_dict({k[len("model."):]: v for k, v in state.items()})
    if "vae" in stage.train:  # the encoder trained: new latents, new scaling (a decoder-only stage keeps both)
        a, b = calibrate_latent_scaling(model, trainer.dataset)
        print(f"train: VAE latent scaling_factor {a:.6g}, shift_factor {b:.6g}", file=sys.stderr)
    if ours:
        model.save_pretrained(Path(trainer.run_dir) / "model")
    else:
        backbone_training().save_backbone_model(model, Path(trainer.run_dir) / "model")
    print(f"train: wrote {Path(trainer.run_dir) / 'model'}", file=sys.stderr)


if __name__ == "__main__":
    sys.exit(main())
