"""The numba kernels of the fused projection (:mod:`diff4splat.render.fused_projection`, which documents it).

One loop over Gaussians (``prange`` over blocks of Gaussians, each block with its own 3×3 scratch matrices;
each Gaussian's cameras in order inside, so sums over cameras do not depend on the thread count) does what
:func:`diff4splat.render.projection.project_gaussians` does with ~100 tensor operations, in float64. The
backward is the chain rule of the same formulas written out; each step names the forward formula it
differentiates. Imported on first use (numba's import time).
"""
from __future__ import annotations

import math

import numpy as np
from numba import prange

from diff4splat.render.fused_kernels import KERNEL, threads
from diff4splat.render.projection import EIGEN_FLOOR, FOV_MARGIN, RADIUS_MAX

__all__ = ["project_forward", "project_backward", "threads"]

_BLOCK = 256
"""Gaussians per parallel work item (one set of scratch matrices each)."""


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
    """det(J Σc Jᵀ) for Σc = vm vmᵀ (vm = Rv·R·diag(s)) as the sum of the squared 2×2 minors of A = J·vm
    (Cauchy–Binet), as :func:`diff4splat.render.projection.project_gaussians`: s00·s11 − s01² cancels the long
    axis's L⁴ of an elongated Gaussian, the minors are products of the axes' own lengths."""
    a0, a1, a2 = (j00 * vm[0, 0] + j02 * vm[2, 0], j00 * vm[0, 1] + j02 * vm[2, 1], j00 * vm[0, 2] + j02 * vm[2, 2])
    b0, b1, b2 = (j11 * vm[1, 0] + j12 * vm[2, 0], j11 * vm[1, 1] + j12 * vm[2, 1], j11 * vm[1, 2] + j12 * vm[2, 2])
    return (a1 * b2 - a2 * b1) ** 2 + (a2 * b0 - a0 * b2) ** 2 + (a0 * b1 - a1 * b0) ** 2


@KERNEL(parallel=True)
def project_forward(means, quats, scales, opacities, viewmats, ks, width, height, near, far, eps2d, antialiased,
                    means2d, depths, covars2d, conics, opac_out, radii, comps):  # pragma: no cover - compiled
    """EWA projection of N Gaussians into C pinhole cameras (blocks of Gaussians in parallel), in float64.

    Inputs (float64): means (N, 3) world units; quats (N, 4) unit wxyz quaternions (normalised by the caller);
    scales (N, 3) standard deviations (not log); opacities (N,); viewmats (C, 4, 4) world-to-camera; ks (C, 3, 3)
    intrinsics in pixels; width, height in pixels; near, far: depth planes; eps2d: dilation added to the 2D
    covariance diagonal (pixels²); antialiased: multiply opacities by the compensation (Mip-Splatting eq. 9).

    Outputs (the caller's zeroed arrays, in the input dtype), written in place at (c, i) for each Gaussian i
    kept by camera c (culled entries stay 0): means2d (C, N, 2) pixels; depths (C, N) camera z; covars2d (C, N, 3)
    = (σxx, σxy, σyy) pixels², dilated; conics (C, N, 3) its inverse (a, b, c); opac_out (C, N); radii (C, N)
    int32 3σ radius in pixels (0 = culled, at most RADIUS_MAX); comps (C, N) compensation (1.0 unless
    ``antialiased``).
    """
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
    """Backward pass of :func:`project_forward` (gsplat ``fully_fused_projection_bwd``), summed over cameras.

    Inputs: the forward's means (N, 3), quats (N, 4), scales (N, 3), opacities (N,), viewmats (C, 4, 4),
    ks (C, 3, 3), width, height, eps2d, antialiased and its radii (C, N) (entries with radius 0 are skipped);
    the output gradients g_means2d (C, N, 2), g_depths (C, N), g_covars2d (C, N, 3), g_conics (C, N, 3),
    g_opac (C, N), g_comps (C, N) (float64, zeros where the output had no gradient).

    Outputs, in place (zeroed by the caller): v_means (N, 3), v_scales (N, 3), v_opac (N,) accumulated over
    cameras; v_quats (N, 4) written per Gaussian (w.r.t. the unit quaternion). No gradients for viewmats or ks.
    """
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
