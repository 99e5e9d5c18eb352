"""The stages of the render pipeline shared by the tile path, the dense reference and the ray path.

:func:`render_pipeline` validates (:mod:`.validate`), projects (:mod:`.projection`), builds the
per-Gaussian features (:func:`color_features`, depth channel), hands each camera's visible Gaussians to
a compositor and applies the render mode (:func:`mode_backgrounds`, :func:`expected_depth`). The tile
rasterizers (:func:`diff4splat.render.fused.composite_fused`, :func:`diff4splat.render.tiles.composite_tiles`)
and the dense reference (:func:`diff4splat.render.reference.composite_dense`) are compositors of this one
pipeline, so they differ only in how Gaussians are composited. :func:`compute_dtype` and
:func:`diff4splat.devices.full_precision` fix the precision every path computes in.
"""
from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from diff4splat.cameras.path import camera_centers
from diff4splat.devices import full_precision
from diff4splat.render.projection import Projection, project_gaussians
from diff4splat.render.settings import RasterSettings
from diff4splat.render.sh import sh_to_color, spherical_harmonics
from diff4splat.render.validate import validate_inputs

__all__ = [
    "Compositor", "LOW_PRECISION", "compute_dtype", "color_features", "mode_backgrounds",
    "expected_depth", "render_pipeline",
]

# A compositor renders one camera: (means2d (M,2), conics (M,3), opacities (M,), depths (M,),
# feats (M,F), covars2d (M,3), background (F,) or None, width, height, tile_size)
#   -> (colors (H*W, F), alphas (H*W,), info dict).  Only the M visible Gaussians are passed.
Compositor = Callable[..., tuple[Tensor, Tensor, dict]]

LOW_PRECISION = (torch.float16, torch.bfloat16)
"""Input dtypes the renderer computes in float32 instead (outputs are float32 then)."""


def compute_dtype(dtype: torch.dtype) -> torch.dtype:
    """The dtype the renderer computes in for inputs of ``dtype``: float16/bfloat16 → float32, else itself."""
    return torch.float32 if dtype in LOW_PRECISION else dtype


# Under ``torch.autocast(dtype=bfloat16)`` the projection's matmuls/einsums would run in bfloat16 (8-bit mantissa:
# depth errors of metres, wrong culling); the renderer runs under :func:`diff4splat.devices.full_precision` and
# computes in the dtype of its inputs (float32 for float16/bfloat16 inputs, :func:`compute_dtype`), as gsplat's
# kernels compute in float32 whatever the autocast state.


def color_features(
    colors: Tensor,  # (N, D) or (N, K, 3) SH
    means: Tensor,  # (N, 3)
    viewmats: Tensor,  # (C, 4, 4)
    sh_degree: int | None,
) -> Tensor:
    """Per-camera colour features (C, N, D): ``colors`` as given, or with ``sh_degree`` the INRIA
    SH colour max(SH(dir) + 0.5, 0) along dir = mean − camera centre (centre −Rᵀt, gsplat
    ``rasterization``; :mod:`diff4splat.render.sh`)."""
    C, N = viewmats.shape[0], means.shape[0]
    if sh_degree is None:
        return colors[None].expand(C, N, colors.shape[-1])
    campos = camera_centers(viewmats)  # (C, 3)
    dirs = means[None] - campos[:, None]  # (C, N, 3)
    return sh_to_color(spherical_harmonics(sh_degree, dirs, colors[None]))


def mode_backgrounds(backgrounds: Tensor | None, render_mode: str, C: int, dtype: torch.dtype) -> Tensor | None:
    """Backgrounds (C, F) of the composited features for ``render_mode``: the colour for "RGB",
    0 for the depth channel ("D"/"ED" → (C, 1) zeros, "RGB+D"/"RGB+ED" → colour then 0); None stays None."""
    if backgrounds is None:
        return None
    bgs = backgrounds.to(dtype)
    if render_mode in ("D", "ED"):
        return bgs.new_zeros(C, 1)
    if render_mode != "RGB":
        return torch.cat([bgs, bgs.new_zeros(C, 1)], dim=-1)
    return bgs


def expected_depth(render_colors: Tensor, render_alphas: Tensor, render_mode: str) -> Tensor:
    """For "ED"/"RGB+ED", divide the accumulated depth (last channel) by max(alpha, 1e-10), so it is
    0 where alpha is 0; other modes are returned unchanged. (C, H, W, F), (C, H, W, 1) → (C, H, W, F)."""
    if render_mode not in ("ED", "RGB+ED"):
        return render_colors
    return torch.cat([render_colors[..., :-1], render_colors[..., -1:] / render_alphas.clamp(min=1e-10)], dim=-1)


