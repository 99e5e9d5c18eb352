"""Stage configurations: which modules train, at what resolution, on which scenes, with which losses.

Diff4Splat trains progressively (Pan et al. 2025): (1) static geometry pretraining at low resolution
with the deformation module frozen, (2) static high-resolution refinement, (3) dynamic fine-tuning
with everything unfrozen and the motion loss on. Before them, the tiny configuration trains its own
video VAE (``vae`` stage); the VAE then stays frozen, as the text encoder always does (the paper
uses a frozen T5; the tiny text encoder is a frozen randomly initialised T5-style network whose
features the DiT's cross-attention learns to read).

``configs/training/train_<stage>.yaml`` files (package data; :func:`load_stage` takes their names, e.g.
``train_stage1``) override :class:`StageConfig`'s defaults.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

from torch import nn

from diff4splat.config_files import STAGE_CONFIGS
from diff4splat.io.structured import read_yaml
from models.bundle import DEFAULT_CONFIG
from models.pretrained import config_from_dict

from .losses import LossWeights
from .trainer import TrainerConfig

__all__ = ["StageConfig", "load_stage", "stage_names", "apply_freezing", "MODULES", "STAGE_CONFIG_DIR"]

STAGE_CONFIG_DIR = STAGE_CONFIGS
"""The shipped stage configs (``train_vae``, ``train_stage1`` … ``train_stage3``): ``configs/training/``
(:mod:`diff4splat.config_files`)."""

MODULES = ("vae", "text_encoder", "dit", "ldrm", "ldrm.deformation", "ldrm.head", "ldrm.image_branch")
"""Module names a stage can train (``ldrm.deformation`` is the LDRM's deformation network; ``ldrm.head`` and
``ldrm.image_branch`` alone train a new head on the LDRM's features, which the deformation network also reads)."""

OBJECTIVES = ("vae", "diffusion", "reconstruction")


@dataclass
class StageConfig:
    """One training stage.

    Attributes:
        name: stage name (``vae``, ``stage1``, ``stage2``, ``stage3``).
        model_config: model config name (``configs/<name>.yaml``) used when ``init_from`` is None.
        init_from: a model folder (``Diff4SplatModel.save_pretrained``) to start from, usually the
            previous stage's ``<run_dir>/model``; None = a seeded random model.
        data: dataset root in data_prep's format.
        train: modules whose parameters are optimised (others frozen); see :data:`MODULES`.
        objectives: subset of ``vae`` (reconstruction + KL), ``diffusion`` (flow matching of the DiT),
            ``reconstruction`` (rendering losses of the LDRM).
        scenes: ``static``, ``dynamic`` or ``all`` (ClipDataset filter).
        height, width, num_frames: clip size (pixels, frames T = 1 + 4k).
        render_frames: target frames rendered per clip for the rendering losses (frame 0 always
            included); fewer frames = faster steps.
        deformation: predict deformation (times passed to the LDRM); off in static stages.
        motion: motion (track) loss on.
        latent_noise: largest σ of the noise mixed into latent frames 1… before the LDRM sees them,
            x = (1 − σ)·z + σ·ε with σ ~ U(0, latent_noise) per clip (the flow-matching interpolant), so the
            LDRM learns to read imperfect, generated latents; frame 0 (the photo's own latent) stays clean.
            0 = off (ours; Lyra-style training on generated latents costs a sampler run per step).
        weights: loss weights (:class:`training.losses.LossWeights`).
        kl_weight: weight of the VAE KL term (per element, β-VAE style).
        caption_dropout: probability of training the DiT without text (the empty-prompt path).
        flow_shift: timestep shift of the logit-normal training σ.
        trainer: optimisation, device and precision settings (:class:`training.trainer.TrainerConfig`: ``device``
            auto/cpu/cuda[:N], ``bf16`` auto = on for CUDA, ``tf32``, ``gradient_checkpointing`` of the DiT,
            ``strategy`` ddp/fsdp under torchrun).
    """

    name: str = "stage1"
    model_config: str = DEFAULT_CONFIG
    init_from: str | None = None
    data: str = "data/synth_train"
    train: tuple[str, ...] = ("dit", "ldrm")
    objectives: tuple[str, ...] = ("diffusion", "reconstruction")
    scenes: str = "static"
    height: int = 32
    width: int = 32
    num_frames: int = 17
    render_frames: int = 3
    deformation: bool = False
    motion: bool = False
    latent_noise: float = 0.0
    weights: LossWeights = field(default_factory=LossWeights)
    kl_weight: float = 1e-6
    caption_dropout: float = 0.1
    flow_shift: float = 1.0
    trainer: TrainerConfig = field(default_factory=TrainerConfig)

    def __post_init__(self) -> None:
        for m in self.train:
            if m not in MODULES:
                raise ValueError(f"stage.train: unknown module {m!r} (known: {MODULES})")
        for o in self.objectives:
            if o not in OBJECTIVES:
                raise ValueError(f"stage.objectives: unknown objective {o!r} (known: {OBJECTIVES})")
        if self.scenes not in ("static", "dynamic", "all"):
            raise ValueError(f"stage.scenes must be static, dynamic or all, got {self.scenes!r}")
        if self.motion and not self.deformation:
            raise ValueError("stage.motion needs stage.deformation (tracks move through the deformation)")
        if not 1 <= self.render_frames <= self.num_frames:
            raise ValueError(f"stage.render_frames must lie in [1, num_frames], got {self.render_frames}")
        if not 0 <= self.latent_noise <= 1:
            raise ValueError(f"stage.latent_noise must lie in [0, 1], got {self.latent_noise}")
        if not 0 <= self.caption_dropout <= 1:
            raise ValueError(f"stage.caption_dropout must lie in [0, 1], got {self.caption_dropout}")


def stage_names() -> list[str]:
    """Names of the shipped stage configs, sorted (``train_stage1`` … ``train_vae``)."""
    return sorted(p.stem for p in STAGE_CONFIG_DIR.glob("*.yaml"))


def load_stage(name_or_path: str | os.PathLike, **overrides) -> StageConfig:
    """Load a stage config by name (``configs/training/<name>.yaml``, e.g. ``train_stage1``) or a YAML path;
    ``overrides`` replace top-level fields (``trainer`` may be a dict of trainer fields).

    Raises:
        FileNotFoundError: no such name or file (the message lists the shipped names).
        ValueError: unknown or invalid fields.
    """
    path = Path(name_or_path)
    if path.suffix not in (".yaml", ".yml"):
        path = STAGE_CONFIG_DIR / f"{name_or_path}.yaml"
    if not path.is_file():
        raise FileNotFoundError(f"stage config: {str(name_or_path)!r} not found "
                                f"(shipped: {', '.join(stage_names())}; or a .yaml path)")
    data = read_yaml(path, "stage config")
    for k, v in overrides.items():
        if v is None:
            continue
        if isinstance(v, dict) and isinstance(data.get(k), dict):
            data[k] = {**data[k], **v}
        else:
            data[k] = v
    return config_from_dict(StageConfig, data, str(path))


def apply_freezing(model: nn.Module, train: tuple[str, ...]) -> dict[str, int]:
    """Freeze every parameter except those of the modules in ``train``.

    ``"ldrm"`` without ``"ldrm.deformation"`` trains the LDRM with its deformation network frozen.

    Returns:
        Trainable parameter count per module name.
    """
    model.requires_grad_(False)
    counts = {}
    for name in train:
        if name == "ldrm" and "ldrm.deformation" not in train:
            params = [p for n, p in model.ldrm.named_parameters() if not n.startswith("deformation.")]
        else:  # an optional part the model does not have (an LDRM without image branch) trains nothing
            parent, _, leaf = name.rpartition(".")
            module = getattr(model.get_submodule(parent), leaf, None) if parent else model.get_submodule(name)
            params = [] if module is None else list(module.parameters())
        for p in params:
            p.requires_grad_(True)
        counts[name] = sum(p.numel() for p in params)
    return counts
