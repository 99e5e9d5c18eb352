"""Spatiotemporal deformation network of the LDRM (Diff4Splat, Pan et al. 2025, LDRM section).

Given canonical latent features of the reference frame and query times, it predicts per-pixel
deformation maps (Δμ, Δq, Δs) that move the pixel-aligned canonical Gaussians to each time
(docs/DESIGN.md: μ_t = μ + Δμ(t); q_t = normalize(Δq(t) ⊗ q); s_t = s · exp(Δs(t))).

Pipeline (shapes for B scenes, K times, features (B, C, h, w), pixel grid H = u·h, W = u·w):

1. ``in_conv`` 3×3: (B, C, h, w) → level 0 (B, F, h, w); strided 3×3 convs give levels at
   ½×, ¼×, … resolution ("aggregates multi-resolution spatial features").
2. Time t → NeRF-style sinusoidal embedding (Mildenhall et al. 2020, Eq. 4) → MLP → per-level
   FiLM parameters (γ, β) (Perez et al. 2018): f_{l,k} = up(f_l) · (1 + γ_{l,k}) + β_{l,k},
   summed over levels → (B, K, F, h, w).
3. ``fuse`` 3×3 conv + GELU, the zero-initialised 1×1 ``out_conv`` to 10 raw channels, bilinear
   upsampling by ``u`` to (H, W), then the output activations (:func:`deformation_activations`).

The network is only run for dynamic scenes: the LDRM skips it when no times are asked for.
Everything is branch-free on tensor values so the module exports with ``torch.onnx`` (dynamo).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .pretrained import PretrainedMixin
from .tracing import tracing

__all__ = [
    "DeformationConfig",
    "DeformationNetwork",
    "time_embedding",
    "soft_clamp",
    "unit_quat_from_raw",
    "deformation_activations",
    "RAW_DEFORMATION_CHANNELS",
    "CHUNK_ELEMENTS",
    "IDENTITY_QUAT",
]

RAW_DEFORMATION_CHANNELS = 10
"""Raw output channels: Δμ (3), Δq (4), Δs (3), in this order."""

CHUNK_ELEMENTS = 1 << 24
"""Hidden values (B · k · F · h · w) of one chunk of key times in :meth:`DeformationNetwork.forward`: 64 MiB in
float32, a few times that with the conv's output and GELU (ours: bounds memory for long camera paths)."""

IDENTITY_QUAT = (1.0, 0.0, 0.0, 0.0)
"""The rotation Δq of no deformation, wxyz: what the heads add their output to (zero-init → identity)."""


@dataclass
class DeformationConfig:
    """Sizes of :class:`DeformationNetwork` (defaults: the tiny CPU model).

    Attributes:
        in_channels: C, channels of the canonical feature map (= the LDRM token width).
        hidden: F, channels of every internal feature map.
        levels: number of spatial resolutions (1×, ½×, ¼×, … ), ≥ 1.
        time_frequencies: L, sinusoid octaves of the time embedding (2L features).
        max_offset: bound of |Δμ| per axis, metres (soft clamp, see :func:`soft_clamp`).
        max_log_scale: bound of |Δs| per axis (log-scale offset; e^{±bound} scale factor).
    """

    in_channels: int = 64
    hidden: int = 32
    levels: int = 3
    time_frequencies: int = 6
    max_offset: float = 2.0
    max_log_scale: float = 3.0

    def __post_init__(self) -> None:
        for name in ("in_channels", "hidden", "levels", "time_frequencies"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"DeformationConfig.{name} must be ≥ 1, got {getattr(self, name)}")
        for name in ("max_offset", "max_log_scale"):
            if not float(getattr(self, name)) > 0:
                raise ValueError(f"DeformationConfig.{name} must be > 0, got {getattr(self, name)}")


def time_embedding(times: Tensor, frequencies: int) -> Tensor:  # times: (K,)
    """Sinusoidal embedding of clip times (NeRF positional encoding, Mildenhall et al. 2020, Eq. 4).

    γ(t) = (sin(2⁰πt), cos(2⁰πt), …, sin(2^{L−1}πt), cos(2^{L−1}πt)); frequencies 2^k·π suit
    t ∈ [0, 1] (the lowest octave spans half a period over the clip, so t = 0 and t = 1 differ).

    Args:
        times: (K,) clip times in [0, 1] (not checked here; the LDRM validates them).
        frequencies: L ≥ 1.

    Returns:
        (K, 2L) features in [−1, 1], same dtype as ``times``.
    """
    freqs = math.pi * torch.pow(2.0, torch.arange(frequencies, dtype=times.dtype, device=times.device))
    angles = times[:, None] * freqs[None, :]  # (K, L)
    return torch.stack([torch.sin(angles), torch.cos(angles)], dim=-1).reshape(times.shape[0], 2 * frequencies)