def keep_in_graph(out: Tensor, *inputs: Tensor | None) -> Tensor:
    """``out`` itself, or ``out`` attached to the autograd graph of ``inputs`` with zero gradient when it is not.

    A view in which no Gaussian is visible composites nothing, so the PyTorch compositors' image would be a
    detached zero/background tensor and ``loss.backward()`` would raise; the fused path and gsplat keep their
    outputs attached. The anchor is an empty slice's sum (exactly 0, and 0 even beside inf), so ``out``'s values
    are unchanged.

    Args:
        out: a rendered output, any shape.
        inputs: the tensors it was computed from, any shapes (None entries skipped).

    Returns:
        ``out``'s values and shape, requiring grad when any input does and grad mode is on.
    """
    if out.requires_grad or not torch.is_grad_enabled():
        return out
    sources = [t for t in inputs if t is not None and t.requires_grad]
    if not sources:
        return out
    return out + sum(t.reshape(-1)[:0].sum() for t in sources)


@full_precision
def render_pipeline(
    compositor: Compositor,
    means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, colors: Tensor,
    viewmats: Tensor, Ks: Tensor, width: int, height: int, settings: RasterSettings, *,
    project: Callable[..., Projection] = project_gaussians,
) -> tuple[Tensor, Tensor, dict]:
    """Validate, project, build per-Gaussian features, composite each camera, apply the render mode.

    Features follow gsplat's ``rasterization``: colours (SH evaluated along mean − camera centre,
    then max(·+0.5, 0)); "D"/"ED" replace them by camera-space depth z, "RGB+D"/"RGB+ED" append it;
    the depth channel's background is 0. "ED" divides the accumulated depth by max(alpha, 1e-10)
    (so it is 0 where alpha is 0). ``means`` … ``height`` as in :func:`diff4splat.render.rasterize`,
    ``settings`` its keywords (:class:`~diff4splat.render.settings.RasterSettings`);
    ``compositor`` composites one camera (:data:`Compositor`); ``project`` is
    :func:`~diff4splat.render.projection.project_gaussians` or a drop-in replacement with its signature
    (:func:`diff4splat.render.fused_projection.project_fused`).

    Returns:
        render_colors (C, H, W, F), render_alphas (C, H, W, 1), meta (see :func:`diff4splat.render.rasterize`).

    Raises:
        ValueError: as :func:`~diff4splat.render.validate.validate_inputs`.
    """
    validate_inputs(means, quats, scales, opacities, colors, viewmats, Ks, width, height, settings)
    sh_degree, render_mode, tile_size = settings.sh_degree, settings.render_mode, settings.tile_size
    dtype = compute_dtype(means.dtype)  # autocast is off here (full_precision)
    means, quats, scales, opacities = means.to(dtype), quats.to(dtype), scales.to(dtype), opacities.to(dtype)
    viewmats, Ks = viewmats.to(dtype), Ks.to(dtype)
    proj = project(means, quats, scales, opacities, viewmats, Ks, width, height, **settings.projection_keywords())
    C, N = proj.depths.shape
    feats = []
    if render_mode in ("RGB", "RGB+D", "RGB+ED"):
        feats.append(color_features(colors.to(dtype), means, viewmats, sh_degree))
    if render_mode != "RGB":
        feats.append(proj.depths[..., None])
    feats = torch.cat(feats, dim=-1)  # (C, N, F)
    bgs = mode_backgrounds(settings.backgrounds, render_mode, C, dtype)

    out_colors, out_alphas, infos = [], [], []
    for c in range(C):
        vis = torch.nonzero(proj.radii[c] > 0).squeeze(1)
        sel = slice(None) if len(vis) == N else vis  # every Gaussian visible: views of camera c's rows, no gathers
        col, alpha, info = compositor(
            proj.means2d[c, sel], proj.conics[c, sel], proj.opacities[c, sel], proj.depths[c, sel],
            feats[c, sel], proj.covars2d[c, sel], None if bgs is None else bgs[c], width, height, tile_size,
        )
        info["gaussian_ids"] = vis
        anchors = (feats, proj.means2d, proj.conics, proj.opacities)  # attached even when camera c sees nothing
        out_colors.append(keep_in_graph(col, *anchors).reshape(height, width, -1))
        out_alphas.append(keep_in_graph(alpha, *anchors).reshape(height, width, 1))
        infos.append(info)
    render_alphas = torch.stack(out_alphas)
    render_colors = expected_depth(torch.stack(out_colors), render_alphas, render_mode)
    meta = {
        "radii": proj.radii, "means2d": proj.means2d, "depths": proj.depths, "conics": proj.conics,
        "opacities": proj.opacities, "compensations": proj.compensations, "covars2d": proj.covars2d,
        "width": width, "height": height, "tile_size": tile_size, "n_cameras": C,
        "tile_width": -(-width // tile_size), "tile_height": -(-height // tile_size),
        "per_camera": infos,
    }
    return render_colors, render_alphas, meta
