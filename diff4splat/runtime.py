"""How the pipeline reaches the networks: the :class:`NetworkRuntime` protocol, and :class:`TorchRuntime`, which runs
PyTorch networks — our :class:`models.bundle.Diff4SplatModel` or a pretrained diffusers backbone with our LDRM
(:class:`models.backbone_model.BackboneModel`) — through their :class:`models.backbone.Backbone`
(``diff4splat.onnx_runtime.OnnxRuntime`` is the other runtime). Batch 1, float32 tensors in and out.
"""
from __future__ import annotations

import warnings
from contextlib import contextmanager, nullcontext
from dataclasses import fields
from typing import Protocol, runtime_checkable

import torch
from torch import Tensor
from torch.nn.attention import SDPBackend, sdpa_kernel

from diff4splat.assembly.frame_motion import frame_motion
from diff4splat.utils.devices import cpu_bf16_warning
from diff4splat.utils.offload import ModelOffload, weight_bytes
from models.backbone import LatentFormat
from models.backbone_model import BackboneModel, BackboneModelConfig
from models.bundle import Diff4SplatConfig, Diff4SplatModel
from models.dit import VideoDiT
from models.ldrm import LDRMOutput

__all__ = ["NetworkRuntime", "TorchRuntime", "OFFLOAD_MODES", "check_offload", "DTYPES", "FF_CHUNK_TOKENS",
           "ATTENTION_KERNELS", "attention_priority"]


@runtime_checkable
class NetworkRuntime(Protocol):
    """What the pipeline needs from the networks (batch 1, float32 tensors in, or ``input_dtype`` ones; tensors out).

    Attributes:
        config: the model's :class:`Diff4SplatConfig` or :class:`models.backbone_model.BackboneModelConfig`
            (resolution, LDRM, sampling defaults).
        latent: the VAE's :class:`models.backbone.LatentFormat` (channels, temporal and spatial factors).
        has_deformation: whether :meth:`reconstruct` can predict deformation maps (times not None).
        has_motion: whether :meth:`motion` can read the deformation from the frames (an LDRM with a motion network).
        encodes_empty_prompt: whether the transformer needs the empty prompt's text embedding (a pretrained
            backbone's unconditional input) rather than no text at all.
        name: "torch" or "onnxruntime" (written to meta.json).
        input_dtype: the dtype every input is cast to before the networks see it; the pipeline makes its largest
            input, the Plücker rays (1, 6·t·s², n, h, w), in it once instead of holding a float32 copy beside the
            cast of every call (0.33 GB float32 at 49 frames, 512²).
        attention: the fused attention kernel tried first (:data:`ATTENTION_KERNELS`; written to meta.json), None
            for a runtime that does not run torch's attention.
        compiled: whether the transformer's blocks run ``torch.compile``-d
            (:meth:`models.backbone.Backbone.compile_blocks`; written to meta.json).
    """

    config: Diff4SplatConfig | BackboneModelConfig
    latent: LatentFormat
    has_deformation: bool
    has_motion: bool
    encodes_empty_prompt: bool
    name: str
    input_dtype: torch.dtype
    attention: str | None
    compiled: bool

    def sigmas(self, steps: int) -> Tensor:
        """The sampler's σ schedule: (steps + 1,) float64 from 1 to 0
        (:meth:`models.backbone.Backbone.sigmas`)."""

    def encode_image(self, video: Tensor) -> Tensor:
        """(1, 3, 1, H, W) pixels in [−1, 1] → (1, c, 1, h, w) DiT-scaled latent (posterior mean)."""

    def encode_text(self, prompt: str) -> tuple[Tensor, Tensor]:
        """Non-empty prompt → tokens (1, L, d_text), mask (1, L) bool. ValueError if it cannot."""

    def velocity(self, x: Tensor, sigma: Tensor, image_latent: Tensor, plucker: Tensor,
                 text: Tensor | None, text_mask: Tensor | None, guidance: float = 1.0,
                 uncond: Tensor | None = None, uncond_mask: Tensor | None = None) -> Tensor:
        """Flow-matching velocity ε − x0, the network called directly (the sampler's ``velocity_fn`` with the
        conditions bound): x (1, c, n, h, w), sigma (1,) or a 0-dim σ, image_latent (1, c, 1, h, w),
        plucker (1, 6·t·s², n, h, w), text (1, L, d) + mask (1, L) or None → (1, c, n, h, w) float32. With
        ``guidance`` g ≠ 1, classifier-free guidance (Ho & Salimans 2022): the network runs again on the
        unconditional text ``uncond`` + ``uncond_mask`` (None: no text) and the result is v_u + g·(v − v_u)."""

    def reconstruct(self, latents: Tensor, plucker: Tensor, times: Tensor | None, image: Tensor) -> LDRMOutput:
        """LDRM (+ deformation network when ``times`` (K,) is given) → activated maps (B, S, H, W, ·);
        ``image`` (1, 3, H, W) in [−1, 1] is the photograph (used by an LDRM with an image branch)."""

    def motion(self, out: LDRMOutput, frames: Tensor, frame_times: Tensor, viewmats: Tensor, Ks: Tensor,
               sources: Tensor, times: Tensor) -> LDRMOutput:
        """``out`` with its deformation read from the frames (T, 3, H, W) in [0, 1] at the model resolution by the
        LDRM's motion network (:func:`diff4splat.assembly.frame_motion.frame_motion`; cameras (T, 4, 4), (T, 3, 3),
        times (T,), source frame indices (S,), key times (K,))."""

    def decode_latents(self, latents: Tensor) -> Tensor:
        """(1, c, n, h, w) DiT-scaled latents → (1, 3, 1 + t·(n − 1), h·s, w·s) pixels in about [−1, 1] (the VAE
        decoder; :meth:`models.backbone.Backbone.decode_latents`)."""

    def release(self) -> None:
        """The networks are done for this scene: free what they hold on the device (an offloaded network's
        weights), so the pruning renders that follow have the memory."""


