"""What the two diffusers backbones share: their components, the camera-widened patch embedding, and the Hub
folder layout they are loaded from and saved to (docs/DESIGN.md, "Backbones").

A backbone folder is the diffusers layout of the Hub repositories (``model_index.json``, ``transformer/``,
``vae/``, ``text_encoder/``, ``tokenizer/``, ``scheduler/``: ``Wan-AI/Wan2.2-TI2V-5B-Diffusers``,
``THUDM/CogVideoX-5b-I2V``), loaded by the diffusers pipeline class itself, plus ``camera/model.safetensors``: the
zero-initialised camera weights of the patch embedding (:class:`CameraPatchConv`), absent in a
folder fresh from the Hub (then they start at zero). ``transformer/`` keeps the checkpoint's own key names, so the
folder we write is still loadable by diffusers alone.

This module imports diffusers: it is only imported when a diffusers backbone is used (``diff4splat[diffusers]``).
"""
from __future__ import annotations

import abc
import contextlib
import os
from collections.abc import Iterator
from pathlib import Path
from typing import ClassVar

import torch
import torch.nn.functional as F
from diffusers import DiffusionPipeline
from safetensors.torch import load_file, save_file
from torch import Tensor, nn

from diff4splat.io.structured import read_json

from ..backbone import Backbone, LatentFormat
from ..backbone_model import INDEX_FILE

__all__ = ["DiffusersBackbone", "CameraPatchConv", "CAMERA_FOLDER", "CAMERA_WEIGHTS"]