def soft_clamp(x: Tensor, bound: float) -> Tensor:
    """Smooth clamp ``bound · tanh(x / bound)``: slope 1 at 0, values in (−bound, bound), finite for any x.

    Used instead of a hard clamp so gradients never vanish abruptly (our choice).
    """
    return bound * torch.tanh(x / bound)


def unit_quat_from_raw(raw: Tensor, eps: float = 1e-8) -> Tensor:  # raw: (..., 4)
    """Unit wxyz quaternion ``normalize(raw + (1, 0, 0, 0))`` for a network head.

    A zero raw output gives exactly the identity rotation (1, 0, 0, 0). Branch-free so that it
    traces for ONNX: where the sum has norm < ``eps`` (raw ≈ (−1, 0, 0, 0), orientation undefined)
    the identity is returned instead of NaN. (``diff4splat.scene.quaternions.quat_normalize`` raises on
    zero norm, a data-dependent check a traced network head cannot contain.)

    Args:
        raw: (..., 4) any real values (finite).

    Returns:
        (..., 4) unit quaternions, wxyz.
    """
    identity = raw.new_tensor(IDENTITY_QUAT)
    q = raw + identity
    norm = torch.linalg.vector_norm(q, dim=-1, keepdim=True)
    return torch.where(norm < eps, identity.expand_as(q), q / norm.clamp_min(eps))


def deformation_activations(
    raw: Tensor,  # (..., 10) = Δμ raw (3), Δq raw (4), Δs raw (3)
    max_offset: float,
    max_log_scale: float,
) -> tuple[Tensor, Tensor, Tensor]:
    """Map raw deformation channels to (Δμ, Δq, Δs); a zero input gives exactly the identity.

    Δμ = max_offset · tanh(raw_μ / max_offset)      metres, in (−max_offset, max_offset)
    Δq = normalize(raw_q + (1, 0, 0, 0))            unit wxyz (see :func:`unit_quat_from_raw`)
    Δs = max_log_scale · tanh(raw_s / max_log_scale) log-scale offset, s_t = s · exp(Δs)

    Returns:
        d_means (..., 3), d_quats (..., 4), d_scales (..., 3); finite for any finite raw input.
    """
    raw_mu, raw_q, raw_s = raw.split([3, 4, 3], dim=-1)
    return soft_clamp(raw_mu, max_offset), unit_quat_from_raw(raw_q), soft_clamp(raw_s, max_log_scale)


