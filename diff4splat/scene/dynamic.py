"""Dynamic 4D scenes: canonical Gaussians + deformation maps at key times (Diff4Splat §3.2).

A deformation at key time t_k holds, per Gaussian, an offset of the mean Δμ (metres), a rotation
Δq (wxyz, identity (1,0,0,0)) and a log-scale offset Δs. Between key times they are interpolated
linearly (Δq by normalised lerp). The deformed Gaussian (docs/DESIGN.md, "Deformation at time t"):

    μ_t = μ + Δμ(t),    q_t = normalize(Δq(t) ⊗ q),    s_t = s · exp(Δs(t)).

A static scene has no deformation arrays at all: ``at(t)`` returns the canonical Gaussians.

Optional temporal support (4D Gaussians, Yang et al. 2024, "Real-time Photorealistic Dynamic Scene
Representation and Rendering with 4D Gaussian Splatting", ICLR, §3.2): each Gaussian has a time
mean μ_t and time scale σ_t, and its opacity at time t is multiplied by the marginal of its 4D
Gaussian along time, p(t) = exp(−½((t − μ_t)/σ_t)²). The marginal is left unnormalised (peak 1 at
t = μ_t, no 1/(σ_t√(2π)) factor), as in the authors' code (``exp(-0.5 (t - mu_t)² / cov_t)``), so
a Gaussian is exactly as opaque as its canonical opacity at its own time. Gaussians whose opacity
o·p(t) is below a threshold (default :data:`diff4splat.utils.constants.ALPHA_MIN` = 1/255, the 3DGS alpha
cut-off, so gating is exact) can never pass the renderer's
alpha test (alpha ≤ o·p(t)), so ``at(t)`` leaves them out before projection (temporal gating): the
image is unchanged and they cost nothing.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from diff4splat.scene.gaussians import Gaussians, _unchecked
from diff4splat.scene.quaternions import quat_multiply, quat_nlerp, quat_normalize, quat_norms
from diff4splat.utils.checks import check_finite
from diff4splat.utils.constants import ALPHA_MIN

__all__ = ["DynamicGaussians", "compose_deformation"]


def compose_deformation(
    means: Tensor,  # (..., 3) metres
    quats: Tensor,  # (..., 4) wxyz, unnormalised
    scales: Tensor,  # (..., 3) metres, > 0
    d_means: Tensor,  # (..., 3) metres
    d_quats: Tensor,  # (..., 4) wxyz, identity (1, 0, 0, 0), unnormalised
    d_scales: Tensor,  # (..., 3) log-scale offsets
) -> tuple[Tensor, Tensor, Tensor]:
    """Apply a deformation to Gaussians (docs/DESIGN.md, "Conventions": deformation at time t).

    μ_t = μ + Δμ,  q_t = normalize(Δq ⊗ normalize(q)),  s_t = s·exp(Δs). Differentiable; the one place
    the composition is written (``DynamicGaussians.at`` and ``fit`` call it).

    Returns:
        means (..., 3), unit quats (..., 4), scales (..., 3).

    Raises:
        ValueError: a zero-norm quaternion in ``quats`` or ``d_quats``.
    """
    q = quat_multiply(quat_normalize(d_quats, "d_quats"), quat_normalize(quats, "quats"))
    return means + d_means, q, scales * torch.exp(d_scales)


@dataclass
class DynamicGaussians:
    """Canonical Gaussians plus optional deformation maps sampled at T key times.

    Attributes:
        canonical: M canonical Gaussians (world frame, metres).
        times: (T,) key times in [0, 1], strictly increasing, or None for a static scene.
        d_means: (T, M, 3) mean offsets, metres, or None.
        d_quats: (T, M, 4) rotation offsets, wxyz (identity (1,0,0,0)), or None.
        d_scales: (T, M, 3) log-scale offsets (s_t = s·exp(Δs)), or None.
        t_means: (M,) time mean μ_t of each Gaussian (clip time, any real; [0, 1] spans the clip), or None.
        t_scales: (M,) time standard deviation σ_t > 0 (clip time), or None. Given together with
            ``t_means``; without them every Gaussian exists at every time.

    Raises:
        ValueError: deformation arrays given partially, with wrong shapes, non-finite values,
            zero-norm rotations, or times outside [0, 1] / not strictly increasing; t_means/t_scales
            given alone, not of shape (M,), non-finite, or t_scales ≤ 0.
    """

    canonical: Gaussians
    times: Tensor | None = None
    d_means: Tensor | None = None
    d_quats: Tensor | None = None
    d_scales: Tensor | None = None
    t_means: Tensor | None = None
    t_scales: Tensor | None = None

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
            check_finite(name, t)
        check_finite("times", self.times)
        if bool(((self.times < 0) | (self.times > 1)).any()):
            raise ValueError(f"times must lie in [0, 1], got {self.times.tolist()}")
        if T > 1 and not bool((self.times[1:] > self.times[:-1]).all()):
            raise ValueError("times must be strictly increasing")
        quat_norms(self.d_quats, "d_quats")  # zero norm → ValueError naming d_quats

    def _check_temporal(self) -> None:
        if self.t_means is None and self.t_scales is None:
            return
        if self.t_means is None or self.t_scales is None:
            raise ValueError("t_means and t_scales must be given together (or neither)")
        M = self.canonical.num_gaussians
        for name in ("t_means", "t_scales"):
            t = getattr(self, name)
            if tuple(t.shape) != (M,):
                raise ValueError(f"{name} must have shape ({M},) (one per Gaussian), got {tuple(t.shape)}")
            check_finite(name, t)
        if M and bool((self.t_scales <= 0).any()):
            raise ValueError(f"t_scales must be > 0, min is {float(self.t_scales.min())}")

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
        """True when :meth:`at` depends on t: the scene deforms or has temporal support (else every time gives
        the canonical Gaussians, and writers leave out what would repeat them)."""
        return not self.is_static or self.has_temporal

    def temporal_opacity(self, t: float) -> Tensor:
        """Marginal p(t) = exp(−½((t − μ_t)/σ_t)²) of every Gaussian (Yang et al. 2024), peak 1.

        Args:
            t: time in [0, 1].

        Returns:
            (M,) values in [0, 1] (ones when the scene has no temporal support).

        Raises:
            ValueError: t outside [0, 1] or not finite.
        """
        t = _check_time(t)
        if not self.has_temporal:
            return torch.ones_like(self.canonical.opacities)
        return torch.exp(-0.5 * ((t - self.t_means) / self.t_scales) ** 2)

    def active_indices(self, t: float, gate: float = ALPHA_MIN) -> Tensor | None:
        """Indices of the Gaussians that pass temporal gating at time ``t``: o·p(t) ≥ ``gate``.

        With ``gate`` ≤ 1/255 the dropped Gaussians have alpha = min(0.99, o·p(t)·exp(−σ)) < 1/255
        at every pixel, which the renderer skips anyway, so the image does not change.

        Args:
            t: time in [0, 1].
            gate: opacity threshold ≥ 0 (0 keeps every Gaussian).

        Returns:
            (K,) int64 ascending indices into the M Gaussians, or None when nothing is gated
            (no temporal support).

        Raises:
            ValueError: t outside [0, 1] / not finite, or gate < 0.
        """
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
        """Interpolated deformation at time ``t``.

        Linear interpolation between the two nearest key times (Δq by shorter-arc nlerp); times before
        the first / after the last key time take the end values.

        Args:
            t: time in [0, 1].
            index: (K,) indices or (M,) bool mask of the Gaussians wanted; None: all M.

        Returns:
            d_means (K, 3) metres, d_quats (K, 4) unit wxyz, d_scales (K, 3) log-scale offsets (K = M without
            ``index``).

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

        With temporal support, opacities are multiplied by p(t) (:meth:`temporal_opacity`) and only
        the Gaussians of :meth:`active_indices` (o·p(t) ≥ ``gate``) are returned, in index order —
        the deformation is evaluated for those only.

        Args:
            t: time in [0, 1].
            gate: temporal gate (see :meth:`active_indices`); ignored without temporal support.
            index: (K,) ascending int64 indices or (M,) bool mask: only these Gaussians (those of them that pass
                the gate), in index order — what ``at(t, gate)`` then a selection returns, without evaluating the
                rest. None: all M.

        The result is not validated as a whole again: the means are sums of finite values and the rotations unit
        quaternions of non-zero ones (:func:`compose_deformation`); only the scales s·exp(Δs), which can overflow
        or underflow, are checked.

        Raises:
            ValueError: t outside [0, 1] or not finite, gate < 0; a deformed scale that is not finite or not > 0.
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
        """:meth:`at`'s deformed means, quats and scales of the Gaussians ``idx`` (None: all) by the numba kernel
        (:mod:`diff4splat.scene.kernels`), or None where the reference must run: a tensor off the CPU or needing
        gradients, mixed dtypes, no numba, or a Gaussian the reference would raise for."""
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
        host = lambda x: x.detach().cpu().contiguous().numpy()  # noqa: E731  (a no-op copy: CPU, checked above)
        kernel(host(index), host(c.means), host(c.quats), host(c.scales), host(self.d_means[k]),
               host(self.d_quats[k]), host(self.d_scales[k]), host(self.d_means[k1]), host(self.d_quats[k1]),
               host(self.d_scales[k1]), float(w), *(host(o) for o in out), host(bad))
        return None if bool(bad.any()) else out

    def select(self, index: Tensor) -> DynamicGaussians:
        """Subset of Gaussians by boolean mask (M,) or indices; deformation and temporal arrays follow. Not
        validated again (every check holds per Gaussian or for the shared key times, so a subset of a valid scene
        is valid)."""
        values = {"canonical": self.canonical.select(index), "times": self.times}
        if self.has_temporal:
            values.update(t_means=self.t_means[index], t_scales=self.t_scales[index])
        if not self.is_static:
            values.update(d_means=self.d_means[:, index], d_quats=self.d_quats[:, index],
                          d_scales=self.d_scales[:, index])
        return _unchecked(DynamicGaussians, values)

    def without_deformation(self, atol: float = 0.0) -> DynamicGaussians:
        """Drop the deformation if it is the identity within ``atol`` (metres / quaternion / log-scale)."""
        if self.is_static:
            return self
        if self.num_gaussians and not (_within(self.d_means, atol) and _within(self.d_scales, atol)
                                       and _identity_rotations(self.d_quats, atol)):
            return self
        return DynamicGaussians(self.canonical, t_means=self.t_means, t_scales=self.t_scales)

    def to(self, *args, **kwargs) -> DynamicGaussians:
        """Move/cast every tensor, temporal arrays included (``Tensor.to`` arguments)."""
        mv = lambda x: None if x is None else x.to(*args, **kwargs)  # noqa: E731
        return DynamicGaussians(self.canonical.to(*args, **kwargs), mv(self.times), mv(self.d_means),
                                mv(self.d_quats), mv(self.d_scales), mv(self.t_means), mv(self.t_scales))


_UNSET = object()
_KERNEL = [_UNSET]


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
    """max |x| ≤ atol, without an |x| copy (the deformation of a large scene is gigabytes)."""
    lo, hi = torch.aminmax(x)
    return bool(torch.maximum(-lo, hi) <= atol)


def _identity_rotations(quats: Tensor, atol: float) -> bool:
    """Every (..., 4) wxyz quaternion, normalised and sign-fixed to w ≥ 0, within ``atol`` of (1, 0, 0, 0) in each
    component: |1 − |w|/‖q‖| ≤ atol and |x|, |y|, |z| ≤ atol·‖q‖ (the sign of q does not change a rotation)."""
    norm = quat_norms(quats, "d_quats")
    return (_within(quats[..., 0].abs() / norm - 1, atol)
            and all(_within(quats[..., i] / norm, atol) for i in (1, 2, 3)))


def _check_time(t: float) -> float:
    t = float(t)
    if not (0.0 <= t <= 1.0):
        raise ValueError(f"time t must lie in [0, 1], got {t}")
    return t
