"""Dynamic 4D scenes: canonical Gaussians + deformation at key times (Diff4Splat §3.2; docs/DESIGN.md, "Deformation
at time t").

Per Gaussian and key time: Δμ (metres), Δq (wxyz, identity (1, 0, 0, 0)) and a log-scale offset Δs, interpolated
linearly between key times (Δq by nlerp): μ_t = μ + Δμ(t), q_t = normalize(Δq(t) ⊗ q), s_t = s·exp(Δs(t)).
Optional temporal support: opacity at t is o·p(t). By default p(t) = exp(−½((t − μ_t)/σ_t)²) (Yang et al., ICLR 2024,
§3.2; unnormalised as in the authors' code); with ramps r_t it is the trapezoid p(t) = clamp((σ_t − |t − μ_t|)/r_t,
0, 1): 1 within σ_t − r_t of μ_t, 0 from σ_t on, a box open at its ends when r_t = 0 (the layers of ``reconstruct``,
which cross-fade exactly; docs/DESIGN.md, "Motion measured from frames …"). Gaussians with o·p(t) below the gate
(:data:`~diff4splat.utils.constants.ALPHA_MIN`) cannot pass the alpha test and are left out before projection.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from diff4splat.scene.gaussians import Gaussians, _unchecked
from diff4splat.scene.quaternions import quat_multiply, quat_nlerp, quat_normalize, quat_norms
from diff4splat.utils.checks import check_finite
from diff4splat.utils.constants import ALPHA_MIN

__all__ = ["DynamicGaussians", "compose_deformation", "distinct_rows"]


def compose_deformation(
    means: Tensor,  # (..., 3) metres
    quats: Tensor,  # (..., 4) wxyz, unnormalised
    scales: Tensor,  # (..., 3) metres, > 0
    d_means: Tensor,  # (..., 3) metres
    d_quats: Tensor,  # (..., 4) wxyz, identity (1, 0, 0, 0), unnormalised
    d_scales: Tensor,  # (..., 3) log-scale offsets
) -> tuple[Tensor, Tensor, Tensor]:
    """Apply a deformation: μ_t = μ + Δμ, q_t = normalize(Δq ⊗ normalize(q)), s_t = s·exp(Δs); differentiable.

    Returns:
        means (..., 3), unit quats (..., 4), scales (..., 3).

    Raises:
        ValueError: a zero-norm quaternion in ``quats`` or ``d_quats``.
    """
    q = quat_multiply(quat_normalize(d_quats, "d_quats"), quat_normalize(quats, "quats"))
    return means + d_means, q, scales * torch.exp(d_scales)


@dataclass
class DynamicGaussians:
    """Canonical Gaussians (M, world frame, metres) plus optional deformation at T key times ``times`` ((T,) in [0, 1],
    strictly increasing, or None for a static scene): ``d_means`` (T, M, 3) metres, ``d_quats`` (T, M, 4) wxyz,
    ``d_scales`` (T, M, 3) log-scale offsets; and optional temporal support, ``t_means`` (M,) clip times and
    ``t_scales`` (M,) > 0, given together (a Gaussian's σ_t, or with ``t_ramps`` (M,) ≥ 0 a trapezoid's half-width
    at zero; module docstring).

    Raises:
        ValueError: deformation arrays given partially, with wrong shapes, non-finite values, zero-norm rotations,
            or times outside [0, 1] / not strictly increasing; t_means/t_scales given alone, t_ramps without them,
            any of the three not (M,) or non-finite, t_scales ≤ 0, t_ramps < 0 or > t_scales.
    """

    canonical: Gaussians
    times: Tensor | None = None
    d_means: Tensor | None = None
    d_quats: Tensor | None = None
    d_scales: Tensor | None = None
    t_means: Tensor | None = None
    t_scales: Tensor | None = None
    t_ramps: Tensor | None = None

    def __post_init__(self) -> None:
        self._check_temporal()
        parts = (self.times, self.d_means, self.d_quats, self.d_scales)
        if all(p is None for p in parts):
            return
        if any(p is None for p in parts):
            raise ValueError("times, d_means, d_quats and d_scales must be given together (or none of them)")
        if self.times.dim() != 1 or self.times.shape[0] < 1:
            raise ValueError(f"times must have shape (T,) with T ≥ 1, got {tuple(self.times.shape)}")
        T, M = self.times.shape[0], self.canonical.num_gaussians
        for name, c in (("d_means", 3), ("d_quats", 4), ("d_scales", 3)):
            t = getattr(self, name)
            if tuple(t.shape) != (T, M, c):
                raise ValueError(f"{name} must have shape {(T, M, c)}, got {tuple(t.shape)}")
            check_finite(name, distinct_rows(t))
        check_finite("times", self.times)
        if bool(((self.times < 0) | (self.times > 1)).any()):
            raise ValueError(f"times must lie in [0, 1], got {self.times.tolist()}")
        if T > 1 and not bool((self.times[1:] > self.times[:-1]).all()):
            raise ValueError("times must be strictly increasing")
        quat_norms(distinct_rows(self.d_quats), "d_quats")  # zero norm → ValueError naming d_quats

    def _check_temporal(self) -> None:
        if self.t_means is None and self.t_scales is None:
            if self.t_ramps is not None:
                raise ValueError("t_ramps needs t_means and t_scales")
            return
        if self.t_means is None or self.t_scales is None:
            raise ValueError("t_means and t_scales must be given together (or neither)")
        M = self.canonical.num_gaussians
        for name in ("t_means", "t_scales") + (() if self.t_ramps is None else ("t_ramps",)):
            t = getattr(self, name)
            if tuple(t.shape) != (M,):
                raise ValueError(f"{name} must have shape ({M},) (one per Gaussian), got {tuple(t.shape)}")
            check_finite(name, t)
        if M and bool((self.t_scales <= 0).any()):
            raise ValueError(f"t_scales must be > 0, min is {float(self.t_scales.min())}")
        if M and self.t_ramps is not None and bool(((self.t_ramps < 0) | (self.t_ramps > self.t_scales)).any()):
            raise ValueError("t_ramps must lie in [0, t_scales]")

    @property
    def is_static(self) -> bool:
        """True when the scene stores no deformation (temporal support may still be present)."""
        return self.times is None

    @property
    def has_temporal(self) -> bool:
        """True when the Gaussians have temporal support (t_means, t_scales)."""
        return self.t_means is not None

    @property
    def changes_with_time(self) -> bool:
        """True when :meth:`at` depends on t: the scene deforms or has temporal support."""
        return not self.is_static or self.has_temporal

    def temporal_opacity(self, t: float) -> Tensor:
        """(M,) p(t) in [0, 1] (module docstring: the Gaussian, or the trapezoid with ``t_ramps``), ones without
        temporal support; ValueError for t outside [0, 1] or not finite."""
        t = _check_time(t)
        if not self.has_temporal:
            return torch.ones_like(self.canonical.opacities)
        if self.t_ramps is None:
            return torch.exp(-0.5 * ((t - self.t_means) / self.t_scales) ** 2)
        inside = self.t_scales - (t - self.t_means).abs()  # ≤ 0 outside the support
        ramp = (inside / self.t_ramps.clamp(min=torch.finfo(inside.dtype).tiny)).clamp(0, 1)
        return torch.where(self.t_ramps > 0, ramp, (inside > 0).to(inside.dtype))

    def active_indices(self, t: float, gate: float = ALPHA_MIN) -> Tensor | None:
        """(K,) int64 ascending indices of the Gaussians with o·p(t) ≥ ``gate`` (≥ 0), or None without temporal support
        (``gate`` ≤ 1/255 leaves the image unchanged); ValueError for t outside [0, 1] / not finite, or gate < 0."""
        if not gate >= 0:
            raise ValueError(f"gate must be >= 0, got {gate}")
        if not self.has_temporal:
            _check_time(t)
            return None
        op = self.canonical.opacities.detach() * self.temporal_opacity(t).detach()
        return torch.nonzero(op >= gate).squeeze(1)

    @property
    def num_gaussians(self) -> int:
        """M, the number of canonical Gaussians."""
        return self.canonical.num_gaussians

    def deformation_at(self, t: float, index: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
        """Deformation at time ``t`` ∈ [0, 1] of the Gaussians ``index`` ((K,) indices or (M,) bool; None: all),
        interpolated between the key times around it (Δq by shorter-arc nlerp; end values outside the key range):
        d_means (K, 3) metres, d_quats (K, 4) unit wxyz, d_scales (K, 3) log-scale offsets.

        Raises:
            ValueError: a static scene, or t outside [0, 1] / not finite.
        """
        if self.is_static:
            raise ValueError("a static scene has no deformation")
        k, k1, w = self._keys(_check_time(t))
        key = (lambda a, j: a[j]) if index is None else (lambda a, j: a[j][index])  # noqa: E731
        lerp = lambda a: (1 - w) * key(a, k) + w * key(a, k1)  # noqa: E731
        return (lerp(self.d_means), quat_nlerp(key(self.d_quats, k), key(self.d_quats, k1), w),
                lerp(self.d_scales))

    def _keys(self, t: float) -> tuple[int, int, float]:
        """(k, k1, w): the key times around ``t`` and the weight of k1 (t clamped to the key range)."""
        times = self.times
        if t <= float(times[0]) or times.shape[0] == 1:
            k, w = 0, 0.0
        elif t >= float(times[-1]):
            k, w = times.shape[0] - 2, 1.0
        else:
            k = int(torch.searchsorted(times, torch.tensor(t, dtype=times.dtype, device=times.device), right=True)) - 1
            w = (t - float(times[k])) / float(times[k + 1] - times[k])
        return k, min(k + 1, times.shape[0] - 1), w

    def at(self, t: float, gate: float = ALPHA_MIN, index: Tensor | None = None) -> Gaussians:
        """The Gaussians at time ``t`` ∈ [0, 1] (the canonical ones for a static scene).

        With temporal support, opacities are o·p(t) and only the Gaussians of :meth:`active_indices` (``gate``) are
        returned, in index order. ``index`` ((K,) ascending int64 or (M,) bool): only these Gaussians, as ``at(t,
        gate)`` then a selection. Only the deformed scales are checked again (they can overflow).

        Raises:
            ValueError: t outside [0, 1] or not finite, gate < 0; a deformed scale that is not finite and > 0.
        """
        t = _check_time(t)
        if not gate >= 0:
            raise ValueError(f"gate must be >= 0, got {gate}")
        p = self.temporal_opacity(t) if self.has_temporal else None  # (M,)
        idx = None if index is None else torch.nonzero(index).squeeze(1) if index.dtype == torch.bool else index
        if p is not None and gate > 0:  # the gate of active_indices, on the Gaussians of ``index`` only
            o = self.canonical.opacities.detach() if idx is None else self.canonical.opacities.detach()[idx]
            keep = o * (p if idx is None else p[idx]).detach() >= gate
            idx = torch.nonzero(keep).squeeze(1) if idx is None else idx[keep]
        fused = None if self.is_static else self._at_fused(t, idx)
        if fused is not None:
            c = self.canonical
            opacities, sh = (c.opacities, c.sh) if idx is None else (c.opacities[idx], c.sh[idx])
            if p is not None:
                opacities = opacities * (p if idx is None else p[idx])
            return _unchecked(Gaussians, {"means": fused[0], "quats": fused[1], "scales": fused[2],
                                          "opacities": opacities, "sh": sh})
        g = self.canonical if idx is None else self.canonical.select(idx)
        if p is not None:
            g = _unchecked(Gaussians, {"means": g.means, "quats": g.quats, "scales": g.scales, "sh": g.sh,
                                       "opacities": g.opacities * (p if idx is None else p[idx])})  # o·p ∈ [0, 1]
        if self.is_static:
            return g
        # the two key times around t, gathered for the active Gaussians only (not every key time of a select)
        means, quats, scales = compose_deformation(g.means, g.quats, g.scales, *self.deformation_at(t, idx))
        check_finite("scales", scales)
        if scales.numel() and not bool((scales > 0).all()):
            raise ValueError(f"deformed scales must be > 0 metres at t = {t} (a log-scale offset underflows)")
        return _unchecked(Gaussians, {"means": means, "quats": quats, "scales": scales, "opacities": g.opacities,
                                      "sh": g.sh})

    def _at_fused(self, t: float, idx: Tensor | None) -> tuple[Tensor, Tensor, Tensor] | None:
        """:meth:`at`'s deformed means, quats, scales of ``idx`` by the numba kernel, or None: run the reference."""
        c = self.canonical
        tensors = (c.means, c.quats, c.scales, self.d_means, self.d_quats, self.d_scales)
        if (any(x.device.type != "cpu" for x in tensors)
                or (torch.is_grad_enabled() and any(x.requires_grad for x in tensors))
                or len({x.dtype for x in tensors}) != 1 or c.means.dtype not in (torch.float32, torch.float64)):
            return None
        kernel = _deform_kernel()
        if kernel is None:
            return None
        k, k1, w = self._keys(t)
        dev = c.means.device
        index = torch.arange(c.num_gaussians, device=dev) if idx is None else idx.long()
        n = index.shape[0]
        out = (c.means.new_empty(n, 3), c.means.new_empty(n, 4), c.means.new_empty(n, 3))
        bad = torch.zeros(n, dtype=torch.bool, device=dev)
        host = lambda x: _host_rows(x.detach().cpu())  # noqa: E731  device: CPU by contract (checked above)
        kernel(host(index), host(c.means), host(c.quats), host(c.scales), host(self.d_means[k]),
               host(self.d_quats[k]), host(self.d_scales[k]), host(self.d_means[k1]), host(self.d_quats[k1]),
               host(self.d_scales[k1]), float(w), *(host(o) for o in out), host(bad))
        return None if bool(bad.any()) else out

    def select(self, index: Tensor) -> DynamicGaussians:
        """Subset by boolean mask (M,) or indices; deformation and temporal arrays follow (not validated again)."""
        values = {"canonical": self.canonical.select(index), "times": self.times}
        if self.has_temporal:
            values.update(t_means=self.t_means[index], t_scales=self.t_scales[index],
                          t_ramps=None if self.t_ramps is None else self.t_ramps[index])
        if not self.is_static:
            n = values["canonical"].num_gaussians
            values.update({k: _select_rows(getattr(self, k), index, n) for k in ("d_means", "d_quats", "d_scales")})
        return _unchecked(DynamicGaussians, values)

    def without_deformation(self, atol: float = 0.0) -> DynamicGaussians:
        """Drop the deformation if it is the identity within ``atol`` (metres / quaternion / log-scale)."""
        if self.is_static:
            return self
        if self.num_gaussians and not (_within(distinct_rows(self.d_means), atol)
                                       and _within(distinct_rows(self.d_scales), atol)
                                       and _identity_rotations(distinct_rows(self.d_quats), atol)):
            return self
        return DynamicGaussians(self.canonical, t_means=self.t_means, t_scales=self.t_scales, t_ramps=self.t_ramps)

    def to(self, *args, **kwargs) -> DynamicGaussians:
        """Move/cast every tensor, temporal arrays included (``Tensor.to`` arguments)."""
        mv = lambda x: None if x is None else x.to(*args, **kwargs)  # noqa: E731
        return DynamicGaussians(self.canonical.to(*args, **kwargs), mv(self.times), mv(self.d_means),
                                mv(self.d_quats), mv(self.d_scales), mv(self.t_means), mv(self.t_scales),
                                mv(self.t_ramps))


