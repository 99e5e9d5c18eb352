"""The whole Diff4Splat model: video VAE, text encoder, video DiT and LDRM (and, where its config names one, the
motion generator) under one config. A checkpoint folder holds ``config.json`` (:class:`Diff4SplatConfig`) and one
sub-folder per network, each written by its ``save_pretrained``; ``configs/models/<name>.yaml`` files override the
dataclass defaults."""
from __future__ import annotations

import dataclasses
import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import nn

from diff4splat.io.structured import read_json, read_yaml
from diff4splat.utils.config_files import MODEL_CONFIGS

from .backbones.ours import OursBackbone
from .dit import VideoDiT, VideoDiTConfig
from .flow_matching import FlowMatchingConfig
from .ldrm import LDRM, LDRMConfig
from .motion_generator import MotionGenerator, MotionGeneratorConfig
from .pretrained import CONFIG_NAME, check_model_size, config_from_dict, count_parameters, save_model_folder, skip_init
from .text_encoder import TextEncoder, TextEncoderConfig
from .vae import VideoVAE, VideoVAEConfig

__all__ = ["Diff4SplatConfig", "Diff4SplatModel", "load_config", "config_path", "config_names", "CONFIG_DIR",
           "WEIGHTS_DIR", "DEFAULT_CONFIG", "NETWORKS", "OPTIONAL_NETWORKS", "GENERATED_COLORS", "GENERATED_FOOTPRINTS",
           "check_generated",
           "largest_network_bytes", "random_init_device"]

CONFIG_DIR = MODEL_CONFIGS
"""Model size configs (``base``, ``tiny``, ``small``, ``paper``): ``configs/models/``."""
WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"
"""Shipped trained weights, one folder per model name."""
DEFAULT_CONFIG = "base"
"""Name of the model config used when none is named (``generate``, ``export-onnx``, ``evaluate``,
:func:`diff4splat.pipeline.load_model`, training, benchmarks); its shipped weights (``WEIGHTS_DIR / DEFAULT_CONFIG``,
model card ``models/weights/base/MODEL_CARD.md``) are what a plain ``generate`` runs."""

_MODULES = {"vae": VideoVAE, "text_encoder": TextEncoder, "dit": VideoDiT, "ldrm": LDRM,
            "motion_generator": MotionGenerator}
NETWORKS = tuple(_MODULES)
"""The networks' attribute names on :class:`Diff4SplatModel`, in data-flow order."""
OPTIONAL_NETWORKS = ("motion_generator",)
"""Networks a config may leave out (its field None): the model's attribute is then None and its folder absent."""


