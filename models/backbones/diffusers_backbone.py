"""What the two diffusers backbones share: their components, the camera-widened patch embedding and the Hub folder
layout (docs/DESIGN.md "Backbones"): ``model_index.json``, ``transformer/``, ``vae/``, ``text_encoder/``,
``tokenizer/``, ``scheduler/``, loaded by the diffusers pipeline class, plus ``camera/model.safetensors`` with the
patch embedding's camera weights (zero when absent). Imported only when a diffusers backbone is used."""
from __future__ import annotations

import abc
import contextlib
import os
from collections.abc import Iterator
from pathlib import Path
from typing import ClassVar

import diffusers
import torch
import torch.nn.functional as F
import transformers
from diffusers import DiffusionPipeline
from safetensors.torch import load_file, save_file
from torch import Tensor, nn

from diff4splat.io.structured import read_json

from ..backbone import Backbone, LatentFormat
from ..backbone_model import INDEX_FILE

__all__ = ["DiffusersBackbone", "CameraPatchConv", "CAMERA_FOLDER", "CAMERA_WEIGHTS"]

CAMERA_FOLDER = "camera"
CAMERA_WEIGHTS = "model.safetensors"
"""``camera/model.safetensors``: key ``<patch_conv_path>.camera_weight``."""


def _get(module: nn.Module, path: str) -> nn.Module:
    for name in path.split("."):
        module = getattr(module, name)
    return module


def _set(module: nn.Module, path: str, value: nn.Module) -> None:
    *parents, last = path.split(".")
    for name in parents:
        module = getattr(module, name)
    setattr(module, last, value)


class CameraPatchConv(nn.Module):
    """A patch-embedding convolution widened by ``camera_channels`` input channels whose weights start at zero
    (Plücker rays as extra channels, as the authors' code paulpanwang/Diff4Splat).

    ``cat([x, plucker], 1)``: the first ``in_channels`` go through the pretrained ``weight``/``bias`` (keeping the
    checkpoint's key names), the rest through ``camera_weight``; at zero the output is the pretrained one bit for
    bit.

    Args:
        conv: the pretrained ``nn.Conv2d``/``nn.Conv3d`` (kernel = stride, no padding); its parameters are taken over.
        camera_channels: extra input channels (6·t·s²).

    Raises:
        TypeError: ``conv`` is not a Conv2d/Conv3d.
    """

    def __init__(self, conv: nn.Conv2d | nn.Conv3d, camera_channels: int):
        super().__init__()
        if not isinstance(conv, (nn.Conv2d, nn.Conv3d)):
            raise TypeError(f"conv must be an nn.Conv2d or nn.Conv3d, got {type(conv).__name__}")
        self.in_channels, self.camera_channels = conv.in_channels, camera_channels
        self.stride, self.padding = conv.stride, conv.padding
        self.weight, self.bias = conv.weight, conv.bias
        self._conv = F.conv3d if isinstance(conv, nn.Conv3d) else F.conv2d
        # Zero-init: the pretrained transformer is unchanged until the camera branch is trained.
        shape = (conv.out_channels, camera_channels, *conv.kernel_size)
        self.camera_weight = nn.Parameter(torch.zeros(shape, device=conv.weight.device, dtype=conv.weight.dtype))

    def forward(self, x: Tensor) -> Tensor:  # (B, in + camera, [T,] H, W)
        """(B, in + camera, [T,] H, W) → the pretrained convolution's output (B, out, [T',] H', W').
        ValueError on another channel count."""
        if x.shape[1] != self.in_channels + self.camera_channels:
            raise ValueError(f"CameraPatchConv: expected {self.in_channels} + {self.camera_channels} channels, "
                             f"got {x.shape[1]}")
        out = self._conv(x[:, :self.in_channels], self.weight, self.bias, self.stride, self.padding)
        return out + self._conv(x[:, self.in_channels:], self.camera_weight, None, self.stride, self.padding)


