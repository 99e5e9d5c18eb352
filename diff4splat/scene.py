"""Dynamic 4D scenes: canonical Gaussians + deformation maps at key times (Diff4Splat §3.2).

A deformation at key time t_k holds, per Gaussian, an offset of the mean Δμ (metres), a rotation
Δq (wxyz, identity (1,0,0,0)) and a log-scale offset Δs. Between key times they are interpolated
linearly (Δq by normalised lerp). The deformed Gaussian (DESIGN.md, "Deformation at time t"):

    μ_t = μ + Δμ(t),    q_t = normalize(Δq(t) ⊗ q),    s_t = s · exp(Δs(t)).

A static scene has no deformation arrays at all: ``at(t)`` returns the canonical Gaussians.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from .gaussians import Gaussians, check_finite
from .quaternions import quat_multiply, quat_nlerp, quat_normalize

__all__ = ["DynamicGaussians"]


@dataclass
class DynamicGaussians:
    """Canonical Gaussians plus optional deformation maps sampled at T key times.

    Attributes:
        canonical: M canonical Gaussians (world frame, metres).
        times: (T,) key times in [0, 1], strictly increasing, or None for a static scene.
        d_means: (T, M, 3) mean offsets, metres, or None.
        d_quats: (T, M, 4) rotation offsets, wxyz (identity (1,0,0,0)), or None.
        d_scales: (T, M, 3) log-scale offsets (s_t = s·exp(Δs)), or None.

    Raises:
        ValueError: deformation arrays given partially, with wrong shapes, non-finite values,
            zero-norm rotations, or times outside [0, 1] / not strictly increasing.
    """

    canonical: Gaussians
    times: Tensor | None = None
    d_means: Tensor | None = None
    d_quats: Tensor | None = None
    d_scales: Tensor | None = None

    def __post_init__(self) -> None:
        parts = (self.times, self.d_means, self.d_quats, self.d_scales)
        if all(p is None for p in parts):
            return
        if any(p is None for p in parts):
            raise ValueError("times, d_means, d_quats and d_scales must be given together (or none of them)")
        T, M = self.times.shape[0], self.canonical.num_gaussians
        if self.times.dim() != 1 or T < 1:
            raise ValueError(f"times must have shape (T,) with T ≥ 1, got {tuple(self.times.shape)}")
        for name, c in (("d_means", 3), ("d_quats", 4), ("d_scales", 3)):
            t = getattr(self, name)
            if tuple(t.shape) != (T, M, c):
                raise ValueError(f"{name} must have shape {(T, M, c)}, got {tuple(t.shape)}")
            check_finite(name, t)
        check_finite("times", self.times)
        if bool(((self.times < 0) | (self.times > 1)).any()):
            raise ValueError(f"times must lie in [0, 1], got {self.times.tolist()}")
        if T > 1 and not bool((self.times[1:] > self.times[:-1]).all()):
            raise ValueError("times must be strictly increasing")
        if M and bool((self.d_quats.norm(dim=-1) < 1e-12).any()):
            raise ValueError("d_quats has a zero-norm quaternion")

    @property
    def is_static(self) -> bool:
        """True when the scene stores no deformation."""
        return self.times is None

    @property
    def num_gaussians(self) -> int:
        return self.canonical.num_gaussians

    def deformation_at(self, t: float) -> tuple[Tensor, Tensor, Tensor]:
        """Interpolated deformation at time ``t``.

        Linear interpolation between the two nearest key times (Δq by shorter-arc nlerp); times before
        the first / after the last key time take the end values.

        Args:
            t: time in [0, 1].

        Returns:
            d_means (M, 3) metres, d_quats (M, 4) unit wxyz, d_scales (M, 3) log-scale offsets.

        Raises:
            ValueError: a static scene, or t outside [0, 1] / not finite.
        """
        if self.is_static:
            raise ValueError("a static scene has no deformation")
        t = _check_time(t)
        times = self.times
        if t <= float(times[0]) or times.shape[0] == 1:
            k, w = 0, 0.0
        elif t >= float(times[-1]):
            k, w = times.shape[0] - 2, 1.0
        else:
            k = int(torch.searchsorted(times, torch.tensor(t, dtype=times.dtype), right=True)) - 1
            w = (t - float(times[k])) / float(times[k + 1] - times[k])
        k1 = min(k + 1, times.shape[0] - 1)
        lerp = lambda a: (1 - w) * a[k] + w * a[k1]  # noqa: E731
        return lerp(self.d_means), quat_nlerp(self.d_quats[k], self.d_quats[k1], w), lerp(self.d_scales)

    def at(self, t: float) -> Gaussians:
        """The Gaussians at time ``t`` ∈ [0, 1] (the canonical ones for a static scene).

        Raises:
            ValueError: t outside [0, 1] or not finite.
        """
        t = _check_time(t)
        g = self.canonical
        if self.is_static:
            return g
        d_means, d_quats, d_scales = self.deformation_at(t)
        return Gaussians(
            means=g.means + d_means,
            quats=quat_multiply(d_quats, quat_normalize(g.quats)),
            scales=g.scales * torch.exp(d_scales),
            opacities=g.opacities,
            sh=g.sh,
        )

    def select(self, index: Tensor) -> "DynamicGaussians":
        """Subset of Gaussians by boolean mask (M,) or indices; deformation arrays follow."""
        if self.is_static:
            return DynamicGaussians(self.canonical.select(index))
        return DynamicGaussians(
            self.canonical.select(index), self.times,
            self.d_means[:, index], self.d_quats[:, index], self.d_scales[:, index],
        )

    def without_deformation(self, atol: float = 0.0) -> "DynamicGaussians":
        """Drop the deformation if it is the identity within ``atol`` (metres / quaternion / log-scale)."""
        if self.is_static:
            return self
        ident = self.d_quats.new_tensor([1.0, 0.0, 0.0, 0.0])
        dq = quat_normalize(self.d_quats, "d_quats")
        dq = torch.where(dq[..., :1] < 0, -dq, dq)
        if (self.d_means.abs().max() <= atol and (dq - ident).abs().max() <= atol
                and self.d_scales.abs().max() <= atol) if self.num_gaussians else True:
            return DynamicGaussians(self.canonical)
        return self

    def to(self, *args, **kwargs) -> "DynamicGaussians":
        if self.is_static:
            return DynamicGaussians(self.canonical.to(*args, **kwargs))
        return DynamicGaussians(self.canonical.to(*args, **kwargs), self.times.to(*args, **kwargs),
                                self.d_means.to(*args, **kwargs), self.d_quats.to(*args, **kwargs),
                                self.d_scales.to(*args, **kwargs))


def _check_time(t: float) -> float:
    t = float(t)
    if not (0.0 <= t <= 1.0):
        raise ValueError(f"time t must lie in [0, 1], got {t}")
    return t
