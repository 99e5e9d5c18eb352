"""Stage configurations: which modules train, at what resolution, on which scenes, with which losses. Diff4Splat
trains progressively (Pan et al. 2025): static at low resolution with the deformation frozen, static at full
resolution, then dynamic with the motion loss; the same stages train a diffusers backbone through LoRA
(:mod:`training.backbone_training`). Stages: docs/DESIGN.md, "Training". ``configs/training/train_<stage>.yaml``
(named by :func:`load_stage`, e.g. ``train_stage1``) override :class:`StageConfig`'s defaults.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path

from torch import nn

from diff4splat.io.structured import read_yaml
from diff4splat.utils.config_files import STAGE_CONFIGS
from models.backbone import BACKBONE_KINDS
from models.bundle import DEFAULT_CONFIG
from models.pretrained import config_from_dict

from .losses import LossWeights
from .trainer import TrainerConfig

__all__ = ["StageConfig", "LoraSettings", "load_stage", "stage_names", "apply_freezing", "MODULES", "STAGE_CONFIG_DIR",
           "LORA_TARGETS", "BACKBONE_DTYPES", "RENDERED_SCENES"]

STAGE_CONFIG_DIR = STAGE_CONFIGS
"""The shipped stage configs, ``configs/training/`` (:mod:`diff4splat.utils.config_files`)."""

MODULES = ("vae", "vae.decoder", "text_encoder", "dit", "ldrm", "ldrm.deformation", "ldrm.motion", "ldrm.head",
           "ldrm.image_branch", "ldrm.image_depth", "motion_generator")
"""Module names a stage can train: ``vae.decoder`` alone keeps the encoder and latent scaling; ``ldrm.motion`` is
:mod:`models.motion`, ``ldrm.image_depth`` :class:`models.mono_depth.MonoDepth`; a diffusers backbone's ``dit`` is
its LoRA adapters and camera weights; ``motion_generator`` :mod:`models.motion_generator`."""

OBJECTIVES = ("vae", "diffusion", "reconstruction", "distill", "depth", "tracking", "motion_generation")

RENDERED_SCENES = ("decoded", "assembled")
"""What the reconstruction objective renders (:attr:`StageConfig.scene`)."""

LORA_TARGETS = ("to_q", "to_k", "to_v", "to_out.0", "net.0.proj", "net.2")
"""LoRA target modules (peft suffix match) of both diffusers transformers: the attention projections and the
feed-forward linears of each block (nothing outside the blocks matches)."""

BACKBONE_DTYPES = ("float32", "bfloat16")


@dataclass
class LoraSettings:
    """LoRA adapters (Hu et al. 2022) on a diffusers transformer: W x + (α/r)·B A x, A random, B zero (training
    starts from the pretrained transformer). ``rank`` ≥ 1, ``alpha`` > 0, ``dropout`` in [0, 1),
    ``target_modules`` name suffixes; ValueError naming ``stage.lora.<field>`` otherwise."""

    rank: int = 64
    alpha: float = 64.0
    dropout: float = 0.0
    target_modules: tuple[str, ...] = LORA_TARGETS

    def __post_init__(self) -> None:
        if self.rank < 1:
            raise ValueError(f"stage.lora.rank must be ≥ 1, got {self.rank}")
        if not self.alpha > 0:
            raise ValueError(f"stage.lora.alpha must be > 0, got {self.alpha}")
        if not 0 <= self.dropout < 1:
            raise ValueError(f"stage.lora.dropout must lie in [0, 1), got {self.dropout}")
        self.target_modules = tuple(self.target_modules)
        if not self.target_modules or not all(isinstance(t, str) and t for t in self.target_modules):
            raise ValueError(f"stage.lora.target_modules must be module names, got {self.target_modules!r}")


@dataclass
class StageConfig:
    """One training stage.

    ``init_from``: a model folder (usually the previous stage's ``<run_dir>/model``; None: a seeded random
    ``model_config``); ``train``: modules optimised (:data:`MODULES`, :func:`apply_freezing`); ``objectives``: of
    ``vae``, ``diffusion``, ``reconstruction``, ``distill`` (needs ``teacher``, blur ``distill_sigma`` pixels),
    ``depth`` (``ldrm.image_depth``), ``tracking``, ``motion_generation`` (``motion_generator``; the clip's height and
    width its ``image_size``); ``scenes``: ClipDataset filter; clip size ``height``×``width``,
    ``num_frames`` = 1 + 4k; ``render_frames`` per clip (frame 0 included); ``scene``: :data:`RENDERED_SCENES`
    (``decoded``: every source frame's Gaussians over black, the paper's §3.3; ``assembled``: the scene ``generate``
    builds); ``deformation``: predict deformation, ``motion``: track loss on (needs ``deformation``); ``kl_weight``:
    the VAE's KL weight; ``caption_dropout``: probability of no text; ``latent_noise``: largest σ of U(0, σ) noise
    mixed into latent frames 1… before the LDRM reads them; ``flow_shift``: timestep shift of our DiT's training σ;
    ``backbone``: ``ours`` or a diffusers kind held by ``init_from`` (then ``lora`` exactly when ``train`` lists
    ``dit``, frozen weights in ``backbone_dtype``); ``trainer``: :class:`training.trainer.TrainerConfig`. Raises
    ValueError naming ``stage.<field>``.
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
    scene: str = "decoded"
    deformation: bool = False
    motion: bool = False
    latent_noise: float = 0.0
    weights: LossWeights = field(default_factory=LossWeights)
    kl_weight: float = 1e-6
    caption_dropout: float = 0.1
    flow_shift: float = 1.0
    backbone: str = "ours"
    lora: LoraSettings | None = None
    backbone_dtype: str = "float32"
    teacher: str | None = None
    distill_sigma: float = 1.0
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
        if self.scene not in RENDERED_SCENES:
            raise ValueError(f"stage.scene must be one of {RENDERED_SCENES}, got {self.scene!r}")
        if self.motion and not self.deformation:
            raise ValueError("stage.motion needs stage.deformation (tracks move through the deformation)")
        if not 1 <= self.render_frames <= self.num_frames:
            raise ValueError(f"stage.render_frames must lie in [1, num_frames], got {self.render_frames}")
        if not 0 <= self.latent_noise <= 1:
            raise ValueError(f"stage.latent_noise must lie in [0, 1], got {self.latent_noise}")
        if not 0 <= self.caption_dropout <= 1:
            raise ValueError(f"stage.caption_dropout must lie in [0, 1], got {self.caption_dropout}")
        if ("distill" in self.objectives) != (self.teacher is not None):
            raise ValueError("stage.teacher: the distill objective needs a teacher model folder, and only it uses one")
        if not 0 < self.flow_shift < math.inf:  # σ' = sσ/(1 + (s − 1)σ): s ≤ 0 is no schedule
            raise ValueError(f"stage.flow_shift must be > 0, got {self.flow_shift}")
        if not 0 <= self.kl_weight < math.inf:
            raise ValueError(f"stage.kl_weight must be ≥ 0, got {self.kl_weight}")
        if not self.distill_sigma >= 0:
            raise ValueError(f"stage.distill_sigma must be ≥ 0 pixels, got {self.distill_sigma}")
        if isinstance(self.lora, dict):
            self.lora = config_from_dict(LoraSettings, self.lora, "stage.lora")
        self._check_backbone()

    def _check_backbone(self) -> None:
        """The backbone fields agree with ``train``, ``objectives`` and ``lora``."""
        if self.backbone not in BACKBONE_KINDS:
            raise ValueError(f"stage.backbone must be one of {BACKBONE_KINDS}, got {self.backbone!r}")
        if self.backbone_dtype not in BACKBONE_DTYPES:
            raise ValueError(f"stage.backbone_dtype must be one of {BACKBONE_DTYPES}, got {self.backbone_dtype!r}")
        if self.backbone == "ours":
            if self.lora is not None:
                raise ValueError("stage.lora: LoRA adapts a diffusers backbone's transformer; stage.backbone is ours "
                                 "(its DiT trains in full)")
            if self.backbone_dtype != "float32":
                raise ValueError("stage.backbone_dtype applies to a diffusers backbone; stage.backbone is ours")
            return
        frozen = sorted({"vae", "vae.decoder", "text_encoder"} & set(self.train))
        if frozen:
            raise ValueError(f"stage.train: the {self.backbone} backbone's {' and '.join(frozen)} cannot train "
                             "(trainable: dit through LoRA, ldrm and its parts)")
        if "distill" in self.objectives:
            raise ValueError("stage.objectives: distill follows a teacher model of our networks (backbone ours), "
                             f"not {self.backbone}")
        if "vae" in self.objectives:
            raise ValueError(f"stage.objectives: the {self.backbone} backbone's VAE is pretrained (no vae objective)")
        if ("dit" in self.train) != (self.lora is not None):
            raise ValueError(f"stage.lora: the {self.backbone} transformer trains through LoRA: give a lora: section "
                             "exactly when stage.train lists dit")


