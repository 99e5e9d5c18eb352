"""Fused CPU compositor: one JIT-compiled loop over each tile's (Gaussian, pixel) pairs, forward and backward.

The same compositor as :func:`diff4splat.render.tiles.composite_tiles` (the pure-PyTorch path, kept as
the reference and the fallback) — same tile binning (:func:`~diff4splat.render.tiles.bin_tiles`), same
3DGS rules, same outputs — but each pair's data is touched once instead of through ~40 tensor passes.

Per tile (tiles in parallel, ``numba.prange``; a tile is one thread's work, so the result does not depend on
the thread count), Gaussians are visited front to back in the tile's depth-sorted list, and for each the
pixels of its support box inside the tile (gsplat ``rasterize_to_pixels_fwd``, with the loops swapped so a
pair is evaluated only inside the box): σ = ½(a dx² + c dy²) + b dx dy, skipped if σ < 0; alpha =
min(0.99, o·exp(−σ)), skipped if < 1/255; a pixel stops before the Gaussian that would take its
transmittance T below 1e-4; otherwise it adds w = alpha·T times the features and T ← T·(1 − alpha).
T and the sums are float64. The backward pass (gsplat ``rasterize_to_pixels_bwd``) walks each tile's list
back to front from each pixel's last included Gaussian, recovering T_i = T_{i+1}/(1 − alpha_i), with
∂L/∂alpha_i = T_i·v_i − (Σ_{j>i} w_j v_j)/(1 − alpha_i), v_i = feat_i·∂L/∂colour + ∂L/∂alpha − bg·∂L/∂colour,
and writes each pair's gradient into its intersection's own slot; slots are summed per Gaussian afterwards
(``index_add_`` in intersection order), so the backward is deterministic too.

numba (a PyPI wheel, no compiler needed) compiles the kernels on first use and caches them on disk. Without
numba the tile path is used, with one warning.
"""
from __future__ import annotations

import warnings

import numpy as np
import torch
from torch import Tensor

from diff4splat.constants import ALPHA_MAX, ALPHA_MIN, T_MIN
from diff4splat.render.tiles import bin_tiles, composite_tiles

__all__ = ["composite_fused", "fused_available"]

try:  # optional at import time: the tile path is the fallback
    import numba
    from numba import njit, prange
except ImportError:  # pragma: no cover - exercised by monkeypatching fused_available in the tests
    numba = None
else:
    import os

    if "NUMBA_THREADING_LAYER" not in os.environ:
        # numba's own thread pool: its OpenMP layer shares libgomp with torch and resets torch's thread count
        # (torch.set_num_threads(1) read back 2 after one parallel launch)
        numba.config.THREADING_LAYER = "workqueue"

_WARNED = [False]


def fused_available() -> bool:
    """True when numba imports (the fused kernels can be compiled)."""
    return numba is not None


