"""A pretrained diffusers backbone with our LDRM: the model ``generate --checkpoint DIR`` runs for a diffusers folder.

The folder is the backbone's Hub layout (:mod:`models.backbones.diffusers_backbone`) plus our ``camera/``, ``ldrm/``
and ``diff4splat.json`` (:class:`BackboneModelConfig`); fresh from the Hub it has none of ours (camera weights zero,
:data:`DEFAULTS`, a random LDRM with a warning). Only :func:`backbone_class` imports diffusers."""
from __future__ import annotations

import dataclasses
import importlib
import json
import logging
import os
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import nn

from diff4splat.io.structured import read_json
from diff4splat.utils.checks import MissingExtraError

from .backbone import Backbone, LatentFormat
from .bundle import Diff4SplatConfig, check_generated
from .flow_matching import FlowMatchingConfig
from .ldrm import LDRM, LDRMConfig
from .pretrained import (
    CONFIG_NAME,
    WEIGHTS_NAME,
    check_model_size,
    config_from_dict,
    count_parameters,
    save_model_folder,
)

__all__ = ["BackboneModel", "BackboneModelConfig", "backbone_class", "folder_backbone", "DEFAULTS",
           "CONFIG_FILE", "INDEX_FILE", "PIPELINES"]

CONFIG_FILE = "diff4splat.json"
INDEX_FILE = "model_index.json"
"""The file that makes a folder a diffusers pipeline (the Hub layout of a backbone)."""
LDRM_FOLDER = "ldrm"

PIPELINES = {"WanPipeline": "wan2.2-ti2v", "WanImageToVideoPipeline": "wan2.2-ti2v",
             "CogVideoXImageToVideoPipeline": "cogvideox-i2v"}
"""``model_index.json`` ``_class_name`` → backbone kind."""
_MODULES = {"wan2.2-ti2v": ("models.backbones.wan", "WanBackbone"),
            "cogvideox-i2v": ("models.backbones.cogvideox", "CogVideoXBackbone")}

DEFAULTS = {
    # Wan2.2-TI2V-5B: 1280×704, 121 frames at 24 fps (Wan-Video/Wan2.2 README and its diffusers example).
    "wan2.2-ti2v": dict(name="wan2.2-ti2v-5b", height=704, width=1280, num_frames=121, guidance=5.0),
    # CogVideoX-5B-I2V: 720×480, 49 frames at 8 fps (THUDM/CogVideoX-5b-I2V model card).
    "cogvideox-i2v": dict(name="cogvideox-5b-i2v", height=480, width=720, num_frames=49, guidance=6.0),
}
"""Resolution, clip length and guidance scale of each backbone as released (README / model card, diffusers'
default ``guidance_scale``): what a folder without ``diff4splat.json`` uses."""


@dataclass
class BackboneModelConfig:
    """A backbone model's configuration (``diff4splat.json``): the fields of :class:`models.bundle.Diff4SplatConfig`
    the pipeline reads, with the backbone in place of our VAE, text encoder and DiT.

    Attributes:
        name: model name.
        backbone: a kind of :data:`PIPELINES`.
        height, width: model resolution, pixels (multiples of the VAE's spatial factor × the patch sizes).
        num_frames: default clip length T = 1 + 4k.
        fov_y_deg, scene_depth, prune_opacity, static_atol, generated_colors, generated_footprint: as
            :class:`models.bundle.Diff4SplatConfig`.
        vae: the backbone VAE's :class:`LatentFormat` (must agree with the loaded VAE).
        ldrm: the LDRM's config on those latents; the paper's sizes by default.
        sampling: ``steps`` and ``sampler``; ``shift`` is informational (:meth:`Backbone.sigmas` decides).

    Raises:
        ValueError: an unknown backbone, an LDRM that does not match ``vae``, or a bad size.
    """

    name: str = "wan2.2-ti2v-5b"
    backbone: str = "wan2.2-ti2v"
    height: int = 704
    width: int = 1280
    num_frames: int = 121
    fov_y_deg: float = Diff4SplatConfig.fov_y_deg  # one home: our model's defaults
    scene_depth: float = Diff4SplatConfig.scene_depth
    prune_opacity: float = Diff4SplatConfig.prune_opacity
    static_atol: float = Diff4SplatConfig.static_atol
    generated_colors: str = Diff4SplatConfig.generated_colors
    generated_footprint: str = Diff4SplatConfig.generated_footprint
    vae: LatentFormat = field(default_factory=lambda: LatentFormat(48, 4, 16))
    ldrm: LDRMConfig = field(default_factory=LDRMConfig.paper)
    sampling: FlowMatchingConfig = field(default_factory=lambda: FlowMatchingConfig(steps=50))

    def __post_init__(self) -> None:
        if isinstance(self.vae, dict):
            self.vae = LatentFormat(**self.vae)
        if self.backbone not in _MODULES:
            raise ValueError(f"backbone must be one of {sorted(_MODULES)}, got {self.backbone!r}")
        v, ld = self.vae, self.ldrm
        if (ld.latent_channels, ld.vae_temporal, ld.vae_spatial) != (v.latent_channels, v.temporal_factor,
                                                                     v.spatial_factor):
            raise ValueError(f"ldrm (latent_channels, vae_temporal, vae_spatial) = ({ld.latent_channels}, "
                             f"{ld.vae_temporal}, {ld.vae_spatial}) must match the backbone VAE's "
                             f"({v.latent_channels}, {v.temporal_factor}, {v.spatial_factor})")
        unit = v.spatial_factor * max(2, ld.patch_size)  # the transformers' 2×2 patches
        for name in ("height", "width"):
            value = getattr(self, name)
            if not isinstance(value, int) or value <= 0 or value % unit:
                raise ValueError(f"{name} must be a positive multiple of {unit} pixels, got {value!r}")
        v.num_latent_frames(self.num_frames)
        check_generated(self)

    @classmethod
    def for_backbone(cls, kind: str, latent: LatentFormat, **overrides) -> BackboneModelConfig:
        """The released defaults of backbone ``kind`` (:data:`DEFAULTS`) on ``latent``, the paper's LDRM sizes."""
        ldrm = dataclasses.replace(LDRMConfig.paper(), latent_channels=latent.latent_channels,
                                   vae_temporal=latent.temporal_factor, vae_spatial=latent.spatial_factor)
        released = dict(DEFAULTS[kind])
        sampling = FlowMatchingConfig(steps=50, guidance=released.pop("guidance"))
        return cls(**{**released, "backbone": kind, "vae": latent, "ldrm": ldrm, "sampling": sampling, **overrides})

    def to_dict(self) -> dict:
        """The config as nested plain dicts (``dataclasses.asdict``), JSON-serialisable."""
        return dataclasses.asdict(self)