class DiffusersBackbone(Backbone):
    """A :class:`Backbone` over a diffusers pipeline's components; the transformer's patch embedding is replaced in
    place by a :class:`CameraPatchConv`. Subclasses set ``pipeline_class``, ``pipeline_names`` (accepted
    ``_class_name`` values), ``patch_conv_path`` and ``latent_format(vae)``."""

    encodes_empty_prompt = True  # both were trained with T5/umT5("") as the unconditional text
    pipeline_class: ClassVar[type[DiffusionPipeline]]
    pipeline_names: ClassVar[tuple[str, ...]]
    patch_conv_path: ClassVar[str]

    def __init__(self, transformer: nn.Module, vae: nn.Module, text_encoder: nn.Module, tokenizer, scheduler):
        super().__init__()
        self.latent = self.latent_format(vae)
        conv = _get(transformer, self.patch_conv_path)
        if not isinstance(conv, CameraPatchConv):
            _set(transformer, self.patch_conv_path, CameraPatchConv(conv, self.latent.camera_channels))
        self.transformer, self.vae, self.text_encoder = transformer, vae, text_encoder
        self.tokenizer, self.scheduler = tokenizer, scheduler

    @staticmethod
    @abc.abstractmethod
    def latent_format(vae: nn.Module) -> LatentFormat:
        """The :class:`LatentFormat` of ``vae`` (from its diffusers config)."""

    def posterior(self, video: Tensor, generator: torch.Generator | None = None) -> Tensor:
        """The VAE's raw latent (B, c, n, H/s, W/s) float32 of ``video`` (B, 3, T, H, W) in [−1, 1]: the posterior's
        mode, or a sample drawn with ``generator``.

        Raises:
            ValueError: another shape, T ≠ 1 + t·k, or H, W not multiples of s.
        """
        s = self.latent.spatial_factor
        if video.dim() != 5 or video.shape[1] != 3 or video.shape[3] % s or video.shape[4] % s:
            raise ValueError(f"video must be (B, 3, T, H, W) with H, W multiples of {s}, got {tuple(video.shape)}")
        self.latent.num_latent_frames(video.shape[2])
        dist = self.vae.encode(video.to(self.vae.dtype)).latent_dist
        z = dist.mode() if generator is None else dist.sample(generator)
        return z.to(device=video.device, dtype=torch.float32)

    @property
    def latent_model(self) -> DiffusersBackbone:
        """The backbone itself: its ``encode_latents``/``decode_latents`` normalise as the diffusers pipeline does."""
        return self

    @property
    def text_model(self) -> DiffusersBackbone:
        """The backbone itself: its ``encode_text`` runs the diffusers pipeline's ``encode_prompt``."""
        return self

    @property
    def velocity_model(self) -> DiffusersBackbone:
        """The backbone itself: its ``forward`` returns the velocity in our convention."""
        return self

    @property
    def camera_conv(self) -> CameraPatchConv:
        return _get(self.transformer, self.patch_conv_path)

    @contextlib.contextmanager
    def hub_transformer(self) -> Iterator[nn.Module]:
        """Context: the transformer with a plain patch convolution sharing the weights, as diffusers runs and saves
        it."""
        cam = self.camera_conv
        conv_cls = nn.Conv3d if cam.weight.dim() == 5 else nn.Conv2d
        with torch.device("meta"):
            plain = conv_cls(cam.in_channels, cam.weight.shape[0], tuple(cam.weight.shape[2:]), stride=cam.stride,
                             padding=cam.padding, bias=cam.bias is not None)
        plain.weight, plain.bias = cam.weight, cam.bias
        _set(self.transformer, self.patch_conv_path, plain)
        try:
            yield self.transformer
        finally:
            _set(self.transformer, self.patch_conv_path, cam)

    def components(self) -> dict:
        """The pipeline's components by name (the transformer as is)."""
        return {"transformer": self.transformer, "vae": self.vae, "text_encoder": self.text_encoder,
                "tokenizer": self.tokenizer, "scheduler": self.scheduler}

    def pipeline(self, **kwargs) -> DiffusionPipeline:
        """The diffusers pipeline over these components (inside :meth:`hub_transformer`)."""
        return self.pipeline_class(**self.components(), **kwargs)

    def write_pretrained(self, folder: Path) -> None:
        """Write the Hub layout and ``camera/`` into the existing ``folder``."""
        with self.hub_transformer():
            self.pipeline(**self.pipeline_kwargs()).save_pretrained(folder, safe_serialization=True)
        (folder / CAMERA_FOLDER).mkdir(exist_ok=True)
        key = f"{self.patch_conv_path}.camera_weight"
        save_file({key: self.camera_conv.camera_weight.detach().contiguous().cpu()},
                  str(folder / CAMERA_FOLDER / CAMERA_WEIGHTS), metadata={"backbone": self.kind})

    def pipeline_kwargs(self) -> dict:
        """Pipeline arguments other than the components (e.g. Wan2.2's ``expand_timesteps``)."""
        return {}

    @classmethod
    def from_pretrained(cls, directory: str | os.PathLike, torch_dtype: torch.dtype | None = None
                        ) -> DiffusersBackbone:
        """Load a local Hub-layout folder (and its ``camera/`` weights when present); nothing is downloaded.

        Raises:
            FileNotFoundError: no ``model_index.json``.
            ValueError: ``_class_name`` not in :attr:`pipeline_names`, :meth:`check_index` failed, or camera weights of
                the wrong shape.
        """
        directory = Path(directory)
        index = directory / INDEX_FILE
        if not index.is_file():
            raise FileNotFoundError(f"checkpoint: {index} does not exist")
        data = read_json(index, "checkpoint")
        name = data.get("_class_name")
        if name not in cls.pipeline_names:
            raise ValueError(f"checkpoint: {index} is a {name!r} folder; {cls.__name__} loads "
                             f"{', '.join(cls.pipeline_names)}")
        cls.check_index(data, index)
        dtype = {} if torch_dtype is None else {"dtype": torch_dtype}
        with _quiet_loading():
            pipe = cls.pipeline_class.from_pretrained(str(directory), local_files_only=True, **dtype)
        parts = {k: v for k, v in pipe.components.items() if k in ("transformer", "vae", "text_encoder",
                                                                    "tokenizer", "scheduler")}
        backbone = cls(**parts)
        camera = directory / CAMERA_FOLDER / CAMERA_WEIGHTS
        if camera.is_file():
            state = load_file(str(camera))
            key = f"{cls.patch_conv_path}.camera_weight"
            weight = backbone.camera_conv.camera_weight
            if set(state) != {key} or state[key].shape != weight.shape:
                raise ValueError(f"checkpoint: {camera} holds {sorted(state)} "
                                 f"{[tuple(v.shape) for v in state.values()]}, expected {key} {tuple(weight.shape)}")
            with torch.no_grad():
                weight.copy_(state[key])
        return backbone

    @classmethod
    def check_index(cls, index: dict, path: Path) -> None:
        """Further checks of ``model_index.json`` before loading; ValueError naming ``path``. None by default."""

    def transformer_blocks(self) -> list[nn.Module]:
        """The transformer's blocks in order (``transformer_blocks`` for CogVideoX, ``blocks`` for Wan), with the
        diffusers signatures."""
        return list(self.transformer.transformer_blocks if hasattr(self.transformer, "transformer_blocks")
                    else self.transformer.blocks)


@contextlib.contextmanager
def _quiet_loading() -> Iterator[None]:
    """No progress bars of diffusers or transformers while a pipeline loads from local files (a command's ``--quiet``
    is quiet, and a local load takes seconds); each library's setting is put back after."""
    libraries = (diffusers.utils.logging, transformers.utils.logging)
    bars = [lib.is_progress_bar_enabled() for lib in libraries]
    for lib in libraries:
        lib.disable_progress_bar()
    try:
        yield
    finally:
        for lib, enabled in zip(libraries, bars, strict=True):
            if enabled:
                lib.enable_progress_bar()
