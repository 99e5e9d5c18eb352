"""The fused CPU path: projection, binning and compositing as numba loops (:mod:`.fused_kernels`), forward and
backward, with the PyTorch path (:mod:`.projection`, :mod:`.tiles`) as reference and fallback (docs/DESIGN.md
"The renderer").

Projection (:func:`project_fused`): the formulas of :func:`~diff4splat.render.projection.project_gaussians` per
Gaussian in float64, and their analytic chain rule (gsplat ``fully_fused_projection_bwd``) summed over cameras;
the quaternion normalisation stays a torch op.

Compositing (:func:`composite_fused`): the rules, formulas and outputs of
:func:`diff4splat.render.tiles.composite_tiles` (gsplat ``rasterize_to_pixels_fwd``/``_bwd``), T and sums in
float64. Tiles in parallel, one thread each; per tile, Gaussians front to back, each over the pixels of its support
box in the tile. The backward walks each tile's list back to front from each pixel's last included Gaussian,
recovering T_i = T_{i+1}/(1 − alpha_i); per-intersection gradient slots are summed per Gaussian serially. Results
do not depend on the thread count.

CPU only (diff4splat/utils/devices.py, the device rule): :func:`composite_fused` and :func:`bin_tiles_fused` refuse
other tensors, :func:`project_fused` hands them to the reference.
"""
from __future__ import annotations

import inspect
import warnings

import numpy as np
import torch
from torch import Tensor

from diff4splat.render.projection import Projection, project_gaussians
from diff4splat.render.tiles import composite_tiles, tile_binning
from diff4splat.scene.quaternions import quat_normalize

__all__ = ["project_fused", "composite_fused", "fused_available", "bin_tiles_fused"]

_UNSET = object()
_KERNELS = _UNSET
_WARNED = [False]


def _kernels():
    """:mod:`diff4splat.render.fused_kernels` (imported on first use), or None without numba."""
    global _KERNELS
    if _KERNELS is _UNSET:
        try:
            from diff4splat.render import fused_kernels  # lazy: numba's import time; absent → the PyTorch path
        except ImportError:
            fused_kernels = None
        _KERNELS = fused_kernels
    return _KERNELS


def fused_available() -> bool:
    """True when numba imports (the fused kernels can be compiled)."""
    return _kernels() is not None


def _np(x: Tensor) -> np.ndarray:
    """The CPU tensor ``x`` as a contiguous numpy array."""
    return x.detach().cpu().contiguous().numpy()


def _check_cpu(what: str, x: Tensor) -> None:
    """Raise ValueError unless ``x`` is a CPU tensor (the fused path is numba on the CPU)."""
    if x.device.type != "cpu":
        raise ValueError(f"{what} runs on the CPU only (numba), got a tensor on {x.device}; use the PyTorch "
                         "tile path (diff4splat.render.tiles, rasterize(compositor='torch'))")


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
        arrays = [_np(x.double()) for x in (means, quats, scales, opacities, viewmats, Ks)]
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
        g = [np.zeros(s) if x is None else _np(x.double()) for s, x in zip(shapes, grads[:5], strict=True)]
        g_comps = np.zeros((C, N)) if grads[6] is None else _np(grads[6].double())
        v = (np.zeros((N, 3)), np.zeros((N, 4)), np.zeros((N, 3)), np.zeros(N))
        kernels = _kernels()
        with kernels.threads(torch.get_num_threads()):
            kernels.project_backward(means, quats, scales, opacities, viewmats, Ks, width, height, eps2d,
                                     antialiased, ctx.radii, *g, g_comps, *v)
        return (*(torch.from_numpy(x).to(ctx.dtype) for x in v), None, None, None, None, None, None, None, None)


_REFERENCE = inspect.signature(project_gaussians)


