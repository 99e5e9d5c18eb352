"""Scale-and-shift alignment of relative (affine-invariant) depth to metric depth.

The least-squares fit of MiDaS (Ranftl et al., TPAMI 2020, Eq. 4), (s, t) = argmin Σ_valid (s·x_i + t − y_i)², in
closed form, in depth space (x relative depth, y metres, aligned = s·x + t) or disparity space (x relative inverse
depth, y = 1/metres, aligned = 1/(s·x + t)); aligned values that are not positive are +inf (invalid).
:func:`fit_scale_shift_robust` adds least-median-of-squares over 2-point samples (Rousseeuw, JASA 1984) then IRLS
with Tukey or Huber weights and a MAD scale (Holland & Welsch 1977; Huber 1981). :func:`align_video` fits one
(s, t) for all frames of a video.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from diff4splat.utils.checks import check_int

__all__ = ["DepthAlignment", "SPACES", "fit_scale_shift", "fit_scale_shift_robust", "align_video", "valid_depth_mask"]

SPACES = ("depth", "disparity")
"""Spaces in which s·x + t ≈ y is fitted (module docstring)."""

_LOSSES = ("tukey", "huber")
_TUKEY_C = 4.685  # 95 % asymptotic efficiency under Gaussian noise (Holland & Welsch 1977)
_HUBER_K = 1.345  # 95 % asymptotic efficiency under Gaussian noise (Huber 1981)
_MAD_TO_SIGMA = 1.4826  # 1 / Φ⁻¹(3/4): MAD of a Gaussian → its standard deviation
_CONSTANT_RTOL = 1e-12  # relative variance below which the relative depth is called constant


@dataclass(frozen=True)
class DepthAlignment:
    """A fitted ``scale`` s > 0 and ``shift`` t (metres, or 1/metres in disparity space), the ``space``, the
    ``num_valid`` samples seen, the ``num_inliers`` of non-zero final weight and the inliers' ``rms`` residual in
    the fit space."""

    scale: float
    shift: float
    space: str
    num_valid: int
    num_inliers: int
    rms: float

    def apply(self, relative: np.ndarray) -> np.ndarray:
        """(...) float64 metric z-depth (metres) of a relative depth/disparity map of any shape; +inf where s·x + t ≤ 0
        or the input is not finite."""
        x = np.asarray(relative, dtype=np.float64)
        lin = self.scale * x + self.shift
        with np.errstate(divide="ignore", invalid="ignore"):
            depth = lin if self.space == "depth" else 1.0 / lin
        ok = np.isfinite(lin) & (lin > 0)
        return np.where(ok, depth, np.inf)


def valid_depth_mask(depth: np.ndarray) -> np.ndarray:
    """(...) bool: pixels of a metric depth map (metres) usable as a reference, finite and > 0."""
    d = np.asarray(depth, dtype=np.float64)
    return np.isfinite(d) & (d > 0)


def _check_space(space: str) -> str:
    """Returns ``space``; ValueError unless it is one of :data:`SPACES`."""
    if space not in SPACES:
        raise ValueError(f"space must be one of {SPACES}, got {space!r}")
    return space


def _samples(relative, metric, mask, space: str) -> tuple[np.ndarray, np.ndarray]:
    """Valid (x, y) samples in the fit space, with the degenerate-input checks."""
    x = np.asarray(relative, dtype=np.float64)
    d = np.asarray(metric, dtype=np.float64)
    if x.shape != d.shape:
        raise ValueError(f"relative and metric must have the same shape, got {x.shape} and {d.shape}")
    if mask is None:
        m = np.ones(x.shape, dtype=bool)
    else:
        m = np.asarray(mask)
        if m.shape != x.shape:
            raise ValueError(f"mask must have the shape of the depth maps {x.shape}, got {m.shape}")
        if m.dtype != bool:
            raise ValueError(f"mask must be a boolean array, got dtype {m.dtype}")
    x, d = x[m], d[m]
    if x.size < 2:
        raise ValueError(f"need at least 2 valid pixels to fit scale and shift, got {x.size}")
    if not np.isfinite(x).all():
        raise ValueError(f"relative depth has {int((~np.isfinite(x)).sum())} NaN/inf values among the valid pixels")
    if not np.isfinite(d).all():
        raise ValueError(f"metric depth has {int((~np.isfinite(d)).sum())} NaN/inf values among the valid pixels")
    if space == "disparity":
        if (d <= 0).any():
            raise ValueError(f"metric depth must be > 0 among the valid pixels to fit in disparity space, "
                             f"min is {float(d.min())}")
        d = 1.0 / d
    spread = np.abs(x - x.mean()).max()
    if spread <= _CONSTANT_RTOL * max(np.abs(x).max(), np.finfo(np.float64).tiny):
        raise ValueError(f"relative depth is constant ({float(x[0])}) over the valid pixels; scale is undetermined")
    return x, d


def _weighted_ls(x: np.ndarray, y: np.ndarray, w: np.ndarray | None) -> tuple[float, float]:
    """Closed-form (weighted) least squares (s, t) in centred form; ValueError for zero weighted variance."""
    if w is None:
        xm, ym = x.mean(), y.mean()
        xc = x - xm
        sxx, sxy = np.dot(xc, xc), np.dot(xc, y - ym)
    else:
        wsum = w.sum()
        xm, ym = np.dot(w, x) / wsum, np.dot(w, y) / wsum
        xc = x - xm
        sxx, sxy = np.dot(w * xc, xc), np.dot(w * xc, y - ym)
    if not sxx > 0:
        raise ValueError("relative depth is constant over the pixels with non-zero weight; scale is undetermined")
    s = sxy / sxx
    return float(s), float(ym - s * xm)


def _check_scale(s: float, space: str) -> None:
    """ValueError unless the fitted scale ``s`` is > 0."""
    if not s > 0:
        raise ValueError(f"fitted scale is {s:.6g} ≤ 0 (in {space} space): the relative depth is anti-correlated with "
                         f"the metric depth — was inverse depth passed with space='depth' (or depth with "
                         f"space='disparity')?")


def fit_scale_shift(
    relative: np.ndarray,  # (...) relative depth or disparity
    metric: np.ndarray,  # (...) metric depth, metres
    mask: np.ndarray | None = None,  # (...) bool
    *,
    space: str = "depth",
) -> DepthAlignment:
    """Least-squares scale and shift (module docstring), closed form, of ``relative`` (...) depth (``space="depth"``) or
    inverse depth (``"disparity"``), any units, to ``metric`` (...) z-depth in metres, over ``mask`` (...) bool (None:
    every pixel; see :func:`valid_depth_mask`). ``num_inliers`` of the result is ``num_valid``.

    Raises:
        ValueError: shapes differ; mask not boolean or of another shape; fewer than 2 valid pixels; NaN/inf among the
            valid pixels; metric depth ≤ 0 in disparity space; constant relative depth; fitted scale ≤ 0; unknown
            ``space``.
    """
    space = _check_space(space)
    x, y = _samples(relative, metric, mask, space)
    s, t = _weighted_ls(x, y, None)
    _check_scale(s, space)
    r = s * x + t - y
    return DepthAlignment(s, t, space, int(x.size), int(x.size), float(np.sqrt(np.mean(r * r))))


def _lmeds(x: np.ndarray, y: np.ndarray, iters: int, rng: np.random.Generator, max_eval: int
           ) -> tuple[float, float] | None:
    """Least-median-of-squares over random 2-point samples; ``None`` if no sample was usable."""
    n = x.size
    ev = rng.choice(n, size=max_eval, replace=False) if n > max_eval else np.arange(n)
    xe, ye = x[ev], y[ev]
    i = rng.integers(0, n, size=iters)
    j = rng.integers(0, n, size=iters)
    dx = x[j] - x[i]
    ok = np.abs(dx) > _CONSTANT_RTOL * np.maximum(np.abs(x[i]), np.abs(x[j]))
    i, j, dx = i[ok], j[ok], dx[ok]
    s = (y[j] - y[i]) / dx
    t = y[i] - s * x[i]
    keep = s > 0  # a negative-scale hypothesis can never be the answer
    s, t = s[keep], t[keep]
    if s.size == 0:
        return None
    best, best_med = None, np.inf
    for start in range(0, s.size, 64):  # bounded memory: 64 hypotheses × max_eval residuals at a time
        r = s[start : start + 64, None] * xe[None, :] + t[start : start + 64, None] - ye[None, :]
        med = np.median(np.abs(r), axis=1)
        k = int(np.argmin(med))
        if med[k] < best_med:
            best_med, best = med[k], (float(s[start + k]), float(t[start + k]))
    return best


def fit_scale_shift_robust(
    relative: np.ndarray,  # (...) relative depth or disparity
    metric: np.ndarray,  # (...) metric depth, metres
    mask: np.ndarray | None = None,  # (...) bool
    *,
    space: str = "depth",
    loss: str = "tukey",
    ransac_iters: int = 256,
    irls_iters: int = 30,
    seed: int = 0,
    max_eval: int = 20000,
    tol: float = 1e-10,
) -> DepthAlignment:
    """Outlier-robust scale and shift: LMedS over ``ransac_iters`` (≥ 0) seeded 2-point samples, each hypothesis' median
    over up to ``max_eval`` (≥ 2) samples (0 iterations: start from least squares), then up to ``irls_iters`` (≥ 1) IRLS
    steps with σ = 1.4826·MAD: ``loss`` "tukey" w = (1 − (r/cσ)²)² for |r| < cσ (c = 4.685) or "huber"
    w = min(1, kσ/|r|) (k = 1.345), until (s, t) changes by less than ``tol`` (relative). σ = 0 (over half the samples
    fit exactly) refits the exact samples. Other arguments as :func:`fit_scale_shift`; ``num_inliers`` counts samples
    of non-zero final weight, ``rms`` is over them.

    Raises:
        ValueError: as :func:`fit_scale_shift`; an unknown ``loss``, ``ransac_iters`` < 0, ``irls_iters`` < 1 or
            ``max_eval`` < 2.
    """
    space = _check_space(space)
    if loss not in _LOSSES:
        raise ValueError(f"loss must be one of {_LOSSES}, got {loss!r}")
    ransac_iters, irls_iters, max_eval = (check_int(name, v, lo) for name, v, lo in (
        ("ransac_iters", ransac_iters, 0), ("irls_iters", irls_iters, 1), ("max_eval", max_eval, 2)))
    x, y = _samples(relative, metric, mask, space)
    rng = np.random.default_rng(seed)
    start = _lmeds(x, y, ransac_iters, rng, max_eval) if ransac_iters > 0 else None
    s, t = start if start is not None else _weighted_ls(x, y, None)
    exact_tol = 1e-12 * float(np.abs(y).max())
    w = np.ones_like(x)
    for _ in range(irls_iters):
        r = s * x + t - y
        sigma = float(_MAD_TO_SIGMA * np.median(np.abs(r - np.median(r))))  # robust standard deviation
        if sigma <= exact_tol:
            w = (np.abs(r) <= exact_tol).astype(np.float64)
            s, t = _weighted_ls(x, y, w) if w.sum() >= 2 else (s, t)
            break
        u = r / sigma
        if loss == "tukey":
            w = np.where(np.abs(u) < _TUKEY_C, (1.0 - (u / _TUKEY_C) ** 2) ** 2, 0.0)
        else:
            w = np.minimum(1.0, _HUBER_K / np.maximum(np.abs(u), 1e-300))
        if np.count_nonzero(w) < 2:
            break
        s_new, t_new = _weighted_ls(x, y, w)
        done = abs(s_new - s) <= tol * abs(s) and abs(t_new - t) <= tol * max(abs(t), abs(s) * float(np.abs(x).mean()))
        s, t = s_new, t_new
        if done:
            break
    _check_scale(s, space)
    r = s * x + t - y
    inl = w > 0
    n_in = int(inl.sum())
    rms = float(np.sqrt(np.mean(r[inl] ** 2))) if n_in else float("nan")
    return DepthAlignment(s, t, space, int(x.size), n_in, rms)


def align_video(
    relative: Sequence[np.ndarray] | np.ndarray,  # T × (H, W) relative depth or disparity
    metric: Sequence[np.ndarray] | np.ndarray,  # T × (H, W) metric depth, metres
    masks: Sequence[np.ndarray] | np.ndarray | None = None,  # T × (H, W) bool
    *,
    space: str = "depth",
    robust: bool = True,
    **robust_kwargs,
) -> tuple[DepthAlignment, list[np.ndarray]]:
    """One (s, t) shared by every frame of a video (the fit of the concatenated valid pixels), and the T aligned float64
    depth maps (metres, +inf where invalid). ``relative``, ``metric`` (metres), ``masks`` (None: all valid): T maps
    each, a list of (H_i, W_i) arrays or a (T, H, W) array; ``robust``: :func:`fit_scale_shift_robust` with
    ``robust_kwargs``, else :func:`fit_scale_shift`.

    Raises:
        ValueError: different or zero frame counts, a frame's shapes differ, ``robust_kwargs`` without ``robust``,
            or any error of the fit.
    """
    rel = [np.asarray(r) for r in relative]
    met = [np.asarray(m) for m in metric]
    msk = None if masks is None else [np.asarray(m) for m in masks]
    if len(rel) == 0:
        raise ValueError("align_video needs at least one frame, got 0")
    if len(met) != len(rel) or (msk is not None and len(msk) != len(rel)):
        raise ValueError(f"relative, metric and masks must have the same number of frames, got {len(rel)}, "
                         f"{len(met)}" + ("" if msk is None else f", {len(msk)}"))
    for i, (r, m) in enumerate(zip(rel, met, strict=True)):
        if r.shape != m.shape or (msk is not None and msk[i].shape != r.shape):
            raise ValueError(f"frame {i}: relative, metric and mask shapes differ ({r.shape}, {m.shape})")
    if robust_kwargs and not robust:
        raise ValueError(f"options {sorted(robust_kwargs)} only apply to the robust fit (robust=True)")
    x = np.concatenate([r.reshape(-1) for r in rel])
    y = np.concatenate([m.reshape(-1) for m in met])
    m = None if msk is None else np.concatenate([k.reshape(-1) for k in msk])
    fit = (fit_scale_shift_robust(x, y, m, space=space, **robust_kwargs) if robust
           else fit_scale_shift(x, y, m, space=space))
    return fit, [fit.apply(r) for r in rel]