def stage_names() -> list[str]:
    """Names of the shipped stage configs, sorted (``train_stage1`` … ``train_vae``)."""
    return sorted(p.stem for p in STAGE_CONFIG_DIR.glob("*.yaml"))


def load_stage(name_or_path: str | os.PathLike, **overrides) -> StageConfig:
    """Load a stage config by name (``train_stage1``) or YAML path; non-None ``overrides`` replace top-level fields
    (a dict merges into a dict field). Raises FileNotFoundError (listing the shipped names), ValueError for bad
    fields."""
    path = Path(name_or_path)
    if path.suffix not in (".yaml", ".yml"):
        path = STAGE_CONFIG_DIR / f"{name_or_path}.yaml"
    if not path.is_file():
        raise FileNotFoundError(f"stage config: {str(name_or_path)!r} not found "
                                f"(shipped: {', '.join(stage_names())}; or a .yaml path)")
    data = read_yaml(path, "stage config")
    for k, v in overrides.items():
        if v is not None:
            data[k] = {**data[k], **v} if isinstance(v, dict) and isinstance(data.get(k), dict) else v
    return config_from_dict(StageConfig, data, str(path))


def apply_freezing(model: nn.Module, train: tuple[str, ...]) -> dict[str, int]:
    """Freeze every parameter except those of the modules in ``train``; returns the trainable count per name.
    ``"ldrm"`` leaves out its deformation and motion networks unless they are named too."""

    model.requires_grad_(False)
    counts = {}
    for name in train:
        if name == "ldrm":
            skip = tuple(f"{part}." for part in ("deformation", "motion") if f"ldrm.{part}" not in train)
            params = [p for n, p in model.ldrm.named_parameters() if not n.startswith(skip)]
        else:  # an optional part the model does not have (an LDRM without image branch) trains nothing
            parent, _, leaf = name.rpartition(".")
            module = getattr(model.get_submodule(parent) if parent else model, leaf, None)
            params = [] if module is None else list(module.parameters())
        for p in params:
            p.requires_grad_(True)
        counts[name] = sum(p.numel() for p in params)
    return counts
