"""The numba kernels of the fused path (:mod:`diff4splat.render.fused` documents the algorithms), all float64.

Projection: blocks of Gaussians in parallel, each Gaussian's cameras in order (sums over cameras do not depend on
the thread count); its backward writes out the chain rule, each step naming the forward formula it differentiates.
Binning and compositing: one camera's tiles in parallel. Imported on first use (an ImportError: no numba).
"""
from __future__ import annotations

import math

import numpy as np
from numba import prange

from diff4splat.render.projection import EIGEN_FLOOR, FOV_MARGIN, RADIUS_MAX
from diff4splat.utils.constants import ALPHA_MAX, ALPHA_MIN, OPACITY_LOG_FLOOR, T_MIN
from diff4splat.utils.jit import KERNEL, threads

__all__ = ["KERNEL", "box_kernel", "bin_kernel", "forward_kernel", "backward_kernel", "gather_kernel",
           "project_forward", "project_backward", "threads"]

_BLOCK = 256
"""Gaussians per parallel work item of the projection (one set of scratch matrices each)."""


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
    """tiles.tile_boxes per Gaussian (in parallel): pixel box ``box``, tile box ``tbox`` and ``per_gauss`` count."""
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
    """The lists of tiles.bin_tiles: a serial counting sort of the intersections by tile, then each tile's list
    stably sorted by depth (tiles in parallel). tbox (M, 4): inclusive tile boxes (tx0, ty0, tx1, ty1)."""
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
    """Forward compositing of one camera, tiles in parallel. Inputs: params (M, 6) = [μx, μy, a, b, c, o]; feats
    (M, F); bg (F,) (zeros, ``has_bg`` False, without one); ids, offsets, counts, box: tiles.bin_tiles' binning.
    Outputs, in place: out (H·W, F) (+ T_final·bg); acc = 1 − T_final; t_final; last (index into ``ids`` of each
    pixel's last included Gaussian, −1: none); pairs (n_tiles,) pairs inside the boxes. Pixel q = y·width + x."""
    n_tiles = counts.shape[0]
    n_feat = feats.shape[1]
    for t in prange(n_tiles):
        tx0, ty0, tw, th = _tile_rect(t, tiles_x, tile, width, height)
        T = np.ones(tile * tile)
        col = np.zeros((tile * tile, n_feat))
        lst = np.full(tile * tile, -1, np.int64)
        done = np.zeros(tile * tile, np.bool_)
        n_done = n_pairs = 0
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
    """Backward of :func:`forward_kernel` (its inputs, t_final and last; grad_out (H·W, F), grad_acc (H·W,)),
    tiles in parallel, lists back to front. Accumulates into the zeroed g_params (I, 6), g_feats (I, F), one row
    per intersection, summed per Gaussian by :func:`gather_kernel`; the background's gradient is the caller's."""
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


@KERNEL(inline="always")
def _mm(a, b, out, ta, tb):  # pragma: no cover - compiled
    """out = op(a) @ op(b) for 3×3 matrices, op = transpose where ta / tb."""
    for r in range(3):
        for c in range(3):
            s = 0.0
            for k in range(3):
                s += (a[k, r] if ta else a[r, k]) * (b[c, k] if tb else b[k, c])
            out[r, c] = s


@KERNEL(inline="always")
def _rotmat(q, r):  # pragma: no cover - compiled
    """r = rotation of the unit wxyz quaternion q (quaternions.quat_to_rotmat)."""
    w, x, y, z = q[0], q[1], q[2], q[3]
    r[0, 0], r[0, 1], r[0, 2] = 1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)
    r[1, 0], r[1, 1], r[1, 2] = 2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)
    r[2, 0], r[2, 1], r[2, 2] = 2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)


@KERNEL(inline="always")
def _camera_frame(rot, s, mean, view, m, cov, tmp, cc):  # pragma: no cover - compiled
    """m = R·diag(s); cov = m mᵀ (3DGS eq. 6); cc = Rv cov Rvᵀ; returns the camera-frame centre Rv μ + t."""
    for r in range(3):
        for k in range(3):
            m[r, k] = rot[r, k] * s[k]
    _mm(m, m, cov, False, True)
    _mm(view[:3, :3], cov, tmp, False, False)
    _mm(tmp, view[:3, :3], cc, False, True)
    x = view[0, 0] * mean[0] + view[0, 1] * mean[1] + view[0, 2] * mean[2] + view[0, 3]
    y = view[1, 0] * mean[0] + view[1, 1] * mean[1] + view[1, 2] * mean[2] + view[1, 3]
    z = view[2, 0] * mean[0] + view[2, 1] * mean[1] + view[2, 2] * mean[2] + view[2, 3]
    return x, y, z


