"""Spatiotemporal deformation network of the LDRM (Diff4Splat, Pan et al. 2025, LDRM section).

Canonical features (B, C, h, w) and K times → per-pixel deformation maps (Δμ, Δq, Δs) on the (u·h, u·w) pixel grid,
μ_t = μ + Δμ, q_t = normalize(Δq ⊗ q), s_t = s·exp(Δs) (docs/DESIGN.md "Conventions"). A multi-resolution conv pyramid
is modulated per time by FiLM (Perez et al. 2018) from a NeRF sinusoidal time embedding (Mildenhall et al. 2020
Eq. 4), fused, mapped by a zero-initialised 1×1 conv to 10 raw channels, upsampled bilinearly and activated
(:func:`deformation_activations`). Branch-free on tensor values (ONNX-exportable)."""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from diff4splat.utils.checks import check_number, check_ranges, ranged

from .pretrained import PretrainedMixin
from .tracing import tracing

__all__ = ["DeformationConfig", "DeformationNetwork", "time_embedding", "soft_clamp", "unit_quat_from_raw",
           "deformation_activations", "RAW_DEFORMATION_CHANNELS", "CHUNK_ELEMENTS", "IDENTITY_QUAT"]

RAW_DEFORMATION_CHANNELS = 10
"""Raw output channels: Δμ (3), Δq (4), Δs (3), in this order."""

CHUNK_ELEMENTS = 1 << 24
"""Hidden values (B·k·F·h·w) of one chunk of key times in :meth:`DeformationNetwork.forward` (bounds memory for
long camera paths)."""

IDENTITY_QUAT = (1.0, 0.0, 0.0, 0.0)
"""The rotation Δq of no deformation, wxyz."""


@dataclass
class DeformationConfig:
    """Sizes of :class:`DeformationNetwork` (defaults: the tiny CPU model).

    Attributes:
        in_channels: C, channels of the canonical feature map (the LDRM token width).
        hidden: F, channels of every internal feature map.
        levels: spatial resolutions (1×, ½×, ¼×, …), ≥ 1.
        time_frequencies: L, octaves of the time embedding (2L features).
        max_offset: soft-clamp bound of |Δμ| per axis, metres.
        max_log_scale: soft-clamp bound of |Δs| per axis.

    Raises:
        ValueError: a field out of range.
    """

    in_channels: int = ranged(64)
    hidden: int = ranged(32)
    levels: int = ranged(3)
    time_frequencies: int = ranged(6)
    max_offset: float = ranged(2.0, check_number, lo=0, lo_open=True)
    max_log_scale: float = ranged(3.0, check_number, lo=0, lo_open=True)

    def __post_init__(self) -> None:
        check_ranges("DeformationConfig", self)


def time_embedding(times: Tensor, frequencies: int) -> Tensor:  # times: (K,)
    """γ(t) = (sin(2⁰πt), cos(2⁰πt), …, sin(2^{L−1}πt), cos(2^{L−1}πt)) (NeRF, Mildenhall et al. 2020, Eq. 4):
    ``times`` (K,) in [0, 1] (unchecked) → (K, 2L) in ``times``' dtype."""
    freqs = math.pi * torch.pow(2.0, torch.arange(frequencies, dtype=times.dtype, device=times.device))
    angles = times[:, None] * freqs[None, :]  # (K, L)
    return torch.stack([torch.sin(angles), torch.cos(angles)], dim=-1).reshape(times.shape[0], 2 * frequencies)


def soft_clamp(x: Tensor, bound: float) -> Tensor:
    """``bound · tanh(x / bound)``: slope 1 at 0, values in (−bound, bound), gradients never vanish abruptly."""
    return bound * torch.tanh(x / bound)