OFFLOAD_MODES = ("none", "model", "model-prefetch")
"""``offload`` values: ``none`` keeps every network on the device; ``model`` keeps them in CPU memory and moves
one at a time to the device while it runs (:class:`diff4splat.utils.offload.ModelOffload`); ``model-prefetch`` does the
same and, on CUDA, copies the DiT block by block on a side stream while its first call runs (the copy hides
behind the first sampling step; ``ModelOffload``'s ``prefetch``; not with ``compile``)."""


def check_offload(offload: str, compile: bool) -> None:
    """Raise ValueError for an ``offload`` that is not one of :data:`OFFLOAD_MODES`, or ``model-prefetch`` with
    ``compile`` (a pre-hook added to a ``torch.compile``-d block recompiles it)."""
    if offload not in OFFLOAD_MODES:
        raise ValueError(f"--offload must be one of {OFFLOAD_MODES}, got {offload!r}")
    if offload == "model-prefetch" and compile:
        raise ValueError("--offload model-prefetch does not combine with --compile (its hooks would recompile the "
                         "compiled blocks): use --offload model")


DTYPES = {"float32": torch.float32, "bfloat16": torch.bfloat16, "float16": torch.float16}
"""Weight dtypes a :class:`TorchRuntime` runs in, by name (``generate --dtype``)."""

FF_CHUNK_TOKENS = 8192
"""Our DiT's feed-forward chunk while sampling (``VideoDiT.ff_chunk_tokens``): the paper model's 13,312 tokens
(49 frames, 512²) run its MLP in two halves: the MLP's activation peak 1.38 → 1.04 GB, the step's 1.38 → 1.27 GB
(then self- and cross-attention's; benchmarks/dit_memory.py); smaller models (the shipped base model has 80 tokens)
are one chunk, unchanged."""

ATTENTION_KERNELS = {"auto": None, "cudnn": SDPBackend.CUDNN_ATTENTION, "flash": SDPBackend.FLASH_ATTENTION,
                     "efficient": SDPBackend.EFFICIENT_ATTENTION, "math": SDPBackend.MATH}
"""``attention`` values of a :class:`TorchRuntime` (``generate --attention``): the kernel that every
``F.scaled_dot_product_attention`` of the networks tries first. ``auto`` keeps torch's own order (FlashAttention-2
first on CUDA); ``cudnn`` puts cuDNN's fused attention first, which torch leaves last unless
``TORCH_CUDNN_SDPA_PREFERRED`` is set, and which NVIDIA tunes for Hopper (sm90). The others stay enabled behind the
first, so a kernel that cannot take a call (the CPU has no cuDNN attention; some masks, dtypes or head sizes) hands it
on and every choice runs everywhere. All compute the same attention up to floating-point rounding."""