@KERNEL(inline="always")
def _limits(k, width, height):  # pragma: no cover - compiled
    """fx, fy, cx, cy and gsplat's clamp of x/z and y/z: [−(c/f + m·tan½fov), (W − c)/f + m·tan½fov],
    m = FOV_MARGIN (:mod:`diff4splat.render.projection`)."""
    fx, fy, cx, cy = k[0, 0], k[1, 1], k[0, 2], k[1, 2]
    tx, ty = 0.5 * width / fx, 0.5 * height / fy
    mx, my = FOV_MARGIN * tx, FOV_MARGIN * ty
    return (fx, fy, cx, cy, -(cx / fx + mx), (width - cx) / fx + mx, -(cy / fy + my), (height - cy) / fy + my)


@KERNEL(inline="always")
def _screen_cov(cc, j00, j02, j11, j12):  # pragma: no cover - compiled
    """Σ2d = J Σc Jᵀ with J = [[j00, 0, j02], [0, j11, j12]] (EWA eq. 31); returns s00, s01, s10, s11."""
    s00 = j00 * (j00 * cc[0, 0] + j02 * cc[2, 0]) + j02 * (j00 * cc[0, 2] + j02 * cc[2, 2])
    s01 = j11 * (j00 * cc[0, 1] + j02 * cc[2, 1]) + j12 * (j00 * cc[0, 2] + j02 * cc[2, 2])
    s10 = j00 * (j11 * cc[1, 0] + j12 * cc[2, 0]) + j02 * (j11 * cc[1, 2] + j12 * cc[2, 2])
    s11 = j11 * (j11 * cc[1, 1] + j12 * cc[2, 1]) + j12 * (j11 * cc[1, 2] + j12 * cc[2, 2])
    return s00, s01, s10, s11


@KERNEL(inline="always")
def _screen_det(vm, j00, j02, j11, j12):  # pragma: no cover - compiled
    """det(J Σc Jᵀ) for Σc = vm vmᵀ (vm = Rv·R·diag(s)): the sum of the squared 2×2 minors of J·vm (Cauchy–Binet),
    as projection.project_gaussians."""
    a0, a1, a2 = (j00 * vm[0, 0] + j02 * vm[2, 0], j00 * vm[0, 1] + j02 * vm[2, 1], j00 * vm[0, 2] + j02 * vm[2, 2])
    b0, b1, b2 = (j11 * vm[1, 0] + j12 * vm[2, 0], j11 * vm[1, 1] + j12 * vm[2, 1], j11 * vm[1, 2] + j12 * vm[2, 2])
    return (a1 * b2 - a2 * b1) ** 2 + (a2 * b0 - a0 * b2) ** 2 + (a0 * b1 - a1 * b0) ** 2


