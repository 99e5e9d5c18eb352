"""What the WebGL viewer renders of a scene (docs/DESIGN.md, "Viewer"), reduced to a byte budget (:func:`page_scene`):
absolute keyframes (:meth:`DynamicGaussians.at` at the key times, gate 0), the keys each Gaussian holds, the float16
error bound and the Gaussians covering most; the page interpolates keyframes as
:meth:`DynamicGaussians.deformation_at` does. Bytes: :mod:`diff4splat.io.viewer_data`.
"""
from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from diff4splat.cameras.path import CameraPath
from diff4splat.render.settings import NEAR_PLANE
from diff4splat.scene.dynamic import DynamicGaussians, distinct_rows
from diff4splat.scene.gaussians import Gaussians

__all__ = ["PageScene", "page_scene", "keyframe_times", "time_range", "keyframes", "still_gaussians", "key_windows",
           "held_keyframes", "evenly_spaced", "float16_error_px", "keyframe_dtype", "target_distance", "covering_order",
           "most_covering"]


@dataclass
class PageScene:
    """What one viewer page shows of a scene (:func:`page_scene`).

    Attributes:
        gaussians: the canonical Gaussians kept (N), at the SH degree kept.
        times: (F,) float64 key times kept, ascending in [0, 1]; None for a scene without deformation.
        span: the time slider's range (:func:`time_range`); None for a scene that does not change with time.
        windows: (first (N,), count (N,)) int64 key windows of the kept Gaussians (:func:`key_windows`), or None.
        held: (Σ count, 10) float32 held keyframes (:func:`held_keyframes`), or None.
        support: the kept Gaussians' temporal support (t_means, t_scales[, t_ramps]) (N,) each, or None.
        dtype, float16_error_px: the keyframes' dtype and the float16 error, pixels (:func:`keyframe_dtype`; None
            without keyframes).
        first_pose: (N, 3) means at the first key time (canonical without keyframes), metres.
        target_distance: :func:`target_distance` of ``first_pose`` from the first camera, metres.
        reductions: what the size budget took away, in words (empty: the full scene).
    """

    gaussians: Gaussians
    times: Tensor | None
    span: tuple[float, float] | None
    windows: tuple[Tensor, Tensor] | None
    held: Tensor | None
    support: tuple[Tensor, ...] | None
    dtype: str
    float16_error_px: float | None
    first_pose: Tensor
    target_distance: float
    reductions: list[str]