def folder_backbone(directory: str | os.PathLike) -> str:
    """The backbone kind of a diffusers folder, from ``model_index.json``'s ``_class_name``.

    Raises:
        FileNotFoundError: no ``model_index.json``.
        ValueError: an unreadable index or a pipeline not in :data:`PIPELINES`.
    """
    return _read_index(directory)[1]


def _read_index(directory: str | os.PathLike) -> tuple[dict, str]:
    """(``model_index.json``'s contents, the backbone kind it names); raises as :func:`folder_backbone`."""
    index = Path(directory) / INDEX_FILE
    if not index.is_file():
        raise FileNotFoundError(f"checkpoint: {index} does not exist")
    data = read_json(index, "checkpoint")
    name = data.get("_class_name")
    if name not in PIPELINES:
        raise ValueError(f"checkpoint: {index} is a {name!r} folder; diff4splat runs {', '.join(sorted(PIPELINES))}")
    return data, PIPELINES[name]


def check_backbone_folder(directory: str | os.PathLike) -> tuple[str, BackboneModelConfig | None]:
    """Check a diffusers backbone folder before anything is imported or loaded: the index names a known pipeline,
    every component folder holds its config (each a JSON object), a model's (``config.json``) its weights, a
    ``diff4splat.json`` describes this backbone with an LDRM within the ``parameters`` limit, an ``ldrm/`` holds its
    config and weights. Returns (kind, the ``diff4splat.json`` config or None).

    Raises:
        FileNotFoundError: no index, a component folder, its config or a model's weights missing, ``ldrm/`` without
            its files.
        ValueError: an unreadable index, component config or ``diff4splat.json``, another pipeline or backbone;
            :class:`diff4splat.utils.limits.LimitError` for an LDRM above the limit.
    """
    directory = Path(directory)
    index, kind = _read_index(directory)
    for name, value in index.items():
        if name.startswith("_") or not (isinstance(value, list) and len(value) == 2) or value[0] is None:
            continue  # "_class_name", "_diffusers_version", settings, components left out (None)
        folder = directory / name
        if not folder.is_dir():
            raise FileNotFoundError(f"checkpoint: {directory} has no {name}/ folder, which {INDEX_FILE} names "
                                    f"({value[0]}.{value[1]})")
        configs = sorted(folder.glob("*config*.json"))
        if not configs:
            raise FileNotFoundError(f"checkpoint: {folder} holds no config file (config.json, scheduler_config.json, "
                                    f"tokenizer_config.json) for its {value[1]}")
        for file in configs:
            if not isinstance(read_json(file, "checkpoint"), dict):
                raise ValueError(f"checkpoint: {file} is not a JSON object")
        if (folder / "config.json").is_file() and not any(
                f for pattern in ("*.safetensors", "*.bin") for f in folder.glob(pattern)):
            raise FileNotFoundError(f"checkpoint: {folder} holds no weights (*.safetensors, *.bin) for its "
                                    f"{value[1]}")
    config = None
    if (directory / CONFIG_FILE).is_file():
        where = str(directory / CONFIG_FILE)
        config = config_from_dict(BackboneModelConfig, read_json(directory / CONFIG_FILE, "checkpoint"), where)
        if config.backbone != kind:
            raise ValueError(f"checkpoint: {where} describes a {config.backbone} backbone; the folder holds a {kind}")
        check_model_size(lambda: LDRM(config.ldrm), f"{where} (ldrm)")
    if (directory / LDRM_FOLDER).is_dir():
        missing = [f for f in (CONFIG_NAME, WEIGHTS_NAME) if not (directory / LDRM_FOLDER / f).is_file()]
        if missing:
            raise FileNotFoundError(f"checkpoint: {directory / LDRM_FOLDER} lacks {', '.join(missing)}")
    return kind, config


