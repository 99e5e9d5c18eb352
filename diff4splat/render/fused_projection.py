"""Fused CPU projection: :func:`~diff4splat.render.projection.project_gaussians` as one JIT loop, forward and backward.

The same EWA projection and culling as the PyTorch reference (which it falls back to), computed per Gaussian by
numba kernels (:mod:`.fused_projection_kernels`) in float64: rotation from the unit quaternion, Σ = R S Sᵀ Rᵀ
(3DGS eq. 6), camera frame, gsplat's clamped perspective Jacobian (EWA splatting eq. 29–31), dilation,
compensation (Mip-Splatting eq. 9), conic, 3σ radius and the culls. The backward pass is the analytic chain
rule of those formulas (gsplat ``fully_fused_projection_bwd``), summed over cameras per Gaussian. The
quaternion normalisation stays a torch op (autograd differentiates it), so its zero-norm error is the
reference's.

Scope: pinhole CPU tensors whose ``viewmats`` and ``Ks`` need no gradient; anything else (camera gradients,
CUDA tensors, no numba) uses the reference, so results never depend on which path ran beyond float rounding.
"""
from __future__ import annotations

import inspect

import numpy as np
import torch
from torch import Tensor

from diff4splat.quaternions import quat_normalize
from diff4splat.render.fused import fused_available
from diff4splat.render.projection import Projection, project_gaussians

__all__ = ["project_fused"]

def _kernels():
    """:mod:`.fused_projection_kernels`, imported on first use (keeps numba out of ``import diff4splat``)."""
    from diff4splat.render import fused_projection_kernels  # lazy: numba, ~0.2 s at start-up

    return fused_projection_kernels


def _np64(x: Tensor) -> np.ndarray:
    """The CPU tensor ``x`` as a contiguous float64 numpy array (``.cpu()``: a no-op, this path is CPU-only)."""
    return x.detach().cpu().to(torch.float64).contiguous().numpy()


class _FusedProjection(torch.autograd.Function):
    """Autograd wrapper of the two kernels: (means, unit quats, scales, opacities) → the Projection tensors."""

    @staticmethod
    def forward(ctx, means, quats, scales, opacities, viewmats, Ks, width, height, near, far, eps2d,  # noqa: D102
                antialiased):
        C, N = viewmats.shape[0], means.shape[0]
        # outputs written in the input dtype (no copies)
        dt = torch.empty(0, dtype=means.dtype, device="cpu").numpy().dtype  # device: a CPU tensor, its dtype read
        out = [np.zeros(shape, dt) for shape in ((C, N, 2), (C, N), (C, N, 3), (C, N, 3), (C, N))]
        radii, comps = np.zeros((C, N), np.int32), np.zeros((C, N), dt)
        arrays = [_np64(x) for x in (means, quats, scales, opacities, viewmats, Ks)]
        kernels = _kernels()
        with kernels.threads(torch.get_num_threads()):
            # the planes rounded to the input dtype, as the reference compares z with them in that dtype
            planes = [float(torch.tensor(p, dtype=means.dtype, device="cpu")) for p in (near, far)]
            kernels.project_forward(*arrays, width, height, *planes, float(eps2d), antialiased, *out, radii, comps)
        ctx.arrays, ctx.radii = arrays, radii
        ctx.sizes = (width, height, float(eps2d), antialiased)
        ctx.dtype = means.dtype
        radii_t = torch.from_numpy(radii)
        ctx.mark_non_differentiable(radii_t)
        return (*(torch.from_numpy(x) for x in out), radii_t, torch.from_numpy(comps))

    @staticmethod
    def backward(ctx, *grads):  # noqa: D102
        means, quats, scales, opacities, viewmats, Ks = ctx.arrays
        width, height, eps2d, antialiased = ctx.sizes
        C, N = viewmats.shape[0], means.shape[0]
        shapes = ((C, N, 2), (C, N), (C, N, 3), (C, N, 3), (C, N))
        g = [np.zeros(s) if x is None else _np64(x) for s, x in zip(shapes, grads[:5], strict=True)]
        g_comps = np.zeros((C, N)) if grads[6] is None else _np64(grads[6])
        v = (np.zeros((N, 3)), np.zeros((N, 4)), np.zeros((N, 3)), np.zeros(N))
        kernels = _kernels()
        with kernels.threads(torch.get_num_threads()):
            kernels.project_backward(means, quats, scales, opacities, viewmats, Ks, width, height, eps2d,
                                     antialiased, ctx.radii, *g, g_comps, *v)
        return (*(torch.from_numpy(x).to(ctx.dtype) for x in v), None, None, None, None, None, None, None, None)


_REFERENCE = inspect.signature(project_gaussians)


def project_fused(
    means: Tensor,  # (N, 3)
    quats: Tensor,  # (N, 4)
    scales: Tensor,  # (N, 3)
    opacities: Tensor,  # (N,)
    viewmats: Tensor,  # (C, 4, 4)
    Ks: Tensor,  # (C, 3, 3)
    width: int,
    height: int,
    **settings,
) -> Projection:
    """:func:`~diff4splat.render.projection.project_gaussians` by the fused kernels (module docstring), or by that
    reference where they do not apply: no numba, a non-pinhole model, non-CPU tensors, or ``viewmats``/``Ks``
    requiring gradients. ``settings`` are the reference's keyword arguments with its defaults (``near_plane``,
    ``far_plane``, ``eps2d``, ``antialiased``, ``camera_model``): its signature is the one home of both.

    Returns:
        :class:`~diff4splat.render.projection.Projection`, in the dtype of ``means`` (computed in float64).

    Raises:
        TypeError: a keyword the reference does not take.
        ValueError: unknown camera model or zero-norm quaternion (from the reference's checks).
    """
    bound = _REFERENCE.bind(means, quats, scales, opacities, viewmats, Ks, width, height, **settings)
    bound.apply_defaults()
    a = bound.arguments
    if (a["camera_model"] != "pinhole" or not fused_available() or means.device.type != "cpu"
            or viewmats.requires_grad or Ks.requires_grad):
        return project_gaussians(*bound.args, **bound.kwargs)
    near_plane, far_plane, eps2d, antialiased = a["near_plane"], a["far_plane"], a["eps2d"], a["antialiased"]
    means2d, depths, covars2d, conics, opac, radii, comps = _FusedProjection.apply(
        means, quat_normalize(quats), scales, opacities, viewmats, Ks, width, height, near_plane, far_plane, eps2d,
        antialiased)
    return Projection(means2d=means2d, depths=depths, covars2d=covars2d, conics=conics, opacities=opac, radii=radii,
                      compensations=comps if antialiased else None)
