"""The :class:`NetworkRuntime` protocol the pipeline reaches the networks through, and :class:`TorchRuntime`, which
runs PyTorch networks through their :class:`models.backbone.Backbone` (``diff4splat.onnx_runtime.OnnxRuntime`` is
the other runtime).
"""
from __future__ import annotations

import warnings
from collections.abc import Iterator
from contextlib import AbstractContextManager, contextmanager, nullcontext
from dataclasses import fields
from typing import Protocol, runtime_checkable

import torch
from torch import Tensor, nn
from torch.nn.attention import SDPBackend, sdpa_kernel

from diff4splat.utils.devices import cpu_bf16_warning
from diff4splat.utils.offload import ModelOffload, weight_bytes
from models.backbone import LatentFormat
from models.backbone_model import BackboneModel, BackboneModelConfig
from models.bundle import Diff4SplatConfig, Diff4SplatModel
from models.dit import VideoDiT
from models.ldrm import LDRMOutput

__all__ = ["NetworkRuntime", "TorchRuntime", "OFFLOAD_MODES", "check_offload", "DTYPES", "FF_CHUNK_TOKENS",
           "ATTENTION_KERNELS", "check_attention", "attention_priority"]


@runtime_checkable
class NetworkRuntime(Protocol):
    """What the pipeline needs from the networks (batch 1; float32 or ``input_dtype`` tensors in, tensors out).

    Attributes:
        config, latent: the model's config and its VAE's :class:`models.backbone.LatentFormat`.
        has_deformation, has_motion, has_motion_generator: whether :meth:`reconstruct` predicts deformation maps;
            whether :meth:`motion_network` is served; whether :meth:`motion_generator` is.
        encodes_empty_prompt: whether the unconditional input is the empty prompt's embedding rather than no text.
        name, attention, compiled: "torch" or "onnxruntime"; the fused attention kernel tried first
            (:data:`ATTENTION_KERNELS`, None outside torch); whether the blocks are ``torch.compile``-d (meta.json).
        input_dtype: the dtype inputs are cast to; the pipeline makes the Plücker rays in it once.
    """

    config: Diff4SplatConfig | BackboneModelConfig
    latent: LatentFormat
    has_deformation: bool
    has_motion: bool
    has_motion_generator: bool
    encodes_empty_prompt: bool
    name: str
    input_dtype: torch.dtype
    attention: str | None
    compiled: bool

    def sigmas(self, steps: int) -> Tensor:
        """The sampler's σ schedule: (steps + 1,) float64 from 1 to 0."""

    def encode_image(self, video: Tensor) -> Tensor:
        """(1, 3, 1, H, W) pixels in [−1, 1] → (1, c, 1, h, w) DiT-scaled latent (posterior mean)."""

    def encode_text(self, prompt: str) -> tuple[Tensor, Tensor]:
        """Non-empty prompt → tokens (1, L, d_text), mask (1, L) bool. ValueError if it cannot."""

    def velocity(self, x: Tensor, sigma: Tensor, image_latent: Tensor, plucker: Tensor,
                 text: Tensor | None, text_mask: Tensor | None, guidance: float = 1.0,
                 uncond: Tensor | None = None, uncond_mask: Tensor | None = None) -> Tensor:
        """Flow-matching velocity ε − x0: x (1, c, n, h, w), sigma (1,) or 0-dim, image_latent (1, c, 1, h, w),
        plucker (1, 6·t·s², n, h, w), text (1, L, d) + mask (1, L) or None → (1, c, n, h, w) float32. ``guidance``
        g ≠ 1 runs again on ``uncond`` (None: no text) and returns v_u + g·(v − v_u) (Ho & Salimans 2022)."""

    def reconstruct(self, latents: Tensor, plucker: Tensor, times: Tensor | None, image: Tensor) -> LDRMOutput:
        """LDRM (+ deformation when ``times`` (K,) is given) → maps (B, S, H, W, ·); image (1, 3, H, W) in [−1, 1]."""

    def motion_network(self) -> AbstractContextManager[nn.Module]:
        """Context: the LDRM's motion network (:class:`models.motion.MotionNetwork`) on the runtime's device and in its
        dtype for the block, for :func:`diff4splat.assembly.frame_motion.frame_motion`; ValueError where
        ``has_motion`` is False."""

    def motion_generator(self) -> AbstractContextManager[nn.Module]:
        """Context: the motion generator (:class:`models.motion_generator.MotionGenerator`) on the runtime's device
        for the block; ValueError where ``has_motion_generator`` is False."""

    def decode_latents(self, latents: Tensor) -> Tensor:
        """(1, c, n, h, w) DiT-scaled latents → (1, 3, 1 + t·(n − 1), h·s, w·s) pixels in about [−1, 1]."""

    def release(self) -> None:
        """Free what the networks hold on the device (an offloaded network's weights)."""


