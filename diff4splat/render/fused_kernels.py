"""The numba kernels of the fused compositor (:mod:`diff4splat.render.fused`, which documents the algorithm).

Imported only when the fused compositor first runs, so ``import diff4splat`` does not pay numba's import time;
an ``ImportError`` here (no numba) makes :mod:`.fused` fall back to the PyTorch tile path.
"""
from __future__ import annotations

import contextlib
import functools
import os

import numba
import numpy as np
import torch
from numba import njit, prange

from diff4splat.constants import ALPHA_MAX, ALPHA_MIN, OPACITY_LOG_FLOOR, T_MIN

__all__ = ["KERNEL", "box_kernel", "bin_kernel", "forward_kernel", "backward_kernel", "gather_kernel", "threads"]

if "NUMBA_THREADING_LAYER" not in os.environ:
    # OpenMP first: torch's CPU wheel runs on libgomp, and numba's "omp" layer then shares torch's thread pool.
    # With numba's own "workqueue" pool, torch's OpenMP threads still spin-wait after each torch op and take
    # the cores from numba's threads: the 256²/65,536 forward kernel took 28 ms instead of 19 ms.
    numba.config.THREADING_LAYER_PRIORITY = ["omp", "workqueue", "tbb"]


KERNEL = functools.partial(njit, cache=True, error_model="numpy")
"""numba's njit as every kernel of the fused renderer uses it: cached on disk; NumPy's error model (a division
by zero gives inf/NaN instead of a Python exception check before every division and integer floor division:
that check made the binning ~10× slower)."""


@contextlib.contextmanager
def threads(n: int):
    """Run the kernel launches inside on ``n`` threads (at most numba's pool size), then restore torch's count.

    numba's OpenMP layer sets the shared OpenMP thread count at each launch (``omp_set_num_threads``), which is
    also torch's: without the restore, ``torch.set_num_threads(1)`` read back 2 after one launch.
    """
    saved = torch.get_num_threads()
    numba.set_num_threads(max(1, min(n, numba.config.NUMBA_NUM_THREADS)))
    try:
        yield
    finally:
        if torch.get_num_threads() != saved:
            torch.set_num_threads(saved)