if numba is not None:

    @njit(cache=True, inline="always")
    def _tile_rect(t, tiles_x, tile, width, height):  # pragma: no cover - compiled
        """Origin (x, y) and size (w, h) of tile t, clipped to the image."""
        tx0 = (t % tiles_x) * tile
        ty0 = (t // tiles_x) * tile
        return tx0, ty0, min(tile, width - tx0), min(tile, height - ty0)

    @njit(cache=True, inline="always")
    def _clip_box(box, g, tx0, ty0, tw, th):  # pragma: no cover - compiled
        """Gaussian g's inclusive pixel box (x0, y0, x1, y1) clipped to the tile (empty when x0 > x1 or y0 > y1)."""
        return max(box[g, 0], tx0), max(box[g, 1], ty0), min(box[g, 2], tx0 + tw - 1), min(box[g, 3], ty0 + th - 1)

    @njit(parallel=True, cache=True)
    def _forward_kernel(params, feats, bg, has_bg, ids, offsets, counts, box, width, height, tile, tiles_x,
                        out, acc, t_final, last, pairs):  # pragma: no cover - compiled
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

    @njit(parallel=True, cache=True)
    def _backward_kernel(params, feats, bg, has_bg, ids, offsets, counts, box, width, height, tile, tiles_x,
                         t_final, last, grad_out, grad_acc, g_params, g_feats):  # pragma: no cover - compiled
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


def _np(x: Tensor) -> np.ndarray:
    return x.detach().contiguous().numpy()


class _FusedComposite(torch.autograd.Function):
    """Autograd wrapper of the two kernels: inputs params (M, 6) = [μx, μy, a, b, c, o], feats (M, F),
    background (F,) or None, and the binning; outputs colors (H·W, F), alphas (H·W,)."""

    @staticmethod
    def forward(ctx, params, feats, background, ids, offsets, counts, box, width, height, tile, tiles_x):  # noqa: D102
        n_pix, n_feat = width * height, feats.shape[1]
        p64, f64 = _np(params.double()), _np(feats.double())
        bg = np.zeros(n_feat) if background is None else _np(background.double())
        out, acc = np.empty((n_pix, n_feat)), np.empty(n_pix)
        t_final, last = np.empty(n_pix), np.empty(n_pix, np.int64)
        pairs = np.zeros(counts.shape[0], np.int64)
        _forward_kernel(p64, f64, bg, background is not None, _np(ids), _np(offsets), _np(counts), _np(box),
                        width, height, tile, tiles_x, out, acc, t_final, last, pairs)
        ctx.n_pairs = int(pairs.sum())
        ctx.save_for_backward(params, feats, background, ids, offsets, counts, box)
        ctx.arrays = (p64, f64, bg, t_final, last)
        ctx.sizes = (width, height, tile, tiles_x)
        dtype = params.dtype
        return torch.from_numpy(out).to(dtype), torch.from_numpy(acc).to(dtype), torch.tensor(ctx.n_pairs)

    @staticmethod
    def backward(ctx, grad_out, grad_acc, _):  # noqa: D102
        params, feats, background, ids, offsets, counts, box = ctx.saved_tensors
        p64, f64, bg, t_final, last = ctx.arrays
        width, height, tile, tiles_x = ctx.sizes
        n_isect = ids.shape[0]
        g_params, g_feats = np.zeros((n_isect, 6)), np.zeros((n_isect, f64.shape[1]))
        _backward_kernel(p64, f64, bg, background is not None, _np(ids), _np(offsets), _np(counts), _np(box),
                         width, height, tile, tiles_x, t_final, last, _np(grad_out.double()),
                         _np(grad_acc.double()), g_params, g_feats)
        dtype = params.dtype
        grad_params = torch.zeros(params.shape, dtype=torch.float64).index_add_(0, ids, torch.from_numpy(g_params))
        grad_feats = torch.zeros(feats.shape, dtype=torch.float64).index_add_(0, ids, torch.from_numpy(g_feats))
        grad_bg = None
        if background is not None and ctx.needs_input_grad[2]:
            t = torch.from_numpy(t_final).to(grad_out.dtype)
            grad_bg = (t[:, None] * grad_out).sum(0)
        return (grad_params.to(dtype), grad_feats.to(dtype), grad_bg, None, None, None, None, None, None, None,
                None)


def composite_fused(
    means2d: Tensor,  # (M, 2)
    conics: Tensor,  # (M, 3)
    opacities: Tensor,  # (M,)
    depths: Tensor,  # (M,)
    feats: Tensor,  # (M, F)
    covars2d: Tensor,  # (M, 3)
    background: Tensor | None,  # (F,)
    width: int,
    height: int,
    tile_size: int,
) -> tuple[Tensor, Tensor, dict]:
    """Composite one camera with the fused kernels (module docstring); the same inputs, outputs and rules as
    :func:`diff4splat.render.tiles.composite_tiles`, which it falls back to (warning once) without numba.

    Returns:
        colors (H·W, F), alphas (H·W,) = 1 − T_final, info dict (the binning of :func:`bin_tiles`;
        n_pairs = pairs inside the support boxes).
    """
    if not fused_available():
        if not _WARNED[0]:
            warnings.warn("numba is not installed: the renderer uses the slower pure-PyTorch tile path "
                          "(pip install numba)", RuntimeWarning, stacklevel=2)
            _WARNED[0] = True
        return composite_tiles(means2d, conics, opacities, depths, feats, covars2d, background, width, height,
                               tile_size)
    numba.set_num_threads(max(1, min(torch.get_num_threads(), numba.config.NUMBA_NUM_THREADS)))
    info = bin_tiles(means2d.detach(), covars2d.detach(), opacities.detach(), depths.detach(), width, height,
                     tile_size)
    params = torch.cat([means2d, conics, opacities[:, None]], dim=-1)  # (M, 6)
    box = info.pop("box")
    colors, alphas, n_pairs = _FusedComposite.apply(params, feats, background, info["flatten_ids"],
                                                    info["isect_offsets"], info["tile_counts"], box, width, height,
                                                    tile_size, info["tiles_x"])
    info["n_pairs"] = int(n_pairs)
    return colors, alphas, info
