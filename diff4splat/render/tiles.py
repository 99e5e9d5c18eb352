"""The pure-PyTorch compositors: the tile compositor (reference and fallback of :mod:`.fused`, and the path on
every device) and the dense brute-force one (:func:`composite_dense`), the oracle both are tested against.

As gsplat's CUDA pipeline (Kerbl et al. 2023 §6): visible Gaussians binned into tiles in depth order, tiles
composited in chunks over the (pixel, Gaussian) pairs inside each support box, with segmented prefix sums.
"""
from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from diff4splat.render.projection import splat_alpha, splat_sigma, support_extent
from diff4splat.utils.constants import ALPHA_MAX, LOG_T_MIN, T_MIN

__all__ = ["tile_boxes", "bin_tiles", "composite_tiles", "composite_dense", "keep_in_graph", "pair_budget",
           "tile_binning", "PAIR_BUDGET", "PAIR_BUDGET_DEVICE", "CHUNK_PIXELS", "CHUNK_PIXELS_DEVICE"]

PAIR_BUDGET = 1 << 18
"""Most (pixel, Gaussian) pairs composited at once on the CPU (per-pair arrays of a chunk stay cache-sized)."""
PAIR_BUDGET_DEVICE = 1 << 22
"""The same bound on a non-CPU device, larger: there a chunk costs kernel launches and host syncs, not cache misses."""
CHUNK_PIXELS = 1 << 16
"""Most pixels per chunk on the CPU: the pixel keys of a chunk fit 16 bits, for the numpy radix sort."""
CHUNK_PIXELS_DEVICE = 1 << 22
"""Most pixels per chunk on a non-CPU device (keys sorted by ``torch.argsort(stable=True)``)."""


def pair_budget(device: torch.device) -> int:
    """:data:`PAIR_BUDGET` on the CPU, :data:`PAIR_BUDGET_DEVICE` elsewhere."""
    return PAIR_BUDGET if device.type == "cpu" else PAIR_BUDGET_DEVICE