@KERNEL(inline="always")
def _tile_rect(t, tiles_x, tile, width, height):  # pragma: no cover - compiled
    """Origin (x, y) and size (w, h) of tile t, clipped to the image."""
    tx0 = (t % tiles_x) * tile
    ty0 = (t // tiles_x) * tile
    return tx0, ty0, min(tile, width - tx0), min(tile, height - ty0)


@KERNEL(inline="always")
def _clip_box(box, g, tx0, ty0, tw, th):  # pragma: no cover - compiled
    """Gaussian g's inclusive pixel box (x0, y0, x1, y1) clipped to the tile (empty when x0 > x1 or y0 > y1)."""
    return max(box[g, 0], tx0), max(box[g, 1], ty0), min(box[g, 2], tx0 + tw - 1), min(box[g, 3], ty0 + th - 1)


@KERNEL(parallel=True)
def box_kernel(means2d, covars2d, opacities, width, height, tile, box, tbox, per_gauss):  # pragma: no cover
    """tiles.tile_boxes per Gaussian in float64 (Gaussians in parallel): the opacity-aware support extent
    (projection.support_extent), its inclusive pixel box clipped to the image, the tile box and tile count."""
    for g in prange(means2d.shape[0]):
        tau = np.log(max(np.float64(opacities[g]), OPACITY_LOG_FLOOR) / ALPHA_MIN)
        ex = ey = -1.0
        if tau >= 0:
            ex = np.sqrt(2.0 * tau * max(np.float64(covars2d[g, 0]), 0.0)) * 1.001 + 1e-3
            ey = np.sqrt(2.0 * tau * max(np.float64(covars2d[g, 2]), 0.0)) * 1.001 + 1e-3
        x0 = np.int64(max(np.ceil(means2d[g, 0] - ex - 0.5), 0.0))
        y0 = np.int64(max(np.ceil(means2d[g, 1] - ey - 0.5), 0.0))
        x1 = np.int64(min(np.floor(means2d[g, 0] + ex - 0.5), width - 1))
        y1 = np.int64(min(np.floor(means2d[g, 1] + ey - 0.5), height - 1))
        box[g, 0], box[g, 1], box[g, 2], box[g, 3] = x0, y0, x1, y1
        if x0 <= x1 and y0 <= y1 and ex >= 0:
            tbox[g, 0], tbox[g, 1], tbox[g, 2], tbox[g, 3] = x0 // tile, y0 // tile, x1 // tile, y1 // tile
            per_gauss[g] = (tbox[g, 2] - tbox[g, 0] + 1) * (tbox[g, 3] - tbox[g, 1] + 1)
        else:
            per_gauss[g] = 0


@KERNEL(parallel=True)
def bin_kernel(tbox, per_gauss, depths, tiles_x, counts, flatten_ids, isect_tiles):  # pragma: no cover
    """Group the tile intersections by tile, each tile's list in depth order (ties by index): a counting sort
    by tile over the Gaussians in index order (serial, sequential reads), then a stable sort by depth of each
    tile's list (tiles in parallel). The same lists as tiles.bin_tiles' global stable depth sort followed by
    a stable sort by tile. tbox (M, 4): each Gaussian's inclusive tile box (tx0, ty0, tx1, ty1), divided
    outside (numba's int64 floor division made this kernel 10× slower)."""
    n = tbox.shape[0]
    for g in range(n):
        if per_gauss[g] > 0:
            for ty in range(tbox[g, 1], tbox[g, 3] + 1):
                for tx in range(tbox[g, 0], tbox[g, 2] + 1):
                    counts[ty * tiles_x + tx] += 1
    offsets = np.empty_like(counts)
    acc = 0
    for t in range(counts.shape[0]):
        offsets[t] = acc
        acc += counts[t]
    cursor = offsets.copy()
    for g in range(n):
        if per_gauss[g] > 0:
            for ty in range(tbox[g, 1], tbox[g, 3] + 1):
                for tx in range(tbox[g, 0], tbox[g, 2] + 1):
                    t = ty * tiles_x + tx
                    flatten_ids[cursor[t]] = g
                    cursor[t] += 1
    for t in prange(counts.shape[0]):
        start, stop = offsets[t], offsets[t] + counts[t]
        ids = flatten_ids[start:stop].copy()
        order = np.argsort(depths[ids], kind="mergesort")
        for k in range(stop - start):
            flatten_ids[start + k] = ids[order[k]]
            isect_tiles[start + k] = t


@KERNEL()
def gather_kernel(ids, per_isect, out):  # pragma: no cover - compiled
    """out[ids[k]] += per_isect[k] for k in order (serial, so the sums do not depend on threads)."""
    for k in range(ids.shape[0]):
        for j in range(per_isect.shape[1]):
            out[ids[k], j] += per_isect[k, j]


@KERNEL(parallel=True)
def forward_kernel(params, feats, bg, has_bg, ids, offsets, counts, box, width, height, tile, tiles_x,
                    out, acc, t_final, last, pairs):  # pragma: no cover - compiled
    """Forward compositing of one camera, tiles in parallel (:mod:`diff4splat.render.fused`); float64 arrays.

    Inputs (M Gaussians, F features, I tile intersections, n_tiles = tiles_x·tiles_y, H·W pixels, row-major
    pixel index q = y·width + x): params (M, 6) = [μx, μy, a, b, c, o] (pixel centre in pixels, conic
    (a, b, c) in 1/pixels², opacity o in [0, 1]); feats (M, F); bg (F,) (zeros and ``has_bg`` False without a
    background); ids (I,) Gaussian index of each intersection, grouped by tile, depth order inside a tile;
    offsets (n_tiles,), counts (n_tiles,): start and length of each tile's run in ``ids``; box (M, 4) int64
    inclusive pixel box (x0, y0, x1, y1); width, height in pixels; tile = tile side in pixels.

    Outputs, written in place: out (H·W, F) composited features (+ T_final·bg with a background); acc (H·W,)
    alpha 1 − T_final; t_final (H·W,) final transmittance; last (H·W,) int64 index into ``ids`` of the last
    Gaussian each pixel included (−1: none); pairs (n_tiles,) int64 (Gaussian, pixel) pairs inside the boxes.
    """
    n_tiles = counts.shape[0]
    n_feat = feats.shape[1]
    for t in prange(n_tiles):
        tx0, ty0, tw, th = _tile_rect(t, tiles_x, tile, width, height)
        T = np.ones(tile * tile)
        col = np.zeros((tile * tile, n_feat))
        lst = np.full(tile * tile, -1, np.int64)
        done = np.zeros(tile * tile, np.bool_)
        n_done = 0
        n_pairs = 0
        start = offsets[t]
        for k in range(start, start + counts[t]):
            g = ids[k]
            x0, y0, x1, y1 = _clip_box(box, g, tx0, ty0, tw, th)
            n_pairs += max(0, x1 - x0 + 1) * max(0, y1 - y0 + 1)
            if n_done == tw * th:
                continue  # every pixel has stopped: only count the pairs (the tile path's n_pairs)
            mx, my, a, b, c, o = params[g, 0], params[g, 1], params[g, 2], params[g, 3], params[g, 4], params[g, 5]
            for y in range(y0, y1 + 1):
                dy = y + 0.5 - my
                for x in range(x0, x1 + 1):
                    p = (y - ty0) * tile + (x - tx0)
                    if done[p]:
                        continue
                    dx = x + 0.5 - mx
                    sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
                    if sigma < 0.0:
                        continue
                    alpha = min(ALPHA_MAX, o * np.exp(-sigma))
                    if alpha < ALPHA_MIN:
                        continue
                    next_t = T[p] * (1.0 - alpha)
                    if next_t < T_MIN:
                        done[p] = True
                        n_done += 1
                        continue
                    w = alpha * T[p]
                    for f in range(n_feat):
                        col[p, f] += w * feats[g, f]
                    T[p] = next_t
                    lst[p] = k
        for y in range(th):
            for x in range(tw):
                p = y * tile + x
                q = (ty0 + y) * width + tx0 + x
                for f in range(n_feat):
                    out[q, f] = col[p, f] + (T[p] * bg[f] if has_bg else 0.0)
                acc[q] = 1.0 - T[p]
                t_final[q] = T[p]
                last[q] = lst[p]
        pairs[t] = n_pairs


@KERNEL(parallel=True)
def backward_kernel(params, feats, bg, has_bg, ids, offsets, counts, box, width, height, tile, tiles_x,
                     t_final, last, grad_out, grad_acc, g_params, g_feats):  # pragma: no cover - compiled
    """Backward pass of :func:`forward_kernel`, tiles in parallel, each tile's list walked back to front.

    Inputs: the forward kernel's params (M, 6), feats (M, F), bg (F,), has_bg, ids (I,), offsets (n_tiles,),
    counts (n_tiles,), box (M, 4), width, height, tile, tiles_x, and its outputs t_final (H·W,) and last (H·W,);
    grad_out (H·W, F) and grad_acc (H·W,): ∂L/∂out and ∂L/∂acc (float64).

    Outputs, accumulated in place (zeroed by the caller): g_params (I, 6) and g_feats (I, F), one row per
    intersection (∂L/∂params and ∂L/∂feats of that pair's Gaussian); the caller sums the rows per Gaussian with
    :func:`gather_kernel`. The background's gradient is computed outside (Σ t_final·grad_out).
    """
    n_tiles = counts.shape[0]
    n_feat = feats.shape[1]
    for t in prange(n_tiles):
        tx0, ty0, tw, th = _tile_rect(t, tiles_x, tile, width, height)
        T = np.empty(tile * tile)
        after = np.zeros(tile * tile)
        lst = np.full(tile * tile, -1, np.int64)
        go = np.zeros((tile * tile, n_feat))
        gacc = np.zeros(tile * tile)
        for y in range(th):
            for x in range(tw):
                p = y * tile + x
                q = (ty0 + y) * width + tx0 + x
                T[p] = t_final[q]
                lst[p] = last[q]
                s = 0.0
                for f in range(n_feat):
                    go[p, f] = grad_out[q, f]
                    if has_bg:
                        s += grad_out[q, f] * bg[f]
                gacc[p] = grad_acc[q] - s
        start = offsets[t]
        for k in range(start + counts[t] - 1, start - 1, -1):
            g = ids[k]
            x0, y0, x1, y1 = _clip_box(box, g, tx0, ty0, tw, th)
            mx, my, a, b, c, o = params[g, 0], params[g, 1], params[g, 2], params[g, 3], params[g, 4], params[g, 5]
            for y in range(y0, y1 + 1):
                dy = y + 0.5 - my
                for x in range(x0, x1 + 1):
                    p = (y - ty0) * tile + (x - tx0)
                    if k > lst[p]:
                        continue
                    dx = x + 0.5 - mx
                    sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
                    if sigma < 0.0:
                        continue
                    vis = np.exp(-sigma)
                    raw = o * vis
                    alpha = min(ALPHA_MAX, raw)
                    if alpha < ALPHA_MIN:
                        continue
                    T[p] = T[p] / (1.0 - alpha)
                    v = gacc[p]
                    for f in range(n_feat):
                        v += feats[g, f] * go[p, f]
                    w = alpha * T[p]
                    d_alpha = T[p] * v - after[p] / (1.0 - alpha)
                    after[p] += w * v
                    for f in range(n_feat):
                        g_feats[k, f] += w * go[p, f]
                    d_raw = d_alpha if raw <= ALPHA_MAX else 0.0
                    d_sigma = -d_raw * raw
                    g_params[k, 0] += -d_sigma * (a * dx + b * dy)
                    g_params[k, 1] += -d_sigma * (b * dx + c * dy)
                    g_params[k, 2] += 0.5 * d_sigma * dx * dx
                    g_params[k, 3] += d_sigma * dx * dy
                    g_params[k, 4] += 0.5 * d_sigma * dy * dy
                    g_params[k, 5] += d_raw * vis