def page_scene(scene: DynamicGaussians, cameras: CameraPath, budget: int | None, size: Callable[..., int],
               max_px: float) -> PageScene:
    """The scene one viewer page shows, reduced to at most ``budget`` bytes (None: never) as measured by
    ``size(num_gaussians, sh_degree, held_keyframes, temporal_arrays, itemsize, keyed)``
    (:func:`diff4splat.io.viewer_data.payload_bytes`); keyframes float16 within ``max_px`` pixels
    (:func:`keyframe_dtype`). ``scene`` on the CPU.

    Reductions, in order, each only while over budget: SH degree → 0; keyframes subsampled (first and last kept, at
    least 2) while the held keyframes take more bytes than the rest of the payload; the Gaussians covering most kept
    (:func:`covering_order`, each at its own size: a still Gaussian holds no keyframe).
    """
    times, span = keyframe_times(scene), time_range(scene, cameras)
    canonical: Gaussians = scene.canonical
    degree = canonical.sh_degree
    n, keyed = canonical.num_gaussians, times is not None
    support_arrays = () if not scene.has_temporal else (scene.t_means, scene.t_scales) + (
        () if scene.t_ramps is None else (scene.t_ramps,))
    reductions: list[str] = []
    dtype, err = ("float32", None) if times is None else keyframe_dtype(scene, times, cameras, max_px)
    itemsize = 2 if dtype == "float16" else 4
    still = None if times is None else still_gaussians(scene)
    first, count = (None, None) if times is None else key_windows(scene, times, still)
    held = lambda: 0 if count is None else int(count.sum())  # noqa: E731
    total = lambda: size(n, degree, held(), len(support_arrays), itemsize, keyed)  # noqa: E731
    if budget is not None and total() > budget and degree > 0:
        reductions.append(f"SH degree {degree} → 0")
        degree = 0
    F = 0 if times is None else times.shape[0]
    kept_times = times
    while (budget is not None and kept_times is not None and total() > budget and len(kept_times) > 2
           and 2 * held() * 10 * itemsize > total()):
        kept_times = times[evenly_spaced(F, len(kept_times) - 1).unique()]  # fewer while the larger part
        first, count = key_windows(scene, kept_times, still)
    if kept_times is not None and len(kept_times) < F:
        reductions.append(f"{F} → {len(kept_times)} keyframes")
        times = kept_times
    keep = None
    if budget is not None and total() > budget:
        order = covering_order(canonical.opacities.detach().cpu(), canonical.scales.detach().cpu())
        cost = size(1, degree, 0, len(support_arrays), itemsize, keyed)
        cost = (torch.full((n,), cost, dtype=torch.int64, device=order.device)
                + (0 if count is None else count[order] * 10 * itemsize))
        m = max(1, int(torch.searchsorted(torch.cumsum(cost, 0), budget, right=True)))
        keep = order[:m].sort().values
        reductions.append(f"{n:,} → {m:,} Gaussians (those covering most)")
        if count is not None:
            first, count = first[keep], count[keep]
    g = canonical if keep is None else canonical.select(keep)
    if degree < canonical.sh_degree:
        g = Gaussians(g.means, g.quats, g.scales, g.opacities, g.sh[:, :1])
    frames = None if times is None else held_keyframes(scene, times, first, count, keep)  # what was kept
    support = None
    if scene.has_temporal:
        support = support_arrays if keep is None else tuple(a[keep] for a in support_arrays)
    first_pose = g.means.detach() if times is None else scene.at(float(times[0]), gate=0.0, index=keep).means
    return PageScene(g, times, span, None if first is None else (first, count), frames, support, dtype, err,
                     first_pose, target_distance(first_pose, cameras.viewmats[0].detach().cpu()), reductions)


def keyframe_times(scene: DynamicGaussians) -> Tensor | None:
    """Key times (F,) in [0, 1]: the deformation's own times, None for a scene without deformation (with temporal
    support only, the page evaluates the opacities at any time from μ_t and σ_t: no keyframes)."""
    return None if scene.is_static else scene.times.detach().cpu().double()


def time_range(scene: DynamicGaussians, cameras: CameraPath) -> tuple[float, float] | None:
    """The time slider's range in [0, 1]: the deformation's first and last key times, else (with temporal support
    only) the path's first and last frame times; None for a scene that does not change with time (no controls)."""
    times = keyframe_times(scene)
    if times is None and scene.has_temporal:
        times = cameras.times.detach().cpu().double()
    return None if times is None else (float(times.min()), float(times.max()))


@torch.no_grad()
def keyframes(scene: DynamicGaussians, times: Tensor, index: Tensor | None = None) -> dict[str, Tensor]:
    """Absolute Gaussians at every key time (:meth:`DynamicGaussians.at` with gate 0, so all N in order).

    Args:
        index: (N,) ascending indices of the Gaussians wanted (the ones a reduced page keeps); None: all.

    Returns:
        {"means": (F, N, 3) metres, "quats": (F, N, 4) unit wxyz, "scales": (F, N, 3) metres}, float32 on the CPU
        (opacities are not keyframed: with temporal support the page evaluates them from μ_t and σ_t).
    """
    F, N = len(times), scene.num_gaussians if index is None else index.shape[0]
    cpu = torch.device("cpu")  # the payload is bytes for the page: built on the host
    out = {"means": torch.empty(F, N, 3, device=cpu), "quats": torch.empty(F, N, 4, device=cpu),
           "scales": torch.empty(F, N, 3, device=cpu)}
    for i, t in enumerate(times):  # one time at a time into the outputs: memory F·N·10 floats, not twice that
        g = scene.at(float(t), gate=0.0, index=index)
        for key, dst in out.items():
            src = getattr(g, key).detach()
            dst[i] = (src / src.norm(dim=-1, keepdim=True) if key == "quats" else src).to("cpu", torch.float32)
    return out


