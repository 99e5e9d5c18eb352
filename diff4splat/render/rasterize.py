"""``rasterize``: the Gaussian rasterizer's entry point (gsplat ``rasterization`` signature), and its dispatch.

Same rules and outputs as the dense reference (:mod:`diff4splat.render.reference`): all are compositors of
:func:`diff4splat.render.stages.render_pipeline`. Which path renders a call is decided by :func:`choose_path`
(docs/DESIGN.md "The renderer", diff4splat/devices.py "the device rule"):

- "ray": a non-pinhole camera model or a camera effect (:func:`diff4splat.render.raytrace.raytrace`), any
  device and dtype;
- "gsplat": pinhole, non-CPU, not float64, gsplat installed, ``compositor=None``
  (:mod:`diff4splat.render.gsplat_backend`);
- "fused": the numba JIT path (:func:`diff4splat.render.fused.composite_fused`), CPU tensors only — numpy and
  numba never see a device tensor;
- "torch": the pure-PyTorch tile path (:func:`diff4splat.render.tiles.composite_tiles`), the reference and
  fallback, on every device (the default for non-CPU tensors without gsplat, and for float64 there).

Everything before compositing (projection, SH, gathers) is plain autograd. :func:`rasterize` packs its keywords
into one :class:`~diff4splat.render.settings.RasterSettings`, which every path takes.
"""
from __future__ import annotations

import functools

from torch import Tensor

from diff4splat.render.defaults import (
    CAMERA_MODEL,
    EPS2D,
    FAR_PLANE,
    NEAR_PLANE,
    RASTERIZE_MODE,
    RENDER_MODE,
    SH_DEGREE,
    TILE_SIZE,
)
from diff4splat.render.fused import composite_fused
from diff4splat.render.fused_projection import project_fused
from diff4splat.render.gsplat_backend import rasterize_gsplat, use_gsplat
from diff4splat.render.projection import project_gaussians
from diff4splat.render.raytrace import render_rays
from diff4splat.render.settings import RasterSettings
from diff4splat.render.stages import render_pipeline
from diff4splat.render.tiles import composite_tiles

__all__ = ["rasterize", "choose_path", "COMPOSITORS", "DEFAULT_COMPOSITOR", "DEVICE_COMPOSITOR", "PATHS"]

COMPOSITORS = {"fused": (project_fused, composite_fused), "torch": (project_gaussians, composite_tiles)}
"""Tile paths by name, (projection, compositor): the fused JIT loops (numba, CPU only) and the pure-PyTorch
reference (any device)."""
DEFAULT_COMPOSITOR = "fused"
"""What ``compositor=None`` uses for CPU tensors (the fused path falls back to "torch", warning once, without
numba)."""
DEVICE_COMPOSITOR = "torch"
"""What ``compositor=None`` uses for non-CPU tensors that gsplat does not take (float64, or gsplat absent)."""
PATHS = ("ray", "gsplat", *COMPOSITORS)
"""The names :func:`choose_path` returns."""


def choose_path(means: Tensor, camera_model: str = CAMERA_MODEL, camera_params: object = None,
                compositor: str | None = None) -> str:
    """Which path renders a :func:`rasterize` call (a pure decision: nothing is computed or imported).

    Args:
        means: (N, 3) the call's centres; only ``device`` and ``dtype`` are read (a meta tensor will do).
        camera_model, camera_params, compositor: as :func:`rasterize`.

    Returns:
        One of :data:`PATHS`: "ray" for a non-pinhole ``camera_model`` or any ``camera_params`` (every device);
        else "gsplat" for ``compositor=None`` when :func:`~diff4splat.render.gsplat_backend.use_gsplat` holds
        (non-CPU, not float64, gsplat importable); else the compositor named, or for None
        :data:`DEFAULT_COMPOSITOR` ("fused") on the CPU and :data:`DEVICE_COMPOSITOR` ("torch") elsewhere.
        An explicit "torch" is honoured on every device (the PyTorch reference on CUDA, even with gsplat).

    Raises:
        ValueError: ``compositor`` not None/"fused"/"torch"; or "fused" with non-CPU ``means`` (numba runs on
            the CPU only: pass ``compositor="torch"`` or None).
    """
    if compositor is not None and compositor not in COMPOSITORS:
        raise ValueError(f"compositor must be one of {sorted(COMPOSITORS)} or None, got {compositor!r}")
    if camera_model != "pinhole" or camera_params is not None:  # camera effects only when asked for
        return "ray"
    device = getattr(means, "device", None)  # not a tensor: the input validation of the path says so
    on_cpu = device is None or device.type == "cpu"
    if compositor == "fused" and not on_cpu:
        raise ValueError(f"compositor='fused' runs on the CPU only (numba), got tensors on {device}; "
                         "use compositor='torch' or None (gsplat when installed, else the PyTorch tile path)")
    if compositor is None:
        if device is not None and use_gsplat(means, camera_model):
            return "gsplat"
        return DEFAULT_COMPOSITOR if on_cpu else DEVICE_COMPOSITOR
    return compositor