class DeformationNetwork(nn.Module, PretrainedMixin):
    """Time-conditioned multi-resolution CNN predicting per-pixel Gaussian deformation maps."""

    config_class = DeformationConfig

    def __init__(self, config: DeformationConfig) -> None:
        super().__init__()
        self.config = config
        c, f = config.in_channels, config.hidden
        self.in_conv = nn.Conv2d(c, f, 3, padding=1)
        self.down = nn.ModuleList(nn.Conv2d(f, f, 3, stride=2, padding=1) for _ in range(config.levels - 1))
        self.time_mlp = nn.Sequential(
            nn.Linear(2 * config.time_frequencies, f),
            nn.SiLU(),
            nn.Linear(f, config.levels * 2 * f),
        )
        self.fuse = nn.Conv2d(f, f, 3, padding=1)
        self.out_conv = nn.Conv2d(f, RAW_DEFORMATION_CHANNELS, 1)
        # Zero-init of the last layer (weights AND bias): its raw output is exactly 0 for any input,
        # and the activations map 0 to the identity deformation — Δμ = 0, Δq = normalize(0 + (1,0,0,0))
        # = (1,0,0,0), Δs = 0 so s_t = s·exp(0) = s. Training therefore starts from the static
        # canonical scene and learns motion as a residual (as adaLN-Zero in DiT, Peebles & Xie 2023).
        # Gradients still reach out_conv (its input features are non-zero), so it leaves zero at step 1.
        nn.init.zeros_(self.out_conv.weight)
        nn.init.zeros_(self.out_conv.bias)

    def _raw(self, pyramid: list[Tensor], film: Tensor, upsample: int) -> Tensor:
        """Raw channels (B, k, u·h, u·w, 10) of k key times from the levels (each (B, F, h, w)) and their FiLM
        parameters (k, levels, 2, F, 1, 1)."""
        B, _, h, w = pyramid[0].shape
        k = film.shape[0]
        # Per-time FiLM: bilinear weights sum to 1, so up(f)·(1+γ)+β = up(f·(1+γ)+β); modulating
        # after upsampling is the same and lets the levels share one (B, k, F, h, w) sum.
        agg = pyramid[0].new_zeros(())
        for i, feat in enumerate(pyramid):
            gamma, beta = film[:, i, 0], film[:, i, 1]  # (k, F, 1, 1)
            agg = agg + feat[:, None] * (1 + gamma[None]) + beta[None]  # (B, k, F, h, w)
        x = F.gelu(self.fuse(agg.reshape(B * k, self.config.hidden, h, w)))
        # 1×1 conv then bilinear upsampling equals upsampling then the 1×1 conv (both linear,
        # bilinear weights sum to 1 so the bias commutes too) at u² less cost.
        raw = F.interpolate(self.out_conv(x), scale_factor=upsample, mode="bilinear", align_corners=False)
        return raw.reshape(B, k, RAW_DEFORMATION_CHANNELS, h * upsample, w * upsample).permute(0, 1, 3, 4, 2)

    def forward(
        self,
        features: Tensor,  # (B, C, h, w) canonical features of the reference latent frame
        times: Tensor,  # (K,) in [0, 1]
        upsample: int,
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Deformation maps at K times on the pixel grid (H, W) = (upsample·h, upsample·w).

        Args:
            features: (B, C, h, w), C = ``config.in_channels``.
            times: (K,) clip times in [0, 1], K ≥ 1 (validated by the caller, the LDRM).
            upsample: integer factor from feature to pixel resolution (8·patch for the LDRM).

        Returns:
            d_means: (B, K, H, W, 3) metres, |·| < max_offset.
            d_quats: (B, K, H, W, 4) unit wxyz; identity (1, 0, 0, 0) = no rotation.
            d_scales: (B, K, H, W, 3) log-scale offsets, |·| < max_log_scale.

        Raises:
            ValueError: ``features`` not (B, C, h, w) with C = in_channels, ``times`` not (K,),
                or ``upsample`` < 1.
        """
        cfg = self.config
        if features.dim() != 4 or features.shape[1] != cfg.in_channels:
            raise ValueError(f"features must have shape (B, {cfg.in_channels}, h, w), got {tuple(features.shape)}")
        if times.dim() != 1:
            raise ValueError(f"times must have shape (K,), got {tuple(times.shape)}")
        if int(upsample) < 1:
            raise ValueError(f"upsample must be a positive integer, got {upsample}")
        B, _, h, w = features.shape
        K = times.shape[0]
        # Multi-resolution pyramid, each level brought back to (h, w).
        level = F.gelu(self.in_conv(features))
        pyramid = [level]
        for down in self.down:
            level = F.gelu(down(level))
            pyramid.append(F.interpolate(level, size=(h, w), mode="bilinear", align_corners=False))
        # The embedding in float32 at least, then the network's dtype (diffusers' timestep embeddings do the same):
        # in bfloat16 the top octave's angles (up to 2⁵·π rad) would be off by up to 0.5 rad.
        emb = time_embedding(times.to(torch.promote_types(times.dtype, torch.float32)), cfg.time_frequencies)
        film = self.time_mlp(emb.to(features.dtype))
        film = film.reshape(K, cfg.levels, 2, cfg.hidden, 1, 1)
        # The (B, k, F, h, w) hidden maps are the network's largest tensors: key times go through in chunks of at
        # most CHUNK_ELEMENTS hidden values, each written into the outputs, so memory grows with K only through the
        # 10 output channels. One chunk while tracing (the exported graph keeps K symbolic). Chunking changes no
        # value: each key time is computed on its own.
        k = K if tracing() else max(1, CHUNK_ELEMENTS // (B * cfg.hidden * h * w))
        u = int(upsample)
        if k >= K:
            return deformation_activations(self._raw(pyramid, film, u), cfg.max_offset, cfg.max_log_scale)
        outs = tuple(features.new_empty(B, K, h * u, w * u, c) for c in (3, 4, 3))
        for i in range(0, K, k):
            parts = deformation_activations(self._raw(pyramid, film[i:i + k], u), cfg.max_offset, cfg.max_log_scale)
            for out, part in zip(outs, parts, strict=True):
                out[:, i:i + k] = part
        return outs