def still_gaussians(scene: DynamicGaussians) -> Tensor:
    """(M,) bool: the Gaussians whose deformation is the identity at every key time (Δμ = 0, Δs = 0, Δq a positive
    multiple of (1, 0, 0, 0)), so :meth:`DynamicGaussians.at` gives exactly their canonical pose at every t. All
    True for a scene without deformation."""
    n = scene.num_gaussians
    if scene.is_static:
        return torch.ones(n, dtype=torch.bool, device=scene.canonical.means.device)
    d_means, d_quats, d_scales = (distinct_rows(x) for x in (scene.d_means, scene.d_quats, scene.d_scales))
    moving = (d_means != 0).any(dim=-1).any(dim=0) | (d_scales != 0).any(dim=-1).any(dim=0)
    moving = moving | (d_quats[..., 1:] != 0).any(dim=-1).any(dim=0) | (d_quats[..., 0] <= 0).any(dim=0)
    return ~moving.expand(n)  # (M,): a shared row's answer holds for every Gaussian


def key_windows(scene: DynamicGaussians, times: Tensor, still: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """The keyframes the page needs of each Gaussian, out of the key times ``times`` (F,) ascending: (first (M,),
    count (M,)) int64, the consecutive keys first … first + count − 1.

    - count 0 for a still Gaussian (``still`` (M,) bool, default :func:`still_gaussians`): its canonical pose, from
      the PLY, at every time;
    - with bounded temporal support (``t_ramps``: opacity 0 where |t − μ_t| ≥ σ_t) the keys around that window, from
      the last key at or before μ_t − σ_t to the first at or after μ_t + σ_t: wherever the Gaussian is seen, the two
      keys the page interpolates between (its clamped lookup, as :meth:`DynamicGaussians.deformation_at`) are held;
    - all F keys otherwise.
    """
    n, F = scene.num_gaussians, times.shape[0]
    times = times.double().cpu()
    still = (still_gaussians(scene) if still is None else still).cpu()
    host = times.device  # the windows are page data: built on the host
    first = torch.zeros(n, dtype=torch.int64, device=host)
    last = torch.full((n,), F - 1, dtype=torch.int64, device=host)
    if scene.t_ramps is not None:
        mu, sigma = scene.t_means.detach().double().cpu(), scene.t_scales.detach().double().cpu()
        first = (torch.searchsorted(times, mu - sigma, right=True) - 1).clamp(0, F - 1)
        last = torch.searchsorted(times, mu + sigma).clamp(0, F - 1)
    count = torch.where(still, 0, last - first + 1)
    return torch.where(still, 0, first), count


@torch.no_grad()
def held_keyframes(scene: DynamicGaussians, times: Tensor, first: Tensor, count: Tensor,
                   index: Tensor | None = None) -> Tensor:
    """The keyframes the page holds (:func:`key_windows`) of the Gaussians ``index`` ((K,) ascending; None: all),
    Gaussian by Gaussian and within one by key time: (Σ count, 10) float32 on the CPU, each row the means (3) metres,
    unit quats (4) wxyz and scales (3) metres of :meth:`DynamicGaussians.at` (gate 0) at that key time, the same
    values as :func:`keyframes` at the held keys. ``first``, ``count``: (K,) of the Gaussians ``index``."""
    first, count = first.cpu(), count.cpu()
    start = torch.cumsum(count, 0) - count  # each Gaussian's first row
    out = torch.empty(int(count.sum()), 10, device="cpu")  # page data: built on the host
    for f, t in enumerate(times.tolist()):  # one time at a time: memory of the held rows only
        held = torch.nonzero((first <= f) & (f < first + count)).squeeze(1)
        if held.numel() == 0:
            continue
        g = scene.at(float(t), gate=0.0, index=held.to(scene.canonical.means.device) if index is None
                     else index[held.to(index.device)])
        quats = g.quats.detach()
        out[start[held] + f - first[held]] = torch.cat(
            [g.means.detach(), quats / quats.norm(dim=-1, keepdim=True), g.scales.detach()], dim=1).to("cpu",
                                                                                                    torch.float32)
    return out


def evenly_spaced(n: int, k: int, device: torch.device | str = "cpu") -> Tensor:
    """(k,) int64 indices into ``n`` items, evenly spaced from 0 to n − 1: round(i · (n − 1) / (k − 1)), halves up,
    in exact integer arithmetic (a float32 ``linspace`` rounds n − 1 up to n above 2²⁴ items: an index past the
    end). ``k`` ≥ 1 (k = 1: [0]); indices repeat when k > n."""
    i = torch.arange(k, dtype=torch.int64, device=device)
    if k == 1:
        return i
    return (2 * i * (n - 1) + (k - 1)) // (2 * (k - 1))


FLOAT16_CHECK_POINTS = 200_000
"""Most keyframe means :func:`float16_error_px` measures (an evenly spaced subset of the F·N)."""


def float16_error_px(
    means: Tensor,  # (F, N, 3) world, metres
    viewmats: Tensor,  # (C, 4, 4) world-to-camera (OpenCV)
    Ks: Tensor,  # (C, 3, 3) pixels
    near: float = NEAR_PLANE,
    max_points: int = FLOAT16_CHECK_POINTS,
    max_cameras: int = 9,
) -> float:
    """Largest image-plane displacement, pixels, caused by rounding ``means`` to float16, over the cameras and
    the Gaussians in front of them (z > ``near``) whose projection lies within 4× the principal point's
    distance from the image origin; 0.0 when no Gaussian is in view. Large inputs are measured on a seeded
    evenly spaced subset of ``max_points`` points and ``max_cameras`` evenly spaced cameras (first and last kept)."""
    pts = means.reshape(-1, 3)
    if pts.shape[0] > max_points:
        pts = pts[evenly_spaced(pts.shape[0], max_points, pts.device)]  # the same subset on every device
    pts = pts.double()  # after the pick: a float64 copy of the subset, not of every frame's means
    if viewmats.shape[0] > max_cameras:
        pick = evenly_spaced(viewmats.shape[0], max_cameras, viewmats.device)
        viewmats, Ks = viewmats[pick], Ks[pick]
    half = pts.half().double()
    worst = 0.0
    for vm, K in zip(viewmats.double(), Ks.double(), strict=True):
        a, b = pts @ vm[:3, :3].T + vm[:3, 3], half @ vm[:3, :3].T + vm[:3, 3]
        ok = (a[:, 2] > near) & (b[:, 2] > near)
        if not bool(ok.any()):
            continue
        pa = (a[ok] @ K.T)[:, :2] / a[ok, 2:3]
        pb = (b[ok] @ K.T)[:, :2] / b[ok, 2:3]
        lim = 4 * float(max(K[0, 2], K[1, 2]))  # ignore Gaussians far outside the image (grazing angles)
        keep = (pa.abs() < lim).all(1)
        if bool(keep.any()):
            worst = max(worst, float((pa[keep] - pb[keep]).norm(dim=1).max()))
    return worst


def _fits_float16(x: Tensor) -> bool:
    """Every value rounds to a finite float16: |x| < 65520 (the largest float16 is 65504; from 65520 on, rounding
    gives inf) and no NaN, from one min/max pass instead of a float16 copy of the keyframes."""
    lo, hi = torch.aminmax(x)
    return bool(torch.maximum(-lo, hi) < 65520)  # NaN compares False


@torch.no_grad()
def keyframe_dtype(scene: DynamicGaussians, times: Tensor, cameras: CameraPath, max_px: float) -> tuple[str, float]:
    """("float16" or "float32", :func:`float16_error_px`) of the keyframes of all N Gaussians at ``times`` (F,),
    float16 when that error is ≤ ``max_px`` pixels and every value fits: the error, without holding the keyframes,
    from the evenly spaced F·N means it measures, deformed at their own times (:meth:`DynamicGaussians.at` with
    ``index``); the range from a bound, max |μ| + max |Δμ| and max s·exp(max Δs) below 65520, else each time's."""
    F, N = len(times), scene.num_gaussians
    dev = scene.canonical.means.device
    pick = (evenly_spaced(F * N, FLOAT16_CHECK_POINTS, dev) if F * N > FLOAT16_CHECK_POINTS
            else torch.arange(F * N, device=dev))
    means = [scene.at(float(times[f]), gate=0.0, index=pick[pick // N == f] % N).means.detach()
             for f in range(F)]
    err = float16_error_px(torch.cat(means)[None].cpu(), cameras.viewmats.detach().cpu(),
                           cameras.Ks.detach().cpu())
    return ("float16" if err <= max_px and _keyframes_fit_float16(scene, times) else "float32"), err


def _keyframes_fit_float16(scene: DynamicGaussians, times: Tensor) -> bool:
    """Every keyframe value rounds to a finite float16 (the quaternions are unit): true when the bound
    max |μ| + max |Δμ| and max s·exp(max Δs) is below 65520, else checked at each time."""
    c = scene.canonical
    if c.num_gaussians == 0:
        return True
    lo, hi = torch.aminmax(distinct_rows(scene.d_means.detach()))
    bound = max(float(c.means.detach().abs().max()) + float(torch.maximum(-lo, hi)),
                float(c.scales.detach().max()) * math.exp(float(distinct_rows(scene.d_scales.detach()).max())))
    if bound < 65520:
        return True
    for t in times:
        g = scene.at(float(t), gate=0.0)
        if not (_fits_float16(g.means.detach()) and _fits_float16(g.scales.detach())):
            return False
    return True

def target_distance(means: Tensor, viewmat: Tensor) -> float:
    """Median z-depth of the Gaussians in front of the first camera (the orbit centre's distance), metres."""
    z = (means.double() @ viewmat[:3, :3].double().T + viewmat[:3, 3].double())[:, 2]
    z = z[z > NEAR_PLANE]
    return float(z.median()) if z.numel() else 1.0


def covering_order(opacities: Tensor, scales: Tensor) -> Tensor:
    """(N,) int64: the Gaussians from the one that covers most to the one that covers least, opacity times
    footprint, o·(s₁s₂s₃)^⅔ (a Gaussian's area, m², for ``opacities`` (N,) and ``scales`` (N, 3) metres; the
    opacity × volume importance of 3DGS pruning, as an area). Equal scores (a photo layer's disks are alike) are
    taken in a fixed pseudo-random order (seed 0), so a scene of many alike layers keeps part of each, spread over its
    pixels, not the first layers whole."""
    n = opacities.shape[0]
    score = opacities.double() * scales.double().prod(dim=-1).pow(2 / 3)
    order = torch.randperm(n, generator=torch.Generator(device="cpu").manual_seed(0),
                           device="cpu").to(opacities.device)  # the same order on every device: a CPU generator
    return order[torch.argsort(score[order], descending=True, stable=True)]


def most_covering(opacities: Tensor, scales: Tensor, m: int) -> Tensor:
    """(m,) ascending indices of the ``m`` Gaussians that cover most (the first ``m`` of :func:`covering_order`)."""
    return covering_order(opacities, scales)[:m].sort().values