CAMERA_FOLDER = "camera"
CAMERA_WEIGHTS = "model.safetensors"
"""``camera/model.safetensors``: the patch embedding's camera weights, key ``<patch_conv_path>.camera_weight``."""


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
    """A transformer's patch-embedding convolution widened by ``camera_channels`` input channels whose weights
    start at zero (the authors' code, paulpanwang/Diff4Splat: Plücker rays as extra patch-embedding channels).

    The input is ``cat([x, plucker], dim=1)``: the first ``in_channels`` go through the pretrained ``weight`` and
    ``bias``, the rest through ``camera_weight`` (no bias); the sum is the widened convolution (a convolution is
    linear in its input channels). Kept as two weights so that ``weight``/``bias`` keep the pretrained checkpoint's
    key names (``patch_embedding.weight``; the transformer folder stays loadable by diffusers) and, with
    ``camera_weight`` at zero, the output is the pretrained convolution's bit for bit (adding +0.0).

    Args:
        conv: the pretrained ``nn.Conv2d`` or ``nn.Conv3d`` (kernel = stride, no padding); its parameters are
            taken over, not copied.
        camera_channels: extra input channels (6·t·s²).
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
        """The widened patch embedding: conv(x[:, :in]) + conv_camera(x[:, in:]).

        Args:
            x: (B, in_channels + camera_channels, T, H, W) for a Conv3d, (B, in_channels + camera_channels, H, W)
                for a Conv2d: latents concatenated with packed Plücker rays along dim 1.

        Returns:
            (B, out_channels, T', H', W') or (B, out_channels, H', W'): the pretrained convolution's output size
            (⌊T/k_t⌋, ⌊H/k_h⌋, ⌊W/k_w⌋ for kernel = stride and no padding).

        Raises:
            ValueError: ``x.shape[1]`` ≠ in_channels + camera_channels.
        """
        if x.shape[1] != self.in_channels + self.camera_channels:
            raise ValueError(f"CameraPatchConv: expected {self.in_channels} + {self.camera_channels} channels, "
                             f"got {x.shape[1]}")
        out = self._conv(x[:, :self.in_channels], self.weight, self.bias, self.stride, self.padding)
        return out + self._conv(x[:, self.in_channels:], self.camera_weight, None, self.stride, self.padding)


class DiffusersBackbone(Backbone):
    """A :class:`Backbone` over a diffusers pipeline's components.

    Subclasses set ``pipeline_class`` (the diffusers pipeline whose folder layout and helpers they use),
    ``pipeline_names`` (``_class_name`` values of ``model_index.json`` they accept), ``patch_conv_path`` (the
    transformer's patch-embedding convolution) and ``latent_format(vae)``.

    Args:
        transformer, vae, text_encoder, tokenizer, scheduler: the pipeline's components; the transformer's patch
            embedding is replaced by a :class:`CameraPatchConv` (camera weights zero) in place.
    """

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
        """The VAE's raw latent of ``video``: its posterior's mode (the pipelines' ``retrieve_latents(...,
        sample_mode="argmax")``), or a sample drawn with ``generator``; float32 on the video's device.

        Args:
            video: (B, 3, T, H, W) in [−1, 1], T = 1 + t·k, H and W multiples of the spatial factor s.

        Returns:
            (B, c, n, H/s, W/s) before the backbone's normalisation.

        Raises:
            ValueError: a video of another shape, T ≠ 1 + t·k, or H, W not multiples of s.
        """
        s = self.latent.spatial_factor
        if video.dim() != 5 or video.shape[1] != 3 or video.shape[3] % s or video.shape[4] % s:
            raise ValueError(f"video must be (B, 3, T, H, W) with H, W multiples of {s}, got {tuple(video.shape)}")
        self.latent.num_latent_frames(video.shape[2])
        dist = self.vae.encode(video.to(self.vae.dtype)).latent_dist
        z = dist.mode() if generator is None else dist.sample(generator)
        return z.to(device=video.device, dtype=torch.float32)

    @property
    def velocity_model(self) -> DiffusersBackbone:
        """The backbone itself: its ``forward`` (each subclass's) runs the transformer the way its diffusers pipeline
        does and returns the velocity in our convention (:attr:`models.backbone.Backbone.velocity_model`)."""
        return self

    @property
    def camera_conv(self) -> CameraPatchConv:
        return _get(self.transformer, self.patch_conv_path)

    @contextlib.contextmanager
    def hub_transformer(self) -> Iterator[nn.Module]:
        """The transformer with its pretrained patch embedding back (an ``nn.Conv2d``/``nn.Conv3d`` sharing the
        weights): what diffusers itself would run, for saving in the Hub layout and for comparisons."""
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
        """The diffusers pipeline over these components, the transformer as diffusers runs it (its own patch
        embedding: call inside :meth:`hub_transformer`). ``kwargs``: the pipeline's other arguments."""
        return self.pipeline_class(**self.components(), **kwargs)

    def write_pretrained(self, folder: Path) -> None:
        """Write the Hub layout and ``camera/`` into the existing folder ``folder`` (the caller owns it)."""
        with self.hub_transformer():
            self.pipeline(**self.pipeline_kwargs()).save_pretrained(folder, safe_serialization=True)
        (folder / CAMERA_FOLDER).mkdir(exist_ok=True)
        key = f"{self.patch_conv_path}.camera_weight"
        save_file({key: self.camera_conv.camera_weight.detach().contiguous().cpu()},
                  str(folder / CAMERA_FOLDER / CAMERA_WEIGHTS), metadata={"backbone": self.kind})

    def pipeline_kwargs(self) -> dict:
        """Pipeline arguments other than the components written to ``model_index.json`` (e.g. Wan2.2's
        ``expand_timesteps=True``)."""
        return {}

    @classmethod
    def from_pretrained(cls, directory: str | os.PathLike, torch_dtype: torch.dtype | None = None
                        ) -> DiffusersBackbone:
        """Load a Hub-layout folder (and its ``camera/`` weights when present) from a local path; nothing is
        downloaded.

        Raises:
            FileNotFoundError: no ``model_index.json``.
            ValueError: ``_class_name`` not one of :attr:`pipeline_names` or another check of :meth:`check_index`
                failed; camera weights of the wrong shape.
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
        """Further checks of a folder's ``model_index.json`` (``index``, read from ``path``) before anything loads;
        ValueError naming ``path`` when the folder is not this backbone's. Nothing by default."""

    def transformer_blocks(self) -> list[nn.Module]:
        """The diffusers transformer's blocks in order: its ``transformer_blocks`` (CogVideoX), else its ``blocks``
        (Wan). Each takes hidden states (B, N, D) among other arguments, with the diffusers model's own signature
        (FSDP units, gradient checkpointing, regional compilation)."""
        return list(self.transformer.transformer_blocks if hasattr(self.transformer, "transformer_blocks")
                    else self.transformer.blocks)
