"""Stage configurations: which modules train, at what resolution, on which scenes, with which losses.

Diff4Splat trains progressively (Pan et al. 2025): (1) static geometry pretraining at low resolution
with the deformation module frozen, (2) static high-resolution refinement, (3) dynamic fine-tuning
with everything unfrozen and the motion loss on. Before them, the tiny configuration trains its own
video VAE (``vae`` stage); the VAE then stays frozen, as the text encoder always does (the paper
uses a frozen T5; the tiny text encoder is a frozen randomly initialised T5-style network whose
features the DiT's cross-attention learns to read).

The same stages train a pretrained diffusers backbone (``backbone: wan2.2-ti2v`` or ``cogvideox-i2v``, ``init_from``
a diffusers folder; :mod:`training.backbone_training`): its VAE and text encoder frozen, its transformer through LoRA
adapters (``lora:``, :class:`LoraSettings`) plus the zero-initialised camera weights of its patch embedding, our
LDRM in full.

``configs/training/train_<stage>.yaml`` files (package data; :func:`load_stage` takes their names, e.g.
``train_stage1``, ``train_wan_stage1``) override :class:`StageConfig`'s defaults.
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
"""The shipped stage configs (``train_vae``, ``train_stage1`` … ``train_stage3``, ``train_wan_stage1`` … and
``train_cogvideox_stage1`` …): ``configs/training/``
(:mod:`diff4splat.utils.config_files`)."""

MODULES = ("vae", "vae.decoder", "text_encoder", "dit", "ldrm", "ldrm.deformation", "ldrm.motion", "ldrm.head",
           "ldrm.image_branch", "ldrm.image_depth")
"""Module names a stage can train (``vae.decoder`` is the VAE's decoder alone: the encoder, hence every latent the
DiT and the LDRM were trained on, and the latent scaling stay as they are; ``ldrm.deformation`` is the LDRM's
deformation network; ``ldrm.motion`` its motion network (:mod:`models.motion`); ``ldrm.head`` and
``ldrm.image_branch`` alone train a new head on the LDRM's features, which the deformation network also reads;
``ldrm.image_depth`` is the monocular depth network of frame 0, :class:`models.mono_depth.MonoDepth`;
``dit`` of a diffusers backbone is its transformer's LoRA adapters and camera weights)."""

OBJECTIVES = ("vae", "diffusion", "reconstruction", "distill", "depth", "tracking")

RENDERED_SCENES = ("decoded", "assembled")
"""What the reconstruction objective renders (:attr:`StageConfig.scene`)."""

LORA_TARGETS = ("to_q", "to_k", "to_v", "to_out.0", "net.0.proj", "net.2")
"""LoRA target modules (peft suffix match) of both diffusers transformers: the self- and cross-attention projections
(``blocks.N.attn1|attn2.to_q|to_k|to_v|to_out.0`` of ``WanTransformer3DModel``,
``transformer_blocks.N.attn1.to_*`` of ``CogVideoXTransformer3DModel``) and the feed-forward layers
(``blocks.N.ffn.net.0.proj|net.2``, ``transformer_blocks.N.ff.net.0.proj|net.2``); nothing outside the blocks
(embeddings, patch embedding, adaLN, output projection) matches."""

BACKBONE_DTYPES = ("float32", "bfloat16")


@dataclass
class LoraSettings:
    """LoRA adapters (Hu et al. 2022, "LoRA: Low-Rank Adaptation of Large Language Models") on a diffusers
    backbone's transformer: W x + (α/r)·B A x with A (r, in) random, B (out, r) zero, so training starts from the
    pretrained transformer exactly.

    Attributes:
        rank: r ≥ 1.
        alpha: α > 0 (the update is scaled by α/r).
        dropout: dropout on the adapters' input, in [0, 1) (drawn from torch's global RNG, which checkpoints save).
        target_modules: module-name suffixes that get adapters (:data:`LORA_TARGETS`: attention and FFN linears).
    """

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

    Attributes:
        name: stage name (``vae``, ``stage1``, ``stage2``, ``stage3``).
        model_config: model config name (``configs/<name>.yaml``) used when ``init_from`` is None.
        init_from: a model folder (``Diff4SplatModel.save_pretrained``) to start from, usually the
            previous stage's ``<run_dir>/model``; None = a seeded random model.
        data: dataset root in data_prep's format.
        train: modules whose parameters are optimised (others frozen); see :data:`MODULES`.
        objectives: subset of ``vae`` (reconstruction + KL), ``diffusion`` (flow matching of the DiT),
            ``reconstruction`` (rendering losses of the LDRM), ``distill`` (the LDRM head's raw maps regressed onto a
            teacher LDRM's, low-passed: :func:`training.losses.head_distillation_loss`; a new head learns what an
            older one knew before the rendering losses refine it), ``depth`` (the LDRM's monocular depth network,
            ``ldrm.image_depth``, on every frame of the clips against their metric depth: the scale-invariant log
            loss, λ 0.5, :func:`training.losses.log_depth_loss`).
        scenes: ``static``, ``dynamic`` or ``all`` (ClipDataset filter).
        height, width, num_frames: clip size (pixels, frames T = 1 + 4k).
        render_frames: target frames rendered per clip for the rendering losses (frame 0 always
            included); fewer frames = faster steps.
        scene: what the rendering losses render. ``decoded``: the LDRM's pixel-aligned Gaussians of every source
            frame alone, over black (the paper's LDRM objective, Pan et al. 2025 §3.3: every source frame's
            Gaussians must explain the views, so later frames learn to read their latents). ``assembled``: the scene
            ``generate`` builds (:func:`diff4splat.assembly.assemble.assemble_scene`: the photo layer of frame 0 on the
            predicted depth, the backdrop, the non-redundant later-frame Gaussians over the photo's mean colour),
            where later frames are seen only through disocclusions.
        deformation: predict deformation (times passed to the LDRM); off in static stages.
        motion: motion (track) loss on.
        latent_noise: largest σ of the noise mixed into latent frames 1… before the LDRM sees them,
            x = (1 − σ)·z + σ·ε with σ ~ U(0, latent_noise) per clip (the flow-matching interpolant), so the
            LDRM learns to read imperfect, generated latents; frame 0 (the photo's own latent) stays clean.
            0 = off (ours; Lyra-style training on generated latents costs a sampler run per step).
        weights: loss weights (:class:`training.losses.LossWeights`).
        kl_weight: weight of the VAE KL term (per element, β-VAE style).
        caption_dropout: probability of training the DiT without text (the empty-prompt path).
        flow_shift: timestep shift of the logit-normal training σ of our DiT (a diffusers backbone draws σ its own
            way: :meth:`models.backbone.Backbone.training_sigmas`).
        backbone: ``ours`` (our VAE, text encoder and DiT) or a diffusers backbone (``wan2.2-ti2v``,
            ``cogvideox-i2v``), which ``init_from`` must then hold (a folder with ``model_index.json``). A diffusers
            backbone's ``train`` may list ``dit`` (its transformer through LoRA, plus the camera weights of the
            patch embedding) and the LDRM's parts; its VAE and text encoder stay frozen, and it has no ``vae``
            objective.
        lora: the LoRA adapters of a diffusers backbone's transformer (:class:`LoraSettings`; YAML ``lora:
            {rank: 64, alpha: 64}``); required when such a stage trains ``dit``, refused for ``ours``.
        backbone_dtype: ``float32`` or ``bfloat16``: the dtype a diffusers backbone's frozen weights are loaded and
            kept in (``bfloat16`` halves their memory; it needs ``trainer.bf16``). The trained weights (LoRA,
            camera, LDRM) are float32 either way.
        teacher: the model folder whose LDRM the ``distill`` objective follows (required by it, refused otherwise);
            its own transformer reads the same (noised) latents, so the student's trunk may differ.
        distill_sigma: blur of the teacher's maps in the ``distill`` objective, pixels (≥ 0).
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

    ``"ldrm"`` trains the LDRM without its deformation and motion networks, which train only when named
    (``"ldrm.deformation"``, ``"ldrm.motion"``). (A diffusers
    backbone model's ``"dit"`` is its LoRA and camera weights:
    :func:`training.backbone_training.apply_backbone_freezing`, which calls this for the rest.)

    Returns:
        Trainable parameter count per module name.
    """
    model.requires_grad_(False)
    counts = {}
    for name in train:
        if name == "ldrm":
            skip = tuple(f"{part}." for part in ("deformation", "motion") if f"ldrm.{part}" not in train)
            params = [p for n, p in model.ldrm.named_parameters() if not n.startswith(skip)]
        else:  # an optional part the model does not have (an LDRM without image branch) trains nothing
            parent, _, leaf = name.rpartition(".")
            module = getattr(model.get_submodule(parent), leaf, None) if parent else model.get_submodule(name)
            params = [] if module is None else list(module.parameters())
        for p in params:
            p.requires_grad_(True)
        counts[name] = sum(p.numel() for p in params)
    return counts