@KERNEL(parallel=True)
def project_forward(means, quats, scales, opacities, viewmats, ks, width, height, near, far, eps2d, antialiased,
                    means2d, depths, covars2d, conics, opac_out, radii, comps):  # pragma: no cover - compiled
    """EWA projection of N Gaussians into C pinhole cameras, as projection.project_gaussians (its arguments, quats
    unit; near, far the planes). Writes the caller's zeroed arrays at (c, i) for each kept Gaussian: means2d,
    depths, covars2d, conics, opac_out, radii (int32) and comps (1.0 unless ``antialiased``), the Projection's."""
    n_cam, n = viewmats.shape[0], means.shape[0]
    for blk in prange((n + _BLOCK - 1) // _BLOCK):
        rot, m, cov, tmp, cc = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
        for i in range(blk * _BLOCK, min(n, (blk + 1) * _BLOCK)):
            _rotmat(quats[i], rot)
            for c in range(n_cam):
                x, y, z = _camera_frame(rot, scales[i], means[i], viewmats[c], m, cov, tmp, cc)
                if not (near <= z <= far) or z <= 0.0:  # as project_gaussians: near = 0 never divides by 0
                    continue
                fx, fy, cx, cy, xlo, xhi, ylo, yhi = _limits(ks[c], width, height)
                rz = 1.0 / z
                j02 = -fx * min(max(x * rz, xlo), xhi) * rz
                j12 = -fy * min(max(y * rz, ylo), yhi) * rz
                s00, s01, s10, s11 = _screen_cov(cc, fx * rz, j02, fy * rz, j12)
                sxy = 0.5 * (s01 + s10)
                _mm(viewmats[c, :3, :3], m, tmp, False, False)  # Rv·R·diag(s)
                det_orig = _screen_det(tmp, fx * rz, j02, fy * rz, j12)
                det = det_orig + eps2d * (s00 + s11) + eps2d * eps2d
                sxx, syy = s00 + eps2d, s11 + eps2d
                if not det > 0:
                    continue
                b = 0.5 * (sxx + syy)
                radius = np.ceil(3.0 * math.sqrt(max(b + math.sqrt(max(b * b - det, EIGEN_FLOOR)), 0.0)))
                mx, my = fx * x * rz + cx, fy * y * rz + cy
                if not (radius > 0 and mx + radius > 0 and mx - radius < width and my + radius > 0
                        and my - radius < height):
                    continue
                comp = math.sqrt(max(det_orig / det, 0.0)) if antialiased else 1.0
                means2d[c, i, 0], means2d[c, i, 1], depths[c, i] = mx, my, z
                covars2d[c, i, 0], covars2d[c, i, 1], covars2d[c, i, 2] = sxx, sxy, syy
                conics[c, i, 0], conics[c, i, 1], conics[c, i, 2] = syy / det, -sxy / det, sxx / det
                opac_out[c, i] = opacities[i] * comp
                radii[c, i] = np.int32(min(radius, RADIUS_MAX))
                comps[c, i] = comp


@KERNEL(parallel=True)
def project_backward(means, quats, scales, opacities, viewmats, ks, width, height, eps2d, antialiased, radii,
                     g_means2d, g_depths, g_covars2d, g_conics, g_opac, g_comps,
                     v_means, v_quats, v_scales, v_opac):  # pragma: no cover - compiled
    """Backward of :func:`project_forward` (gsplat ``fully_fused_projection_bwd``): from its inputs, radii and the
    outputs' gradients g_* (zeros where none), accumulates v_means, v_scales, v_opac over cameras and writes
    v_quats (w.r.t. the unit quaternion) into the caller's zeroed arrays; no gradients for viewmats or ks."""
    n_cam, n = viewmats.shape[0], means.shape[0]
    for blk in prange((n + _BLOCK - 1) // _BLOCK):
        rot, m, cov, tmp, cc = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
        g_rot, g_cc, g_cov, jm = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((2, 3))
        for i in range(blk * _BLOCK, min(n, (blk + 1) * _BLOCK)):
            _rotmat(quats[i], rot)
            g_rot[:] = 0.0
            for c in range(n_cam):
                if radii[c, i] == 0:
                    continue  # culled: every output is the constant 0
                view = viewmats[c]
                x, y, z = _camera_frame(rot, scales[i], means[i], view, m, cov, tmp, cc)
                fx, fy, cx, cy, xlo, xhi, ylo, yhi = _limits(ks[c], width, height)
                rz = 1.0 / z
                ux, uy = x * rz, y * rz
                dux_dx, dux_dz = (rz, -x * rz * rz) if xlo <= ux <= xhi else (0.0, 0.0)
                duy_dy, duy_dz = (rz, -y * rz * rz) if ylo <= uy <= yhi else (0.0, 0.0)
                ux, uy = min(max(ux, xlo), xhi), min(max(uy, ylo), yhi)
                j00, j11, j02, j12 = fx * rz, fy * rz, -fx * ux * rz, -fy * uy * rz
                s00, s01, s10, s11 = _screen_cov(cc, j00, j02, j11, j12)
                sxy = 0.5 * (s01 + s10)
                _mm(view[:3, :3], m, tmp, False, False)  # Rv·R·diag(s)
                det_orig = _screen_det(tmp, j00, j02, j11, j12)
                det = det_orig + eps2d * (s00 + s11) + eps2d * eps2d
                sxx, syy = s00 + eps2d, s11 + eps2d
                inv = 1.0 / det
                # covars2d = (sxx, sxy, syy)
                gxx, gxy, gyy = g_covars2d[c, i, 0], g_covars2d[c, i, 1], g_covars2d[c, i, 2]
                # conics = (syy, −sxy, sxx) / det, det = sxx·syy − sxy²
                ga, gb, gc = g_conics[c, i, 0], g_conics[c, i, 1], g_conics[c, i, 2]
                g_det = -(ga * syy - gb * sxy + gc * sxx) * inv * inv
                gxx += gc * inv + g_det * syy
                gyy += ga * inv + g_det * sxx
                gxy += -gb * inv - 2.0 * g_det * sxy
                if antialiased:
                    # opacities = o·comp, comp = sqrt(max(0, r)), r = det_orig / det (det_orig undilated)
                    comp = math.sqrt(max(det_orig * inv, 0.0))
                    v_opac[i] += g_opac[c, i] * comp
                    if det_orig * inv > 0.0:
                        g_r = 0.5 * (g_comps[c, i] + g_opac[c, i] * opacities[i]) / comp
                        gxx += g_r * (s11 - det_orig * syy * inv) * inv
                        gyy += g_r * (s00 - det_orig * sxx * inv) * inv
                        gxy += g_r * 2.0 * sxy * (det_orig * inv - 1.0) * inv
                else:
                    v_opac[i] += g_opac[c, i]
                # Σ2d = J Σc Jᵀ read as (s00, ½(s01 + s10), s11): G = [[gxx, ½gxy], [½gxy, gyy]];
                # ∂/∂Σc = Jᵀ G J, ∂/∂J = 2 G J Σc (J's zero entries are constants)
                h00, h01, h11 = gxx, 0.5 * gxy, gyy
                gj0 = (h00 * j00, h01 * j11, h00 * j02 + h01 * j12)  # row 0 of G J
                gj1 = (h01 * j00, h11 * j11, h01 * j02 + h11 * j12)  # row 1 of G J
                jm[0, 0], jm[0, 1], jm[0, 2], jm[1, 0], jm[1, 1], jm[1, 2] = j00, 0.0, j02, 0.0, j11, j12
                for r in range(3):
                    for k in range(3):
                        g_cc[r, k] = (jm[0, r] * (h00 * jm[0, k] + h01 * jm[1, k])
                                      + jm[1, r] * (h01 * jm[0, k] + h11 * jm[1, k]))
                gj_00 = 2.0 * (gj0[0] * cc[0, 0] + gj0[1] * cc[1, 0] + gj0[2] * cc[2, 0])
                gj_02 = 2.0 * (gj0[0] * cc[0, 2] + gj0[1] * cc[1, 2] + gj0[2] * cc[2, 2])
                gj_11 = 2.0 * (gj1[0] * cc[0, 1] + gj1[1] * cc[1, 1] + gj1[2] * cc[2, 1])
                gj_12 = 2.0 * (gj1[0] * cc[0, 2] + gj1[1] * cc[1, 2] + gj1[2] * cc[2, 2])
                # J = [[fx/z, 0, −fx·ux/z], [0, fy/z, −fy·uy/z]], ux = clamp(x/z), uy = clamp(y/z)
                gx = -fx * rz * dux_dx * gj_02
                gy = -fy * rz * duy_dy * gj_12
                gz = (-fx * rz * rz * gj_00 - fy * rz * rz * gj_11 + (fx * ux * rz * rz - fx * rz * dux_dz) * gj_02
                      + (fy * uy * rz * rz - fy * rz * duy_dz) * gj_12)
                # means2d = (fx·x/z + cx, fy·y/z + cy); depths = z
                gmx, gmy = g_means2d[c, i, 0], g_means2d[c, i, 1]
                gx += gmx * fx * rz
                gy += gmy * fy * rz
                gz += -(gmx * fx * x + gmy * fy * y) * rz * rz + g_depths[c, i]
                # (x, y, z) = Rv μ + t
                for k in range(3):
                    v_means[i, k] += view[0, k] * gx + view[1, k] * gy + view[2, k] * gz
                # Σc = Rv Σ Rvᵀ → ∂/∂Σ = Rvᵀ G_Σc Rv; Σ = M Mᵀ → ∂/∂M = (G + Gᵀ) M; M = R·diag(s)
                _mm(view[:3, :3], g_cc, tmp, True, False)
                _mm(tmp, view[:3, :3], g_cov, False, False)
                for r in range(3):
                    for k in range(3):
                        g_m = 0.0
                        for t in range(3):
                            g_m += (g_cov[r, t] + g_cov[t, r]) * m[t, k]
                        v_scales[i, k] += g_m * rot[r, k]
                        g_rot[r, k] += g_m * scales[i, k]
            # R(q) for the unit quaternion q = (w, x, y, z) (quaternions.quat_to_rotmat)
            w, x, y, z = quats[i, 0], quats[i, 1], quats[i, 2], quats[i, 3]
            g = g_rot
            v_quats[i, 0] = 2 * (-z * g[0, 1] + y * g[0, 2] + z * g[1, 0] - x * g[1, 2] - y * g[2, 0] + x * g[2, 1])
            v_quats[i, 1] = 2 * (y * g[0, 1] + z * g[0, 2] + y * g[1, 0] - 2 * x * g[1, 1] - w * g[1, 2]
                                 + z * g[2, 0] + w * g[2, 1] - 2 * x * g[2, 2])
            v_quats[i, 2] = 2 * (-2 * y * g[0, 0] + x * g[0, 1] + w * g[0, 2] + x * g[1, 0] + z * g[1, 2]
                                 - w * g[2, 0] + z * g[2, 1] - 2 * y * g[2, 2])
            v_quats[i, 3] = 2 * (-2 * z * g[0, 0] - w * g[0, 1] + x * g[0, 2] + w * g[1, 0] - 2 * z * g[1, 1]
                                 + y * g[1, 2] + x * g[2, 0] + y * g[2, 1])