_FALLBACK_ORDER = (SDPBackend.FLASH_ATTENTION, SDPBackend.EFFICIENT_ATTENTION, SDPBackend.CUDNN_ATTENTION,
                   SDPBackend.MATH)  # behind the preferred kernel; math last: it takes every call


def attention_priority(name: str) -> list[SDPBackend] | None:
    """The SDPA kernel order of ``attention`` value ``name`` (:data:`ATTENTION_KERNELS`): the named kernel, then
    the others; None for ``auto`` (torch's order untouched).

    Raises:
        ValueError: an unknown name.
    """
    if name not in ATTENTION_KERNELS:
        raise ValueError(f"attention must be one of {tuple(ATTENTION_KERNELS)}, got {name!r}")
    first = ATTENTION_KERNELS[name]
    return None if first is None else [first, *(b for b in _FALLBACK_ORDER if b != first)]


class TorchRuntime:
    """:class:`NetworkRuntime` over PyTorch networks (eval mode, no grad): our :class:`Diff4SplatModel` or a
    pretrained diffusers backbone with our LDRM (:class:`models.backbone_model.BackboneModel`), both through their
    :class:`models.backbone.Backbone`.

    Args:
        model: the networks; moved to ``device`` (or, with ``offload="model"``, to the CPU) and cast to
            ``dtype``, in place. A backbone model's text encoder (umT5-XXL / T5-XXL, 11 / 9.5 GB in bf16) stays in
            CPU memory and visits the device only to encode the prompt.
        device: where the networks run.
        dtype: weight dtype (float32, bfloat16 or float16; None keeps the model's). The networks compute in it;
            inputs are cast to it and every output is returned in float32, so the sampler integrates and the
            Gaussians are built in float32 whatever the weights.
        offload: one of :data:`OFFLOAD_MODES`.
        attention: one of :data:`ATTENTION_KERNELS`: the fused attention kernel every network call tries first.
        compile: ``torch.compile`` the transformer's blocks (regional compilation,
            :meth:`models.backbone.Backbone.compile_blocks`): the first sampling step compiles, the later
            ones run fused kernels (``benchmarks/gpu.py`` measures both on a GPU).

    Raises:
        ValueError: an unknown ``offload`` or ``attention``, or a non-floating ``dtype``.

    Warns:
        UserWarning: bfloat16 on a CPU whose bfloat16 matmul leaks NaN across rows
            (:func:`diff4splat.utils.devices.cpu_bf16_warning`).
    """

    name = "torch"
    has_deformation = True

    def __init__(self, model: Diff4SplatModel | BackboneModel, device: str | torch.device = "cpu", *,
                 dtype: torch.dtype | None = None, offload: str = "none", attention: str = "auto",
                 compile: bool = False):
        check_offload(offload, compile)
        attention_priority(attention)  # an unknown name fails here, before any model moves
        self.attention = attention
        if dtype is not None and dtype not in DTYPES.values():
            raise ValueError(f"dtype must be one of {sorted(DTYPES)} (torch dtypes), got {dtype!r}")
        self.device = torch.device(device)
        if self.device.type == "cpu" and dtype == torch.bfloat16 and (message := cpu_bf16_warning()):
            warnings.warn(message, stacklevel=2)
        self.model = model.eval() if dtype is None else model.to(dtype).eval()
        self.config = model.config
        self.backbone = model.backbone
        self.velocity_model = self.backbone.velocity_model  # called directly by :meth:`velocity`
        self.latent = self.backbone.latent
        self.encodes_empty_prompt = self.backbone.encodes_empty_prompt
        self.networks = model.networks()
        self.dtype = next(self.networks["dit"].parameters()).dtype
        self.input_dtype = self.dtype  # velocity and reconstruct cast every input to it
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
        self.compiled = bool(compile)
        if self.compiled:
            self.backbone.compile_blocks()

    @contextmanager
    def _use(self, name: str):
        """The network ``name`` on the device (moved there first with ``offload="model"``, and for a backbone's
        text encoder; moved back after), its attention calls under the runtime's kernel order."""
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
        """Bytes of host memory the weights hold while the runtime runs: every network on the CPU; with model
        offload their CPU copies (:meth:`diff4splat.utils.offload.ModelOffload.host_bytes`: pinned on CUDA, in shared
        blocks each rounded up to a power of two); else a backbone's text encoder, kept on the CPU between visits,
        and nothing more."""
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
        """The sampler's σ schedule: (steps + 1,) float64, decreasing from 1 to 0
        (:meth:`models.backbone.Backbone.sigmas`; ours uses the config's current shift)."""
        return self.model.backbone.sigmas(steps)  # ours: the config's shift as it is now

    def encode_image(self, video: Tensor) -> Tensor:
        """(B, 3, 1, H, W) pixels in [−1, 1] → (B, c, 1, H/s, W/s) DiT-scaled latent (posterior mean), float32
        (:meth:`models.backbone.Backbone.encode_video`, in the runtime's dtype)."""
        with self._use("vae"):
            return self.backbone.encode_video(video.to(self.dtype)).float()

    def encode_text(self, prompt: str) -> tuple[Tensor, Tensor]:
        """Prompt → tokens (1, L, d_text) float32 and mask (1, L) bool, both on the runtime's device
        (:meth:`models.backbone.Backbone.encode_text`, whose errors it passes on)."""
        with self._use("text_encoder"):
            tokens, mask = self.backbone.encode_text([prompt])
        return tokens.float().to(self.device), mask.to(self.device)

    def velocity(self, x: Tensor, sigma: Tensor, image_latent: Tensor, plucker: Tensor, text: Tensor | None,
                 text_mask: Tensor | None, guidance: float = 1.0, uncond: Tensor | None = None,
                 uncond_mask: Tensor | None = None) -> Tensor:
        """Flow-matching velocity ε − x0 by the backbone's velocity network, called directly
        (:attr:`models.backbone.Backbone.velocity_model`): x (B, c, n, h, w), sigma (B,) or a 0-dim σ of the whole
        batch, in [0, 1], image_latent (B, c, 1, h, w), plucker (B, 6·t·s², n, h, w), text (B, L, d_text) and
        text_mask (B, L) bool, or None → (B, c, n, h, w) float32. ``guidance`` g ≠ 1 runs the network a second time
        on ``uncond`` + ``uncond_mask`` (or no text) and returns v_u + g·(v − v_u) (:meth:`NetworkRuntime.velocity`).
        Inputs are cast to the runtime's dtype (σ to float32); the network's ValueError for a wrong shape passes
        through."""
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
        """(B, c, n, h, w) DiT-scaled latents → (B, 3, 1 + t·(n − 1), h·s, w·s) pixels in about [−1, 1], float32
        (:meth:`models.backbone.Backbone.decode_latents`)."""
        with self._use("vae"):
            return self.backbone.decode_latents(latents.to(self.dtype)).float()

    def motion(self, out: LDRMOutput, frames: Tensor, frame_times: Tensor, viewmats: Tensor, Ks: Tensor,
               sources: Tensor, times: Tensor) -> LDRMOutput:
        """:func:`diff4splat.assembly.frame_motion.frame_motion` with the LDRM's motion network, in float32 (the frames,
        cameras and times as :meth:`NetworkRuntime.motion` takes them)."""
        with self._use("ldrm") as ldrm:
            net = ldrm.motion
            dt = next(net.parameters()).dtype
            moved = frame_motion(net, out, frames.to(dt), frame_times.float(), viewmats.float(), Ks.float(), sources,
                                 times.float())
        return LDRMOutput(**{f.name: None if getattr(moved, f.name) is None else getattr(moved, f.name).float()
                             for f in fields(moved)})

    def reconstruct(self, latents: Tensor, plucker: Tensor, times: Tensor | None, image: Tensor) -> LDRMOutput:
        """The LDRM (:class:`models.ldrm.LDRM`) on latents (B, c, n, h, w), plucker (B, 6·t·s², n, h, w), times
        (K,) in [0, 1] (kept float32) or None for a static scene, and the photograph ``image`` (B, 3, H, W) in
        [−1, 1] → :class:`LDRMOutput` of float32 maps (B, S, H, W, ·) for the S source frames, plus deformation
        maps (B, K, S, H, W, ·) when ``times`` is given. The LDRM's ValueError for bad inputs passes through."""
        dt = self.dtype
        with self._use("ldrm") as ldrm:
            # times stay float32 (bfloat16 would round clip times near 1 by up to 2⁻⁹); the deformation network
            # embeds them in float32 and casts the embedding
            out = ldrm(latents.to(dt), plucker.to(dt), None if times is None else times.float(), image.to(dt))
        return LDRMOutput(**{f.name: None if getattr(out, f.name) is None else getattr(out, f.name).float()
                             for f in fields(out)})