def unit_quat_from_raw(raw: Tensor, eps: float = 1e-8) -> Tensor:  # raw: (..., 4)
    """Unit wxyz quaternions ``normalize(raw + (1, 0, 0, 0))`` (..., 4) → (..., 4); zero gives the identity, and a
    norm below ``eps`` gives the identity instead of NaN (branch-free, for ONNX)."""
    identity = raw.new_tensor(IDENTITY_QUAT)
    q = raw + identity
    norm = torch.linalg.vector_norm(q, dim=-1, keepdim=True)
    return torch.where(norm < eps, identity.expand_as(q), q / norm.clamp_min(eps))


def deformation_activations(
    raw: Tensor,  # (..., 10) = Δμ raw (3), Δq raw (4), Δs raw (3)
    max_offset: float,
    max_log_scale: float,
) -> tuple[Tensor, Tensor, Tensor]:
    """Raw (..., 10) → d_means = soft_clamp(raw_μ, max_offset) (..., 3) metres, d_quats =
    :func:`unit_quat_from_raw` (..., 4), d_scales = soft_clamp(raw_s, max_log_scale) (..., 3); zero gives the
    identity."""
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
        self.time_mlp = nn.Sequential(nn.Linear(2 * config.time_frequencies, f), nn.SiLU(),
                                      nn.Linear(f, config.levels * 2 * f))
        self.fuse = nn.Conv2d(f, f, 3, padding=1)
        self.out_conv = nn.Conv2d(f, RAW_DEFORMATION_CHANNELS, 1)
        # Zero-init (as adaLN-Zero): raw output 0 → the identity deformation, training starts from the static scene.
        nn.init.zeros_(self.out_conv.weight)
        nn.init.zeros_(self.out_conv.bias)

    def _raw(self, pyramid: list[Tensor], film: Tensor, upsample: int) -> Tensor:
        """Raw channels (B, k, u·h, u·w, 10) of k key times from the levels (B, F, h, w) and FiLM parameters
        (k, levels, 2, F, 1, 1)."""
        B, _, h, w = pyramid[0].shape
        k = film.shape[0]
        # FiLM after upsampling equals FiLM before (bilinear weights sum to 1); the levels share one sum.
        agg = pyramid[0].new_zeros(())
        for i, feat in enumerate(pyramid):
            gamma, beta = film[:, i, 0], film[:, i, 1]  # (k, F, 1, 1)
            agg = agg + feat[:, None] * (1 + gamma[None]) + beta[None]  # (B, k, F, h, w)
        x = F.gelu(self.fuse(agg.reshape(B * k, self.config.hidden, h, w)))
        # 1×1 conv before bilinear upsampling: the same values (both linear) at u² less cost.
        raw = F.interpolate(self.out_conv(x), scale_factor=upsample, mode="bilinear", align_corners=False)
        return raw.reshape(B, k, RAW_DEFORMATION_CHANNELS, h * upsample, w * upsample).permute(0, 1, 3, 4, 2)

    def forward(self, features: Tensor, times: Tensor, upsample: int) -> tuple[Tensor, Tensor, Tensor]:
        """Deformation maps at K times on the pixel grid (H, W) = (upsample·h, upsample·w), key times in chunks of
        :data:`CHUNK_ELEMENTS` (one chunk while tracing; same values).

        Args:
            features: (B, C, h, w), C = ``in_channels``.
            times: (K,) clip times in [0, 1] (range checked by the LDRM).
            upsample: integer factor from feature to pixel resolution.

        Returns:
            d_means (B, K, H, W, 3) metres, d_quats (B, K, H, W, 4) unit wxyz, d_scales (B, K, H, W, 3) log-scale
            offsets.

        Raises:
            ValueError: ``features`` not (B, C, h, w), ``times`` not (K,), or ``upsample`` < 1.
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
        # The embedding in float32 at least (bfloat16 angles up to 2⁵·π would be off by 0.5 rad), as diffusers.
        emb = time_embedding(times.to(torch.promote_types(times.dtype, torch.float32)), cfg.time_frequencies)
        film = self.time_mlp(emb.to(features.dtype))
        film = film.reshape(K, cfg.levels, 2, cfg.hidden, 1, 1)
        # Key times in chunks of at most CHUNK_ELEMENTS hidden values; one chunk while tracing (K stays symbolic).
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