def rasterize(
    means: Tensor,  # (N, 3)
    quats: Tensor,  # (N, 4)
    scales: Tensor,  # (N, 3)
    opacities: Tensor,  # (N,)
    colors: Tensor,  # (N, D) or (N, K, 3) with sh_degree
    viewmats: Tensor,  # (C, 4, 4)
    Ks: Tensor,  # (C, 3, 3)
    width: int,
    height: int,
    *,
    near_plane: float = NEAR_PLANE,
    far_plane: float = FAR_PLANE,
    eps2d: float = EPS2D,
    sh_degree: int | None = SH_DEGREE,
    backgrounds: Tensor | None = None,
    render_mode: str = RENDER_MODE,
    rasterize_mode: str = RASTERIZE_MODE,
    camera_model: str = CAMERA_MODEL,
    tile_size: int = TILE_SIZE,
    camera_params: object = None,
    compositor: str | None = None,
) -> tuple[Tensor, Tensor, dict]:
    """Render 3D Gaussians into C cameras (gsplat ``rasterization`` signature) on the tensors' device.

    Args:
        means: (N, 3) centres, metres, world frame.
        quats: (N, 4) orientations, wxyz, unnormalised (normalised here; zero norm is an error).
        scales: (N, 3) standard deviations, metres.
        opacities: (N,) in (0, 1).
        colors: (N, D) features composited as given (any D), or with ``sh_degree`` set,
            (N, K, 3) SH coefficients, K ≥ (sh_degree+1)², colour = max(SH(dir) + 0.5, 0) with
            dir = normalise(mean − camera centre) (INRIA convention, :mod:`diff4splat.render.sh`).
        viewmats: (C, 4, 4) world-to-camera, OpenCV frame (x right, y down, z forward).
        Ks: (C, 3, 3) pinhole intrinsics, pixels.
        width, height: image size, pixels. Pixel (i, j) is sampled at (j + 0.5, i + 0.5).
        near_plane, far_plane: Gaussians with camera z outside [near_plane, far_plane] (metres) are
            culled.
        eps2d: screen-space dilation added to Σ2d, pixels².
        sh_degree: None, or 0..3 to evaluate SH.
        backgrounds: (C, D) colour behind the Gaussians, added as T_final·bg (0 for the depth channel).
        render_mode: "RGB", "D" (Σ w·z), "ED" (Σ w·z / alpha, 0 where alpha = 0), "RGB+D", "RGB+ED"
            (depth appended as the last channel).
        rasterize_mode: "classic", or "antialiased" (opacity × sqrt(det Σ2d / det(Σ2d + eps2d·I)),
            Mip-Splatting eq. 9, as gsplat).
        camera_model: "pinhole" (tile path) or "fisheye" (ray path).
        tile_size: tile edge, pixels; a performance knob (results do not depend on it).
        camera_params: None (plain pinhole: this tile path), or a camera effect of
            :mod:`diff4splat.cameras.lenses` — ``ThinLens`` (pinhole depth of field), ``FisheyeKB`` or
            ``FisheyePolynomial`` (fisheye; None → equidistant). Any non-pinhole model or effect is
            rendered by the ray path :func:`diff4splat.render.raytrace.raytrace` (its docstring lists
            the differences: exact ray response, eps2d ignored, hits ordered along the ray, meta
            keys). Rolling shutter needs a dynamic scene: :func:`diff4splat.render.render_rolling_shutter`.
        compositor: tile path, "fused" (projection :mod:`diff4splat.render.fused_projection`, compositing
            :mod:`diff4splat.render.fused`; CPU tensors only) or "torch" (:mod:`diff4splat.render.projection`,
            :mod:`diff4splat.render.tiles`: the reference, any device); None: gsplat for CUDA tensors when
            installed, else :data:`DEFAULT_COMPOSITOR` on the CPU, :data:`DEVICE_COMPOSITOR` elsewhere
            (:func:`choose_path`). Same image and gradients either way (float rounding;
            tests/test_render_fused.py, test_render_fused_projection.py, test_render_devices.py).

    Rules (3DGS, Kerbl et al. 2023; gsplat CUDA kernels): EWA projection and culling as
    :func:`diff4splat.render.projection.project_gaussians`; alpha = min(0.99, o·exp(−σ)), skipped
    if σ < 0 or alpha < 1/255; front to back by depth from T = 1, a Gaussian with
    T·(1 − alpha) < 1e-4 stops the pixel and is not included, otherwise it adds alpha·T·feat.
    A Gaussian contributes at every pixel where its alpha ≥ 1/255 (the tiles cover that support,
    like gsplat's opacity-aware boxes), so the image equals :func:`rasterize_dense`'s.

    Precision: computed in the dtype of ``means`` — float16/bfloat16 inputs in float32 (outputs are
    float32 then) — with ``torch.autocast`` turned off inside, forward and backward, so a bfloat16
    autocast region gives exactly the float32 result (tolerances: tests/test_render_stability.py).

    Backend (:func:`choose_path`): CUDA tensors (not float64) with gsplat installed (extra ``[cuda]``) and
    ``compositor=None`` are rendered by ``gsplat.rasterization`` (:mod:`diff4splat.render.gsplat_backend`,
    which lists the differences, e.g. gsplat's 0.999 alpha clamp); other non-CPU tensors by the PyTorch tile
    path on their device; CPU tensors by the fused path. Outputs are on the device of ``means``.

    Returns:
        render_colors: (C, H, W, D) for "RGB", (C, H, W, 1) for "D"/"ED", (C, H, W, D + 1) otherwise.
        render_alphas: (C, H, W, 1) = 1 − T_final.
        meta: dict — radii (C, N) int32 3σ radius (0 = culled), means2d (C, N, 2) pixels,
            depths (C, N) metres, conics (C, N, 3), opacities (C, N) used (with compensation),
            compensations (C, N) or None, covars2d (C, N, 3), width, height, tile_size, tile_width,
            tile_height, n_cameras, per_camera: list of C dicts (gaussian_ids of the visible
            Gaussians, tiles_per_gauss, flatten_ids (into gaussian_ids), tile_counts, isect_offsets).

    Raises:
        ValueError: wrong shapes (naming the argument), non-finite inputs (naming the tensor),
            zero-norm quaternions, unknown render/rasterize mode or camera model, bad sizes, tensors on
            different devices, an unknown ``compositor`` or ``compositor="fused"`` with non-CPU tensors.
    """
    settings = RasterSettings(near_plane=near_plane, far_plane=far_plane, eps2d=eps2d, sh_degree=sh_degree,
                              backgrounds=backgrounds, render_mode=render_mode, rasterize_mode=rasterize_mode,
                              camera_model=camera_model, tile_size=tile_size, camera_params=camera_params)
    path = choose_path(means, camera_model, camera_params, compositor)
    if path == "ray":
        backend = render_rays
    elif path == "gsplat":
        backend = rasterize_gsplat
    else:
        project, composite = COMPOSITORS[path]
        backend = functools.partial(render_pipeline, composite, project=project)
    return backend(means, quats, scales, opacities, colors, viewmats, Ks, width, height, settings)