def project_fused(*args, **kwargs) -> Projection:
    """:func:`~diff4splat.render.projection.project_gaussians` (its signature: arguments, keywords and defaults, its
    :class:`~diff4splat.render.projection.Projection` in ``means``' dtype) by the fused kernels, or by the reference
    itself without numba, for a non-pinhole model, non-CPU tensors or ``viewmats``/``Ks`` requiring gradients.

    Raises:
        TypeError: arguments the reference does not take.
        ValueError: unknown camera model or zero-norm quaternion (the reference's checks).
    """
    bound = _REFERENCE.bind(*args, **kwargs)
    bound.apply_defaults()
    means, quats, scales, opacities, viewmats, Ks, width, height, near_plane, far_plane, eps2d, antialiased, model = (
        bound.arguments.values())  # in the reference's order
    if (model != "pinhole" or not fused_available() or means.device.type != "cpu"
            or viewmats.requires_grad or Ks.requires_grad):
        return project_gaussians(*bound.args, **bound.kwargs)
    means2d, depths, covars2d, conics, opac, radii, comps = _FusedProjection.apply(
        means, quat_normalize(quats), scales, opacities, viewmats, Ks, width, height, near_plane, far_plane, eps2d,
        antialiased)
    return Projection(means2d=means2d, depths=depths, covars2d=covars2d, conics=conics, opacities=opac, radii=radii,
                      compensations=comps if antialiased else None)


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
        kernels = _kernels()
        with kernels.threads(torch.get_num_threads()):
            kernels.forward_kernel(p64, f64, bg, background is not None, _np(ids), _np(offsets), _np(counts),
                                   _np(box), width, height, tile, tiles_x, out, acc, t_final, last, pairs)
        ctx.n_pairs = int(pairs.sum())
        ctx.save_for_backward(params, feats, background, ids, offsets, counts, box)
        ctx.arrays = (p64, f64, bg, t_final, last)
        ctx.sizes = (width, height, tile, tiles_x)
        dtype = params.dtype
        n_pairs = torch.tensor(ctx.n_pairs, device="cpu")  # the fused path is CPU-only, like its inputs
        return torch.from_numpy(out).to(dtype), torch.from_numpy(acc).to(dtype), n_pairs

    @staticmethod
    def backward(ctx, grad_out, grad_acc, _):  # noqa: D102
        params, feats, background, ids, offsets, counts, box = ctx.saved_tensors
        p64, f64, bg, t_final, last = ctx.arrays
        width, height, tile, tiles_x = ctx.sizes
        n_isect = ids.shape[0]
        g_params, g_feats = np.zeros((n_isect, 6)), np.zeros((n_isect, f64.shape[1]))
        kernels = _kernels()
        with kernels.threads(torch.get_num_threads()):
            kernels.backward_kernel(p64, f64, bg, background is not None, _np(ids), _np(offsets), _np(counts),
                                    _np(box), width, height, tile, tiles_x, t_final, last, _np(grad_out.double()),
                                    _np(grad_acc.double()), g_params, g_feats)
        grad_params, grad_feats = np.zeros(params.shape), np.zeros(feats.shape)
        kernels.gather_kernel(_np(ids), g_params, grad_params)
        kernels.gather_kernel(_np(ids), g_feats, grad_feats)
        dtype = params.dtype
        grad_bg = None
        if background is not None and ctx.needs_input_grad[2]:
            t = torch.from_numpy(t_final).to(grad_out.dtype)
            grad_bg = (t[:, None] * grad_out).sum(0)
        return (torch.from_numpy(grad_params).to(dtype), torch.from_numpy(grad_feats).to(dtype), grad_bg, None, None,
                None, None, None, None, None, None)


@torch.no_grad()
def bin_tiles_fused(
    means2d: Tensor,  # (M, 2)
    covars2d: Tensor,  # (M, 3)
    opacities: Tensor,  # (M,)
    depths: Tensor,  # (M,)
    width: int,
    height: int,
    tile_size: int,
) -> dict:
    """:func:`diff4splat.render.tiles.bin_tiles` (same dict) by two kernels: float64 boxes (a float32 box edge can
    differ where the extent rounds across a pixel centre) and a counting sort by tile, each tile's list depth-sorted.

    Raises:
        RuntimeError: numba is not installed (use :func:`~diff4splat.render.tiles.bin_tiles`).
        ValueError: non-CPU tensors.
    """
    _check_cpu("bin_tiles_fused", means2d)
    if not fused_available():
        raise RuntimeError("bin_tiles_fused needs numba (pip install numba); tiles.bin_tiles does the same without")
    tiles_x, tiles_y = -(-width // tile_size), -(-height // tile_size)
    m = means2d.shape[0]
    box, tbox, per_gauss = np.empty((m, 4), np.int64), np.empty((m, 4), np.int64), np.empty(m, np.int64)
    kernels = _kernels()
    with kernels.threads(torch.get_num_threads()):
        # float64 inputs (exact for float32): one compiled signature per kernel (compiling is slow)
        kernels.box_kernel(_np(means2d.double()), _np(covars2d.double()), _np(opacities.double()), width, height,
                           tile_size, box, tbox, per_gauss)
        n_isect = int(per_gauss.sum())
        counts = np.zeros(tiles_x * tiles_y, np.int64)
        flatten_ids, isect_tiles = np.empty(n_isect, np.int64), np.empty(n_isect, np.int64)
        kernels.bin_kernel(tbox, per_gauss, _np(depths.double()), tiles_x, counts, flatten_ids, isect_tiles)
    return tile_binning(tiles_x, tiles_y, *map(torch.from_numpy, (box, per_gauss, flatten_ids, isect_tiles, counts)))


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
    """Composite one camera with the fused kernels; the inputs, outputs and rules of
    :func:`diff4splat.render.tiles.composite_tiles`, which it falls back to (warning once) without numba.

    Raises:
        ValueError: non-CPU tensors.
    """
    _check_cpu("composite_fused", means2d)
    if not fused_available():
        if not _WARNED[0]:
            warnings.warn("numba is not installed: the renderer uses the slower pure-PyTorch tile path "
                          "(pip install numba)", RuntimeWarning, stacklevel=2)
            _WARNED[0] = True
        return composite_tiles(means2d, conics, opacities, depths, feats, covars2d, background, width, height,
                               tile_size)
    info = bin_tiles_fused(means2d.detach(), covars2d.detach(), opacities.detach(), depths.detach(), width, height,
                           tile_size)
    params = torch.cat([means2d, conics, opacities[:, None]], dim=-1)  # (M, 6)
    box = info.pop("box")
    colors, alphas, n_pairs = _FusedComposite.apply(params, feats, background, info["flatten_ids"],
                                                    info["isect_offsets"], info["tile_counts"], box, width, height,
                                                    tile_size, info["tiles_x"])
    info["n_pairs"] = int(n_pairs)
    return colors, alphas, info