OFFLOAD_MODES = ("none", "model", "model-prefetch")
"""``offload`` values: every network on the device; in CPU memory, one at a time on the device while it runs
(:class:`diff4splat.utils.offload.ModelOffload`); the same with the DiT copied on a CUDA side stream during its first
call (not with ``compile``; docs/DESIGN.md, "Devices")."""


def check_offload(offload: str, compile: bool) -> None:
    """ValueError for an ``offload`` not in :data:`OFFLOAD_MODES`, or ``model-prefetch`` with ``compile``."""
    if offload not in OFFLOAD_MODES:
        raise ValueError(f"--offload must be one of {OFFLOAD_MODES}, got {offload!r}")
    if offload == "model-prefetch" and compile:
        raise ValueError("--offload model-prefetch does not combine with --compile (its hooks would recompile the "
                         "compiled blocks): use --offload model")


DTYPES = {"float32": torch.float32, "bfloat16": torch.bfloat16, "float16": torch.float16}
"""Weight dtypes a :class:`TorchRuntime` runs in, by name (``generate --dtype``)."""

FF_CHUNK_TOKENS = 8192
"""Our DiT's feed-forward chunk, tokens, while sampling (``VideoDiT.ff_chunk_tokens``): lowers the MLP's activation
peak of the paper-size model; smaller models are one chunk."""

ATTENTION_KERNELS = {"auto": None, "cudnn": SDPBackend.CUDNN_ATTENTION, "flash": SDPBackend.FLASH_ATTENTION,
                     "efficient": SDPBackend.EFFICIENT_ATTENTION, "math": SDPBackend.MATH}
"""``attention`` values (``generate --attention``): the SDPA kernel every network call tries first (``auto``: torch's
own order). The others stay enabled behind it, so every choice runs everywhere, with the same result up to rounding."""

_FALLBACK_ORDER = (SDPBackend.FLASH_ATTENTION, SDPBackend.EFFICIENT_ATTENTION, SDPBackend.CUDNN_ATTENTION,
                   SDPBackend.MATH)  # behind the preferred kernel; math last: it takes every call


def check_attention(attention: object, name: str = "attention") -> None:
    """ValueError (naming ``name``) unless ``attention`` is one of :data:`ATTENTION_KERNELS`."""
    if attention not in ATTENTION_KERNELS:
        raise ValueError(f"{name} must be one of {tuple(ATTENTION_KERNELS)}, got {attention!r}")


def attention_priority(name: str) -> list[SDPBackend] | None:
    """The SDPA kernel order for ``name`` (:data:`ATTENTION_KERNELS`): it, then the others; None for ``auto``.
    ValueError for an unknown name (:func:`check_attention`)."""
    check_attention(name)
    first = ATTENTION_KERNELS[name]
    return None if first is None else [first, *(b for b in _FALLBACK_ORDER if b != first)]