@torch.no_grad()
def tile_boxes(
    means2d: Tensor,  # (M, 2)
    covars2d: Tensor,  # (M, 3)
    opacities: Tensor,  # (M,)
    width: int,
    height: int,
    tile_size: int,
) -> tuple[Tensor, Tensor]:
    """Each Gaussian's pixel box (centres inside its :func:`support_extent`, clipped to the image) and tile count.

    Returns:
        box (M, 4) int64 inclusive (x0, y0, x1, y1); tiles_per_gauss (M,) int64 (0: empty box or never visible).
    """
    ext = support_extent(covars2d, opacities)
    lo = torch.ceil(means2d - ext - 0.5).clamp(min=0)  # first pixel index whose centre can be inside
    hi = torch.floor(means2d + ext - 0.5)
    x0, y0 = lo[:, 0].long(), lo[:, 1].long()
    x1, y1 = hi[:, 0].clamp(max=width - 1).long(), hi[:, 1].clamp(max=height - 1).long()
    ok = (x0 <= x1) & (y0 <= y1) & (ext[:, 0] >= 0)
    tw = torch.where(ok, x1 // tile_size - x0 // tile_size + 1, 0)
    per_gauss = tw * torch.where(ok, y1 // tile_size - y0 // tile_size + 1, 0)
    return torch.stack([x0, y0, x1, y1], -1), per_gauss


@torch.no_grad()
def bin_tiles(
    means2d: Tensor,  # (M, 2)
    covars2d: Tensor,  # (M, 3)
    opacities: Tensor,  # (M,)
    depths: Tensor,  # (M,)
    width: int,
    height: int,
    tile_size: int,
) -> dict:
    """Bin screen Gaussians into the tiles their :func:`tile_boxes` box overlaps, depth-sorted (stable) per tile
    (gsplat ``isect_tiles`` + ``isect_offset_encode``); the image therefore does not depend on ``tile_size``.

    Returns:
        dict — tiles_x, tiles_y; box (M, 4); tiles_per_gauss (M,); flatten_ids (I,) Gaussian of each intersection,
        grouped by tile id ty·tiles_x + tx, depth order inside; isect_tiles (I,) their tile ids; tile_counts (T,),
        isect_offsets (T,) length and start of each tile's list.
    """
    tiles_x, tiles_y = -(-width // tile_size), -(-height // tile_size)
    box, per_gauss = tile_boxes(means2d, covars2d, opacities, width, height, tile_size)
    tx0, ty0 = box[:, 0] // tile_size, box[:, 1] // tile_size
    tw = box[:, 2] // tile_size - tx0 + 1
    order = torch.argsort(depths, stable=True)
    n_sorted = per_gauss[order]
    gid = torch.repeat_interleave(order, n_sorted)
    first = torch.repeat_interleave(torch.cumsum(n_sorted, 0) - n_sorted, n_sorted)  # each Gaussian's first slot
    local = torch.arange(len(gid), device=gid.device) - first
    tw_g = tw[gid]
    tile_ids = (ty0[gid] + local // tw_g) * tiles_x + tx0[gid] + local % tw_g
    perm = torch.argsort(tile_ids, stable=True)
    counts = torch.bincount(tile_ids, minlength=tiles_x * tiles_y)
    return tile_binning(tiles_x, tiles_y, box, per_gauss, gid[perm], tile_ids[perm], counts)


def tile_binning(tiles_x: int, tiles_y: int, box: Tensor, tiles_per_gauss: Tensor, flatten_ids: Tensor,
                 isect_tiles: Tensor, tile_counts: Tensor) -> dict:
    """:func:`bin_tiles`' dict from its parts (shapes there); isect_offsets = exclusive cumsum of tile_counts."""
    return {"tiles_x": tiles_x, "tiles_y": tiles_y, "box": box, "tiles_per_gauss": tiles_per_gauss,
            "flatten_ids": flatten_ids, "isect_tiles": isect_tiles, "tile_counts": tile_counts,
            "isect_offsets": torch.cumsum(tile_counts, 0) - tile_counts}


def _stable_argsort_small(keys: Tensor, n_keys: int) -> Tensor:
    """Stable argsort of int keys in [0, n_keys), (P,) → (P,) int64: numpy's radix sort for CPU 16-bit keys."""
    if keys.device.type == "cpu" and n_keys <= 1 << 16:
        return torch.from_numpy(np.argsort(keys.cpu().numpy().astype(np.uint16), kind="stable"))
    return torch.argsort(keys, stable=True)


class _CompositePairs(torch.autograd.Function):
    """Front-to-back compositing of (pixel, Gaussian) pairs sorted by pixel, then depth.

    Forward: log T before pair i is the per-pixel exclusive prefix sum of log(1 − alpha) (float64); pair i is
    included iff T_i·(1 − alpha_i) ≥ 1e-4; w_i = alpha_i·T_i; colour = Σ w·feat + (1 − Σ w)·bg, alpha = Σ w.
    Backward (gsplat ``rasterize_to_pixels_bwd``): v_i = feat_i·∂L/∂colour + ∂L/∂alpha − bg·∂L/∂colour,
    ∂L/∂alpha_i = T_i·v_i − (Σ_{j>i} w_j v_j)/(1 − alpha_i); ∂/∂o = exp(−σ), ∂/∂σ = −alpha (0 where skipped or
    clamped at 0.99), then the chain rule through σ = ½(a dx² + c dy²) + b dx dy, dx = px − μx.
    """

    @staticmethod
    def forward(ctx, params, feats, background, gid, px, py, pix, n_pix):  # noqa: D102
        # params (M, 6) = [μx, μy, a, b, c, o]; feats (M, F); gid, pix (P,) int64; px, py (P,) pixel centres
        prm = params.t().contiguous().index_select(1, gid)  # (6, P), contiguous rows
        dx, dy = px - prm[0], py - prm[1]
        alpha = splat_alpha(dx, dy, prm[2:5].t(), prm[5])
        counts = torch.bincount(pix, minlength=n_pix)
        starts = torch.cumsum(counts, 0) - counts
        log_1ma = torch.log1p(-alpha)
        excl = torch.cumsum(log_1ma, 0, dtype=torch.float64) - log_1ma  # float64: no cancellation
        log_T = (excl - excl.index_select(0, starts.index_select(0, pix))).to(alpha.dtype)
        incl = (log_T + log_1ma) >= LOG_T_MIN  # next_T ≥ 1e-4
        T = torch.exp(log_T)
        w = torch.where(incl, alpha * T, 0.0)
        f = feats.index_select(0, gid)
        out = feats.new_zeros(n_pix, feats.shape[1]).index_add_(0, pix, w[:, None] * f)
        acc = w.new_zeros(n_pix).index_add_(0, pix, w)
        if background is not None:
            out = out + (1.0 - acc)[:, None] * background
        ctx.save_for_backward(params, feats, background, gid, pix, dx, dy, alpha, T, w, incl, acc, starts + counts - 1)
        return out, acc

    @staticmethod
    def backward(ctx, grad_out, grad_acc):  # noqa: D102
        params, feats, background, gid, pix, dx, dy, alpha, T, w, incl, acc, last = ctx.saved_tensors
        grad_out = grad_out.contiguous()
        g_acc = grad_acc if background is None else grad_acc - (grad_out * background).sum(-1)
        go = grad_out.index_select(0, pix)  # (P, F)
        f = feats.index_select(0, gid)
        v = (f * go).sum(-1) + g_acc.index_select(0, pix)
        cwv = torch.cumsum((w * v).double(), 0)
        after = (cwv.index_select(0, last.index_select(0, pix)) - cwv).to(v.dtype)  # Σ_{j>i} w_j v_j
        d_alpha = torch.where(incl & (alpha > 0), T * v - after / (1.0 - alpha), 0.0)
        prm = params.index_select(0, gid)
        sigma = splat_sigma(dx, dy, prm[:, 2:5])
        vis = torch.exp(-sigma)
        raw = prm[:, 5] * vis
        d_raw = torch.where(raw <= ALPHA_MAX, d_alpha, 0.0)
        d_sigma = -d_raw * raw
        a, b, c = prm[:, 2], prm[:, 3], prm[:, 4]
        grads = torch.stack([-d_sigma * (a * dx + b * dy), -d_sigma * (b * dx + c * dy), 0.5 * d_sigma * dx * dx,
                             d_sigma * dx * dy, 0.5 * d_sigma * dy * dy, d_raw * vis], dim=-1)  # (P, 6)
        grad_params = torch.zeros_like(params).index_add_(0, gid, grads)
        grad_feats = torch.zeros_like(feats).index_add_(0, gid, w[:, None] * go)
        grad_bg = None
        if background is not None and ctx.needs_input_grad[2]:
            grad_bg = ((1.0 - acc)[:, None] * grad_out).sum(0)
        return grad_params, grad_feats, grad_bg, None, None, None, None, None


def composite_tiles(
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
    *,
    budget: int | None = None,
) -> tuple[Tensor, Tensor, dict]:
    """Composite one camera tile by tile (a :data:`diff4splat.render.rasterize.Compositor`); same result as
    :func:`composite_dense`, on the inputs' device.

    Tiles of :func:`bin_tiles` are taken in raster order, in chunks of at most ``budget`` pairs (default
    :func:`pair_budget`) and :data:`CHUNK_PIXELS` pixels (:data:`CHUNK_PIXELS_DEVICE` off the CPU), each chunk's
    pairs stably sorted by pixel and composited by :class:`_CompositePairs`.

    Returns:
        colors (H·W, F), alphas (H·W,), info (the binning of :func:`bin_tiles` without box; n_pairs evaluated).
    """
    device = means2d.device
    budget = pair_budget(device) if budget is None else budget
    dtype, n_feat, n_pix = means2d.dtype, feats.shape[-1], width * height
    s, s2 = tile_size, tile_size * tile_size
    info = bin_tiles(means2d.detach(), covars2d.detach(), opacities.detach(), depths.detach(), width, height, s)
    tiles_x, n_tiles = info["tiles_x"], info["tiles_x"] * info["tiles_y"]
    flat, itile, box = info["flatten_ids"], info["isect_tiles"], info["box"][info["flatten_ids"]]
    # Rectangle of each intersection: the Gaussian's pixel box clipped to its tile.
    tx, ty = itile % tiles_x * s, itile // tiles_x * s
    rx0, ry0 = torch.maximum(box[:, 0], tx), torch.maximum(box[:, 1], ty)
    rw = torch.minimum(box[:, 2], tx + s - 1) - rx0 + 1
    n_rect = rw * (torch.minimum(box[:, 3], ty + s - 1) - ry0 + 1)
    # chunk-independent part of each pair's key: tile's first pixel index + rect offset in the tile
    base = (itile * s2 + (ry0 - ty) * s + (rx0 - tx)).to(torch.int32)
    rw32 = rw.to(torch.int32)
    cum_pairs = torch.cumsum(torch.zeros(n_tiles, dtype=torch.long, device=device).index_add_(0, itile, n_rect), 0)
    cum_isect = torch.cumsum(info["tile_counts"], 0)
    params = torch.cat([means2d, conics, opacities[:, None]], dim=-1)  # (M, 6)
    max_tiles = max(1, (CHUNK_PIXELS if device.type == "cpu" else CHUNK_PIXELS_DEVICE) // s2)
    ids, cols, accs = [], [], []
    t0, done_pairs, n_pairs_total = 0, 0, int(cum_pairs[-1]) if n_tiles else 0
    while t0 < n_tiles and done_pairs < n_pairs_total:
        t1 = int(torch.searchsorted(cum_pairs, done_pairs + budget, right=True))
        t1 = min(max(t1, t0 + 1), t0 + max_tiles, n_tiles)
        i0 = int(cum_isect[t0 - 1]) if t0 else 0
        i1 = int(cum_isect[t1 - 1])
        n_chunk_pix = (t1 - t0) * s2
        n = n_rect[i0:i1]
        # Pixel index within the chunk of every pair (int32): rect origin + (row, column) in the rect.
        start = torch.cumsum(n, 0, dtype=torch.int32) - n.to(torch.int32)
        local = torch.arange(int(n.sum()), dtype=torch.int32, device=device) - torch.repeat_interleave(start, n)
        rw_p = torch.repeat_interleave(rw32[i0:i1], n)
        row = torch.div(local, rw_p, rounding_mode="floor")
        key = torch.repeat_interleave(base[i0:i1] - t0 * s2, n) + row * s + (local - row * rw_p)
        perm = _stable_argsort_small(key, n_chunk_pix)
        key = key[perm].long()
        gid = torch.repeat_interleave(flat[i0:i1], n)[perm]
        q = torch.arange(n_chunk_pix, device=device)
        qt = t0 + q // s2
        qx, qy = qt % tiles_x * s + q % s, qt // tiles_x * s + (q % s2) // s
        col, acc = _CompositePairs.apply(
            params, feats, background, gid, (qx.to(dtype) + 0.5)[key], (qy.to(dtype) + 0.5)[key], key, n_chunk_pix
        )
        inside = (qx < width) & (qy < height)
        ids.append((qy * width + qx)[inside])
        cols.append(col[inside])
        accs.append(acc[inside])
        done_pairs = int(cum_pairs[t1 - 1])
        t0 = t1
    out = means2d.new_zeros(n_pix, n_feat) if background is None else background.expand(n_pix, n_feat)
    acc_img = means2d.new_zeros(n_pix)
    if ids:
        all_ids = torch.cat(ids)
        out = out.index_copy(0, all_ids, torch.cat(cols))
        acc_img = acc_img.index_copy(0, all_ids, torch.cat(accs))
    del info["box"]
    info["n_pairs"] = n_pairs_total
    return out, acc_img, info


def composite_dense(
    means2d: Tensor,  # (M, 2)
    conics: Tensor,  # (M, 3)
    opacities: Tensor,  # (M,)
    depths: Tensor,  # (M,)
    feats: Tensor,  # (M, F)
    covars2d: Tensor,  # (M, 3), unused: every pixel is evaluated
    background: Tensor | None,  # (F,)
    width: int,
    height: int,
    tile_size: int,  # unused: no tiles
) -> tuple[Tensor, Tensor, dict]:
    """Composite one camera by brute force (O(H·W·M) memory; the oracle), Gaussians in stable depth order.

    Per pixel from T = 1, each Gaussian front to back with alpha of :func:`splat_alpha` (0 = skipped):
    next_T = T·(1 − alpha); next_T < 1e-4 stops the pixel without it; else the pixel gains alpha·T·feat and
    T = next_T. Finally colour += T·background, alpha = 1 − T (gsplat ``rasterize_to_pixels_fwd``; 3DGS eq. 3).
    Returns colors (H·W, F), alphas (H·W,), info {}.
    """
    dtype, device = means2d.dtype, means2d.device
    order = torch.argsort(depths, stable=True)
    ys, xs = torch.meshgrid(torch.arange(height, dtype=dtype, device=device) + 0.5,
                            torch.arange(width, dtype=dtype, device=device) + 0.5, indexing="ij")
    px, py = xs.reshape(-1, 1), ys.reshape(-1, 1)  # (P, 1)
    m2, cn, op, ft = means2d[order], conics[order], opacities[order], feats[order]
    alphas = splat_alpha(px - m2[None, :, 0], py - m2[None, :, 1], cn[None], op[None])  # (P, M)
    n_pix = px.shape[0]
    T = torch.ones(n_pix, dtype=dtype, device=device)
    done = torch.zeros(n_pix, dtype=torch.bool, device=device)
    out = torch.zeros(n_pix, feats.shape[-1], dtype=dtype, device=device)
    for i in range(alphas.shape[1]):
        a = alphas[:, i]
        next_T = T * (1.0 - a)
        live = ~done & (a > 0)
        stop = live & (next_T < T_MIN)
        take = live & ~stop
        done = done | stop
        w = torch.where(take, a * T, torch.zeros_like(a))
        out = out + w[:, None] * ft[i]
        T = torch.where(take, next_T, T)
    if background is not None:
        out = out + T[:, None] * background
    return out, 1.0 - T, {}


def keep_in_graph(out: Tensor, *inputs: Tensor | None) -> Tensor:
    """``out``, attached with zero gradient to the graph of ``inputs`` (None skipped) when it is not, so a view that
    sees no Gaussian still backpropagates (as the fused path and gsplat do). The anchor is an empty slice's sum,
    exactly 0, so the values are unchanged."""
    if out.requires_grad or not torch.is_grad_enabled():
        return out
    sources = [t for t in inputs if t is not None and t.requires_grad]
    if not sources:
        return out
    return out + sum(t.reshape(-1)[:0].sum() for t in sources)