@dataclass
class Diff4SplatConfig:
    """Top-level configuration: model resolution, default camera and sampling, and the networks.

    Attributes:
        name: model name; names ``models/weights/<name>``.
        height, width: model resolution in pixels (multiples of :attr:`pixel_multiple`).
        num_frames: default clip length T = 1 + 4k.
        fov_y_deg: vertical field of view of the default intrinsics, degrees.
        scene_depth: nominal distance to the scene centre, metres; unit of trajectory amplitudes.
        prune_opacity: Gaussians with opacity below this are pruned from generated scenes.
        static_atol: deformations below this (metres / quaternion / log-scale) count as static.
        generated_colors: colours of source frames 1…'s Gaussians (:data:`GENERATED_COLORS`): ``"ldrm"`` the LDRM's
            maps (the paper, Sec. 3.2), ``"video"`` the decoded video at each pixel
            (:func:`diff4splat.assembly.assemble.video_colors`).
        generated_footprint: their opacity, rotation and scale (:data:`GENERATED_FOOTPRINTS`): ``"ldrm"`` the LDRM's
            maps, ``"pixel"`` opaque disks tiling the source frame
            (:func:`diff4splat.assembly.assemble.pixel_footprint`).
        vae, text_encoder, dit, ldrm, sampling: the networks' and the sampler's configs.
        motion_generator: the motion generator's config (:mod:`models.motion_generator`), or None (no such network).

    Raises:
        ValueError: from :meth:`validate`.
    """

    name: str = "tiny"
    height: int = 64
    width: int = 64
    num_frames: int = 17
    fov_y_deg: float = 50.0
    scene_depth: float = 2.0
    prune_opacity: float = 0.005
    static_atol: float = 1e-6
    generated_colors: str = "ldrm"
    generated_footprint: str = "ldrm"
    vae: VideoVAEConfig = field(default_factory=VideoVAEConfig)
    text_encoder: TextEncoderConfig = field(default_factory=TextEncoderConfig)
    dit: VideoDiTConfig = field(default_factory=lambda: VideoDiTConfig(latent_channels=4, text_dim=64))
    ldrm: LDRMConfig = field(default_factory=LDRMConfig)
    sampling: FlowMatchingConfig = field(default_factory=FlowMatchingConfig)
    motion_generator: MotionGeneratorConfig | None = None

    def __post_init__(self) -> None:
        if isinstance(self.motion_generator, dict):
            self.motion_generator = config_from_dict(MotionGeneratorConfig, self.motion_generator,
                                                     "motion_generator")
        self.validate()

    def validate(self) -> None:
        """Check that the networks fit together; ValueError naming the mismatched fields (latent channels, text width,
        camera channels, VAE compression, resolution, frame count, field of view, depth, generated options)."""
        c = self.vae.latent_channels
        if not (self.dit.latent_channels == c == self.ldrm.latent_channels):
            raise ValueError(f"latent_channels differ: vae {c}, dit {self.dit.latent_channels}, "
                             f"ldrm {self.ldrm.latent_channels}")
        if self.dit.text_dim != self.text_encoder.d_model:
            raise ValueError(f"dit.text_dim ({self.dit.text_dim}) must equal text_encoder.d_model "
                             f"({self.text_encoder.d_model})")
        if (self.ldrm.vae_temporal, self.ldrm.vae_spatial) != (self.vae.temporal_factor, self.vae.spatial_factor):
            raise ValueError(f"ldrm.vae_temporal/vae_spatial ({self.ldrm.vae_temporal}, {self.ldrm.vae_spatial}) "
                             f"must match the VAE ({self.vae.temporal_factor}, {self.vae.spatial_factor})")
        if self.dit.camera_channels != self.ldrm.plucker_channels:
            raise ValueError(f"dit.camera_channels ({self.dit.camera_channels}) must equal "
                             f"6·{self.vae.temporal_factor}·{self.vae.spatial_factor}² = {self.ldrm.plucker_channels}")
        unit = self.pixel_multiple
        for name in ("height", "width"):
            v = getattr(self, name)
            if not isinstance(v, int) or v <= 0 or v % unit:
                raise ValueError(f"{name} must be a positive multiple of {unit} pixels, got {v!r}")
        self.vae.num_latent_frames(self.num_frames)  # raises for T ≠ 1 + 4k
        for name in ("fov_y_deg", "scene_depth"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        check_generated(self)

    @property
    def pixel_multiple(self) -> int:
        """Pixels per side every image size must be a multiple of: VAE spatial factor × the largest DiT/LDRM patch."""
        return self.vae.spatial_factor * max(self.dit.patch_size[1], self.ldrm.patch_size)

    def to_dict(self) -> dict:
        """The config as nested plain dicts (``dataclasses.asdict``), JSON-serialisable: what ``config.json`` and the
        ONNX manifest hold, read back by :func:`models.pretrained.config_from_dict`."""
        return dataclasses.asdict(self)


GENERATED_COLORS = ("ldrm", "video")
"""Values of ``generated_colors``."""
GENERATED_FOOTPRINTS = ("ldrm", "pixel")
"""Values of ``generated_footprint``."""


def check_generated(config: object) -> None:
    """ValueError unless ``config.generated_colors`` is in :data:`GENERATED_COLORS` and ``config.generated_footprint``
    in :data:`GENERATED_FOOTPRINTS`."""
    for name, values in (("generated_colors", GENERATED_COLORS), ("generated_footprint", GENERATED_FOOTPRINTS)):
        if getattr(config, name) not in values:
            raise ValueError(f"{name} must be one of {values}, got {getattr(config, name)!r}")


_KINDS = {str: "string", list: "list", int: "number", float: "number", bool: "boolean"}


def config_names() -> list[str]:
    """Names of the shipped model configs, sorted (``["paper", "small", "tiny"]``)."""
    return sorted(p.stem for p in CONFIG_DIR.glob("*.yaml"))


def config_path(name_or_path: str | os.PathLike) -> Path:
    """The file of a model config: ``configs/models/<name>.yaml`` for a shipped name (which wins over a local
    file), else the given file.

    Raises:
        FileNotFoundError: neither a shipped name nor an existing file (the message lists the names).
        IsADirectoryError: a folder.
    """
    text = os.fspath(name_or_path)
    if text in config_names():
        return CONFIG_DIR / f"{text}.yaml"
    path = Path(text)
    known = ", ".join(config_names())
    if path.is_dir():
        raise IsADirectoryError(f"config: {path} is a folder, not a model config file (YAML or JSON); a model "
                                f"folder is a checkpoint, not a config")
    if not path.is_file():
        if path.suffix or os.sep in text:
            raise FileNotFoundError(f"config: no file {text!r} (or give a shipped config: {known})")
        raise FileNotFoundError(f"config: {text!r} not found (known: {known}) and no file of that name")
    return path


def load_config(name_or_path: str | os.PathLike) -> Diff4SplatConfig:
    """Load a model config by shipped name or from a YAML/JSON file of :class:`Diff4SplatConfig` fields, over the
    defaults; an empty file is the defaults.

    Raises:
        FileNotFoundError, IsADirectoryError: no such config (:func:`config_path`).
        ValueError: naming the file: not UTF-8, not valid YAML/JSON, not a mapping; unknown fields or inconsistent
            networks.
    """
    path = config_path(name_or_path)
    fmt = "JSON" if path.suffix.lower() == ".json" else "YAML"  # not YAML for JSON: YAML 1.1 reads 1e-06 as text
    data = (read_json if fmt == "JSON" else read_yaml)(path, "config", expect=None)
    if data is None:
        data = {}
    if not isinstance(data, dict):
        fields = ", ".join(f.name for f in dataclasses.fields(Diff4SplatConfig)[:4])
        raise ValueError(f"config: {path} is not a model config: it holds a {fmt} "
                         f"{_KINDS.get(type(data), type(data).__name__)}, not a mapping of fields; a model config is a "
                         f"YAML or JSON mapping of fields such as {fields} (see {CONFIG_DIR / 'tiny.yaml'})")
    return config_from_dict(Diff4SplatConfig, data, str(path))


class Diff4SplatModel(nn.Module):
    """The networks of Diff4Splat (Pan et al. 2025, Fig. 2; the motion generator where the config names one) under one
    config."""

    def __init__(self, config: Diff4SplatConfig, *, place: str | torch.device | None = None):
        """Build the networks in :data:`NETWORKS` order (one random stream; an optional network whose config is None
        is None); ``place``: move each there once built."""
        super().__init__()
        self.config = config
        for name, module_cls in _MODULES.items():
            if getattr(config, name) is None:
                setattr(self, name, None)
                continue
            network = module_cls(getattr(config, name))
            setattr(self, name, network if place is None else network.to(place))

    @property
    def backbone(self) -> OursBackbone:
        """The VAE, text encoder and DiT as a :class:`models.backbone.Backbone` view (not a sub-module), with the
        config's sampling shift."""
        s = self.config.sampling
        return OursBackbone(self.vae, self.text_encoder, self.dit, s.shift, (s.logit_normal_mean, s.logit_normal_std))

    def networks(self) -> dict[str, nn.Module]:
        """The networks by name (:data:`NETWORKS`), those the config leaves out omitted."""
        return {name: getattr(self, name) for name in _MODULES if getattr(self, name) is not None}

    def parameter_counts(self) -> dict[str, int]:
        """Parameters per network and in total (works on the meta device)."""
        counts = {name: count_parameters(net) for name, net in self.networks().items()}
        counts["total"] = sum(counts.values())
        return counts

    def save_pretrained(self, directory: str | os.PathLike, *, overwrite: bool = False) -> Path:
        """Write ``config.json`` and one sub-folder per network into ``directory`` (:func:`save_model_folder`:
        atomic, its replacement rules and errors). Returns the directory."""
        def write(folder: Path) -> None:
            (folder / CONFIG_NAME).write_text(json.dumps(self.config.to_dict(), indent=2))
            for name, net in self.networks().items():
                net.write_pretrained(folder / name)

        return save_model_folder(directory, write, overwrite)

    @classmethod
    def from_pretrained(cls, directory: str | os.PathLike, map_location: str = "cpu",
                        dtype: torch.dtype | None = None) -> Diff4SplatModel:
        """Load a folder written by :meth:`save_pretrained`, each network directly in ``dtype`` (None: float32).

        Raises:
            FileNotFoundError: a missing config.json or network sub-folder.
            ValueError: configs that do not fit together or weights that do not match;
                :class:`diff4splat.utils.limits.LimitError` for more parameters than the ``parameters`` limit or weights
                larger than the memory available (counted on the ``meta`` device first).
        """
        directory = Path(directory)
        if not (directory / CONFIG_NAME).is_file():
            raise FileNotFoundError(f"checkpoint: {directory / CONFIG_NAME} does not exist")
        data = read_json(directory / CONFIG_NAME, "checkpoint")
        for name, module_cls in _MODULES.items():  # fields that checkpoints written before they existed lack
            if isinstance(data.get(name), dict):
                data[name] = {**getattr(module_cls.config_class, "SAVED_DEFAULTS", {}), **data[name]}
        config = config_from_dict(Diff4SplatConfig, data, str(directory / CONFIG_NAME))
        check_model_size(lambda: cls(config), str(directory / CONFIG_NAME),  # before any network is built
                         host_dtype=dtype or torch.get_default_dtype() if map_location == "cpu" else None)
        model = cls.__new__(cls)
        nn.Module.__init__(model)
        model.config = config
        for name, module_cls in _MODULES.items():
            if getattr(config, name) is None:
                setattr(model, name, None)
                continue
            sub = module_cls.from_pretrained(directory / name, map_location=map_location, dtype=dtype)
            if sub.config != getattr(config, name):
                raise ValueError(f"checkpoint: {directory / name} config differs from {directory / CONFIG_NAME}")
            setattr(config, name, sub.config)  # one object, as in __init__: edits reach both
            setattr(model, name, sub)
        return model

    @classmethod
    def random(cls, config: Diff4SplatConfig, seed: int = 0, *, device: str | torch.device = "cpu",
               dtype: torch.dtype | None = None, host: bool = False) -> Diff4SplatModel:
        """A randomly initialised model, deterministic for ``seed`` on a given device.

        Args:
            config: the model's configuration.
            seed: seed of ``device``'s generator (values differ between devices).
            device: where the weights are created (a GPU skips the slow CPU initialisation).
            dtype: floating dtype of the weights (None: float32).
            host: move each network to the CPU once built: ``device`` holds one network at a time
                (:func:`largest_network_bytes`).

        Raises:
            LimitError: more parameters than the ``parameters`` limit, or (returned on the CPU) weights larger than the
                memory available (:func:`models.pretrained.check_model_size`).
        """
        device = torch.device(device)
        check_model_size(lambda: cls(config), f"config {config.name!r}",
                         host_dtype=dtype or torch.float32 if device.type == "cpu" or host else None)
        previous = torch.get_default_dtype()
        with torch.random.fork_rng(devices=[device] if device.type == "cuda" else []), device:
            torch.manual_seed(seed)
            try:
                torch.set_default_dtype(dtype or torch.float32)
                model = cls(config, place="cpu" if host else None)
            finally:
                torch.set_default_dtype(previous)
        if host and device.type == "cuda":
            torch.cuda.empty_cache()  # the allocator's cache held the largest network: give it back
        return model


def largest_network_bytes(config: Diff4SplatConfig, dtype: torch.dtype | None = None) -> int:
    """Bytes of the largest network's parameters and buffers in ``dtype`` (None: float32), counted on the ``meta``
    device: what :meth:`Diff4SplatModel.random` with ``host=True`` holds on its device at a time."""
    with torch.device("meta"), skip_init():
        model = Diff4SplatModel(config)
    itemsize = (dtype or torch.float32).itemsize
    return max(sum(t.numel() for t in (*net.parameters(), *net.buffers())) * itemsize
               for net in model.networks().values())


INIT_HEADROOM_BYTES = 1 << 30
"""GPU memory :func:`random_init_device` leaves free beyond the largest network."""


def random_init_device(config: Diff4SplatConfig, device: str | torch.device, dtype: torch.dtype | None = None
                       ) -> torch.device:
    """Where :meth:`Diff4SplatModel.random` (``host=True``) should initialise a model running on ``device``: that CUDA
    device when its free memory holds the largest network plus :data:`INIT_HEADROOM_BYTES`, else the CPU (also when
    the memory cannot be queried). Raises nothing."""
    device = torch.device(device)
    if device.type != "cuda":
        return torch.device("cpu")
    try:
        free, _ = torch.cuda.mem_get_info(device)
    except (RuntimeError, AssertionError):  # a CPU-only build of torch, or no driver
        return torch.device("cpu")
    fits = largest_network_bytes(config, dtype) + INIT_HEADROOM_BYTES <= free
    return device if fits else torch.device("cpu")