class TorchRuntime:
    """:class:`NetworkRuntime` over PyTorch networks (eval mode) through their :class:`models.backbone.Backbone`.

    Args:
        model: :class:`Diff4SplatModel` or :class:`BackboneModel`; moved to ``device`` (with offload, the CPU) and
            cast to ``dtype`` in place. A backbone's text encoder stays on the CPU and visits the device to encode.
        dtype: weight dtype (float32, bfloat16 or float16; None keeps the model's); outputs are float32.
        offload, attention: one of :data:`OFFLOAD_MODES`, :data:`ATTENTION_KERNELS`.
        compile: ``torch.compile`` the transformer's blocks (:meth:`models.backbone.Backbone.compile_blocks`).

    Raises ValueError for an unknown ``offload`` or ``attention`` or a non-floating ``dtype``; warns (UserWarning) of
    bfloat16 on a CPU whose bfloat16 matmul leaks NaN (:func:`diff4splat.utils.devices.cpu_bf16_warning`).
    """

    name = "torch"
    has_deformation = True

    def __init__(self, model: Diff4SplatModel | BackboneModel, device: str | torch.device = "cpu", *,
                 dtype: torch.dtype | None = None, offload: str = "none", attention: str = "auto",
                 compile: bool = False):
        check_offload(offload, compile)
        check_attention(attention)  # before any model moves
        self.attention = attention
        if dtype is not None and dtype not in DTYPES.values():
            raise ValueError(f"dtype must be one of {sorted(DTYPES)} (torch dtypes), got {dtype!r}")
        self.device = torch.device(device)
        if self.device.type == "cpu" and dtype == torch.bfloat16 and (message := cpu_bf16_warning()):
            warnings.warn(message, stacklevel=2)
        self.model = model.eval() if dtype is None else model.to(dtype).eval()
        self.config = model.config
        self.backbone = model.backbone
        self.velocity_model, self.latent_model = self.backbone.velocity_model, self.backbone.latent_model
        self.text_model = self.backbone.text_model
        self.latent = self.backbone.latent
        self.encodes_empty_prompt = self.backbone.encodes_empty_prompt
        self.networks = model.networks()
        self.dtype = next(self.networks["dit"].parameters()).dtype
        self.input_dtype = self.dtype
        if isinstance(self.networks["dit"], VideoDiT):
            self.networks["dit"].ff_chunk_tokens = FF_CHUNK_TOKENS
        prefetch = {"dit": self.backbone.transformer_blocks()} if offload == "model-prefetch" else None
        self.offload = None if offload == "none" else ModelOffload(self.networks, self.device, prefetch=prefetch)
        # A pretrained backbone's text encoder visits the device only while it encodes.
        self.text_visits = isinstance(model, BackboneModel) and self.offload is None
        if self.offload is None:
            for name, net in self.networks.items():
                net.to("cpu" if self.text_visits and name == "text_encoder" else self.device)
        ldrm = self.networks.get("ldrm")
        self.has_motion = getattr(ldrm, "motion", None) is not None
        self.has_motion_generator = "motion_generator" in self.networks
        self.compiled = bool(compile)
        if self.compiled:
            self.backbone.compile_blocks()

    @contextmanager
    def _use(self, name: str):
        """The network ``name`` on the device for the block (moved back after if offloaded), under the kernel order."""
        order = attention_priority(self.attention)
        with nullcontext() if order is None else sdpa_kernel(order, set_priority=True):
            if self.offload is not None:
                with self.offload.use(name) as net:
                    yield net
            elif name == "text_encoder" and self.text_visits:
                net = self.networks[name].to(self.device)
                try:
                    yield net
                finally:
                    net.to("cpu")
            else:
                yield self.networks[name]

    def host_weight_bytes(self) -> int:
        """Bytes of host memory the weights hold: all on the CPU; the offloaded copies
        (:meth:`diff4splat.utils.offload.ModelOffload.host_bytes`); else a visiting text encoder's, or 0."""
        if self.device.type == "cpu":
            return sum(sum(weight_bytes(net)) for net in self.networks.values())
        if self.offload is not None:
            return self.offload.host_bytes()
        return sum(weight_bytes(self.networks["text_encoder"])) if self.text_visits else 0

    def release(self) -> None:
        """Free the device memory of an offloaded network (nothing without offload)."""
        if self.offload is not None:
            self.offload.release()

    def sigmas(self, steps: int) -> Tensor:
        """(steps + 1,) float64 from 1 to 0 (:meth:`models.backbone.Backbone.sigmas`; ours: the config's shift)."""
        return self.model.backbone.sigmas(steps)  # ours: the config's shift as it is now

    def encode_image(self, video: Tensor) -> Tensor:
        """(B, 3, 1, H, W) in [−1, 1] → (B, c, 1, H/s, W/s) DiT-scaled latent (posterior mean), float32."""
        with self._use("vae"):
            return self.latent_model.encode_latents(video.to(self.dtype)).float()

    def encode_text(self, prompt: str) -> tuple[Tensor, Tensor]:
        """Prompt → tokens (1, L, d_text) float32, mask (1, L) bool on the device (errors of the backbone's); no
        graph (inference: the text model builds one only for training)."""
        with self._use("text_encoder"), torch.no_grad():
            tokens, mask = self.text_model.encode_text([prompt])
        return tokens.float().to(self.device), mask.to(self.device)

    def velocity(self, x: Tensor, sigma: Tensor, image_latent: Tensor, plucker: Tensor, text: Tensor | None,
                 text_mask: Tensor | None, guidance: float = 1.0, uncond: Tensor | None = None,
                 uncond_mask: Tensor | None = None) -> Tensor:
        """:meth:`NetworkRuntime.velocity` by the backbone's velocity network, batch B; inputs cast to the runtime's
        dtype (σ in [0, 1] to float32); the network's ValueError for a wrong shape passes through."""
        dt, net = self.dtype, self.velocity_model
        sigma = (sigma.expand(x.shape[0]) if sigma.dim() == 0 else sigma).float()  # float32: its embedding casts
        x, image_latent, plucker = x.to(dt), image_latent.to(dt), plucker.to(dt)
        with self._use("dit"):
            v = net(x, sigma, image_latent, plucker, None if text is None else text.to(dt), text_mask).float()
            if guidance == 1.0:
                return v
            v_uncond = net(x, sigma, image_latent, plucker, None if uncond is None else uncond.to(dt),
                           uncond_mask).float()
        return v_uncond + guidance * (v - v_uncond)

    def decode_latents(self, latents: Tensor) -> Tensor:
        """(B, c, n, h, w) DiT-scaled latents → (B, 3, 1 + t·(n − 1), h·s, w·s) in about [−1, 1], float32."""
        with self._use("vae"):
            return self.latent_model.decode_latents(latents.to(self.dtype)).float()

    @contextmanager
    def motion_network(self) -> Iterator[nn.Module]:
        """:meth:`NetworkRuntime.motion_network`: the LDRM's, moved to the device for the block if offloaded."""
        if not self.has_motion:
            raise ValueError("this model's LDRM has no motion network (has_motion is False)")
        with self._use("ldrm") as ldrm:
            yield ldrm.motion

    @contextmanager
    def motion_generator(self) -> Iterator[nn.Module]:
        """:meth:`NetworkRuntime.motion_generator`, moved to the device for the block if offloaded."""
        if not self.has_motion_generator:
            raise ValueError("this model has no motion generator (has_motion_generator is False)")
        with self._use("motion_generator") as net:
            yield net

    def reconstruct(self, latents: Tensor, plucker: Tensor, times: Tensor | None, image: Tensor) -> LDRMOutput:
        """:class:`models.ldrm.LDRM` on latents (B, c, n, h, w), plucker (B, 6·t·s², n, h, w), times (K,) in [0, 1]
        or None (static), ``image`` (B, 3, H, W) in [−1, 1] → float32 maps (B, S, H, W, ·) [+ (B, K, S, H, W, ·)].
        The LDRM's ValueError passes through."""
        dt = self.dtype
        with self._use("ldrm") as ldrm:
            # times stay float32 (bfloat16 would round clip times near 1 by up to 2⁻⁹)
            out = ldrm(latents.to(dt), plucker.to(dt), None if times is None else times.float(), image.to(dt))
        return LDRMOutput(**{f.name: None if getattr(out, f.name) is None else getattr(out, f.name).float()
                             for f in fields(out)})