def backbone_class(kind: str) -> type[Backbone]:
    """The :class:`Backbone` subclass of ``kind``, imported on demand (with diffusers).

    Raises:
        ValueError: an unknown kind.
        MissingExtraError: diffusers or transformers missing.
    """
    if kind not in _MODULES:
        raise ValueError(f"backbone must be one of {sorted(_MODULES)}, got {kind!r}")
    module, name = _MODULES[kind]
    # transformers' import notes at error level meanwhile: diffusers' pipelines import classes the backbones never use,
    # and transformers notes each missing optional backend (CLIPImageProcessor "requires torchvision") on stderr (its
    # own logger: transformers resets its root logger's level when it is first imported)
    notes = logging.getLogger("transformers.utils.import_utils")
    level = notes.level
    notes.setLevel(logging.ERROR)
    try:
        return getattr(importlib.import_module(module), name)
    except ModuleNotFoundError as e:
        raise MissingExtraError(f"the {kind} backbone needs {e.name}: pip install 'diff4splat[diffusers]'") from None
    finally:
        notes.setLevel(level)


class BackboneModel(nn.Module):
    """A diffusers backbone and our LDRM under one :class:`BackboneModelConfig` (``config.vae`` must equal
    ``backbone.latent``; ValueError otherwise)."""

    def __init__(self, backbone: Backbone, ldrm: LDRM, config: BackboneModelConfig):
        super().__init__()
        if backbone.latent != config.vae:
            raise ValueError(f"config.vae {config.vae} differs from the backbone's {backbone.latent}")
        self.backbone, self.ldrm, self.config = backbone, ldrm, config

    def networks(self) -> dict[str, nn.Module]:
        """The networks by the pipeline's names: ``vae``, ``text_encoder``, ``dit`` (the transformer), ``ldrm``."""
        b = self.backbone
        return {"vae": b.vae, "text_encoder": b.text_encoder, "dit": b.transformer, "ldrm": self.ldrm}

    def parameter_counts(self) -> dict[str, int]:
        """Parameters per network and in total (works on the meta device)."""
        counts = {name: count_parameters(net) for name, net in self.networks().items()}
        counts["total"] = sum(counts.values())
        return counts

    def save_pretrained(self, directory: str | os.PathLike, *, overwrite: bool = False) -> Path:
        """Write the Hub layout, ``camera/``, ``ldrm/`` and ``diff4splat.json`` into ``directory``
        (:func:`~models.pretrained.save_model_folder`: atomic, its replacement rules and errors)."""
        def write(folder: Path) -> None:
            self.backbone.write_pretrained(folder)
            self.ldrm.write_pretrained(folder / LDRM_FOLDER)
            (folder / CONFIG_FILE).write_text(json.dumps(self.config.to_dict(), indent=2))

        return save_model_folder(directory, write, overwrite)

    @classmethod
    def from_pretrained(cls, directory: str | os.PathLike, torch_dtype: torch.dtype | None = None,
                        seed: int = 0) -> BackboneModel:
        """Load a local backbone folder (nothing is downloaded) in ``torch_dtype`` (None: as saved); a folder without
        ``ldrm/`` gets a random LDRM from ``seed``, with a warning.

        Raises:
            FileNotFoundError, ValueError: from :func:`check_backbone_folder`, before diffusers is imported; a
                ``diff4splat.json`` or ``ldrm/`` that does not fit the backbone.
            MissingExtraError: diffusers missing.
        """
        directory = Path(directory)
        kind, config = check_backbone_folder(directory)
        backbone = backbone_class(kind).from_pretrained(directory, torch_dtype=torch_dtype)
        if config is None:
            config = BackboneModelConfig.for_backbone(kind, backbone.latent)
        elif config.vae != backbone.latent:
            raise ValueError(f"checkpoint: {directory / CONFIG_FILE} describes a {config.backbone} backbone with "
                             f"{config.vae}; the folder holds a {kind} with {backbone.latent}")
        if (directory / LDRM_FOLDER).is_dir():
            ldrm = LDRM.from_pretrained(directory / LDRM_FOLDER)
            if ldrm.config != config.ldrm:
                raise ValueError(f"checkpoint: {directory / LDRM_FOLDER} config differs from {directory / CONFIG_FILE}")
        else:
            warnings.warn(f"{directory} has no {LDRM_FOLDER}/: using a randomly initialised LDRM (seed {seed}); "
                          f"train it (docs/DESIGN.md, 'Backbones') before judging its scenes", stacklevel=2)
            with torch.random.fork_rng(devices=[]):
                torch.manual_seed(seed)
                ldrm = LDRM(config.ldrm)
        if torch_dtype is not None:
            ldrm = ldrm.to(torch_dtype)
        return cls(backbone, ldrm, config)