_UNSET = object()
_KERNEL = [_UNSET]


def distinct_rows(x: Tensor) -> Tensor:
    """``x`` (K, M, c), or its first row (K, 1, c) when it repeats one row for every Gaussian (stride 0, as
    ``reconstruct``'s identity rotations and scales): a reduction over the Gaussians gives the same on either, and
    reads K·c values instead of K·M·c."""
    return x[:, :1] if x.shape[1] > 0 and x.stride(1) == 0 else x


def _select_rows(x: Tensor, index: Tensor, n: int) -> Tensor:
    """``x[:, index]`` (K, n, c); a view when ``x`` (K, M, c) repeats one row for every Gaussian (stride 0, as
    ``reconstruct``'s identity rotations and scales), which indexing would copy K·n·c times over."""
    rows = distinct_rows(x)
    return rows.expand(x.shape[0], n, x.shape[2]) if rows is not x else x[:, index]


def _host_rows(x: Tensor) -> np.ndarray:
    """A CPU tensor as the kernel's array: a key's rows shared by every Gaussian (stride 0) stay one row in memory,
    anything else contiguous."""
    shared = x.dim() == 2 and x.shape[0] > 1 and x.stride(0) == 0
    return (x if shared else x.contiguous()).numpy()  # device: a CPU tensor (the caller's .cpu())


def _deform_kernel():
    """:func:`diff4splat.scene.kernels.deform` (imported on first use), or None without numba."""
    if _KERNEL[0] is _UNSET:
        try:
            from diff4splat.scene.kernels import deform  # lazy: numba's import time; absent → the PyTorch reference
        except ImportError:
            deform = None
        _KERNEL[0] = deform
    return _KERNEL[0]


def _within(x: Tensor, atol: float) -> bool:
    """max |x| ≤ atol, without an |x| copy."""
    lo, hi = torch.aminmax(x)
    return bool(torch.maximum(-lo, hi) <= atol)


def _identity_rotations(quats: Tensor, atol: float) -> bool:
    """Every (..., 4) quaternion, normalised and sign-fixed to w ≥ 0, within ``atol`` of (1, 0, 0, 0) per component."""
    norm = quat_norms(quats, "d_quats")
    return (_within(quats[..., 0].abs() / norm - 1, atol)
            and all(_within(quats[..., i] / norm, atol) for i in (1, 2, 3)))


def _check_time(t: float) -> float:
    t = float(t)
    if not (0.0 <= t <= 1.0):
        raise ValueError(f"time t must lie in [0, 1], got {t}")
    return t
