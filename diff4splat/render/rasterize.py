"""``rasterize``: the Gaussian rasterizer's entry point (gsplat ``rasterization`` signature), its dispatch and paths.

:func:`choose_path` picks "ray" (:mod:`.raytrace`), "gsplat" (:func:`rasterize_gsplat`, CUDA), "fused" (:mod:`.fused`,
CPU) or "torch" (:mod:`.tiles`, any device) (docs/DESIGN.md "The renderer"); the tile paths and
:func:`rasterize_dense` are compositors of one pipeline, :func:`render_pipeline`.
"""
from __future__ import annotations

import functools
import importlib.util
import os
import warnings
from collections.abc import Callable

import torch
from torch import Tensor

from diff4splat.render.fused import composite_fused, project_fused
from diff4splat.render.projection import Projection, project_gaussians
from diff4splat.render.raytrace import render_rays
from diff4splat.render.settings import (
    CAMERA_MODEL,
    EPS2D,
    FAR_PLANE,
    NEAR_PLANE,
    RASTERIZE_MODE,
    RENDER_MODE,
    SH_DEGREE,
    TILE_SIZE,
    RasterSettings,
    compute_dtype,
    expected_depth,
    mode_backgrounds,
    validate_inputs,
)
from diff4splat.render.sh import color_features
from diff4splat.render.tiles import composite_dense, composite_tiles, keep_in_graph
from diff4splat.scene.quaternions import quat_normalize
from diff4splat.utils.devices import full_precision

__all__ = [
    "rasterize", "rasterize_dense", "choose_path", "render_pipeline", "rasterize_gsplat", "gsplat_available",
    "use_gsplat", "Compositor", "COMPOSITORS", "DEFAULT_COMPOSITOR", "DEVICE_COMPOSITOR", "PATHS", "NO_GSPLAT_ENV",
]

Compositor = Callable[..., tuple[Tensor, Tensor, dict]]
"""Composites one camera's M visible Gaussians: (means2d (M, 2) pixels, conics (M, 3) 1/pixels², opacities (M,),
depths (M,) metres, feats (M, F), covars2d (M, 3) pixels², background (F,) or None, width, height, tile_size)
→ (colors (H·W, F), alphas (H·W,), info dict)."""
COMPOSITORS = {"fused": (project_fused, composite_fused), "torch": (project_gaussians, composite_tiles)}
"""Tile paths by name: (projection, compositor)."""
DEFAULT_COMPOSITOR = "fused"
"""What ``compositor=None`` uses for CPU tensors (without numba the fused path falls back to "torch")."""
DEVICE_COMPOSITOR = "torch"
"""What ``compositor=None`` uses for non-CPU tensors that gsplat does not take (float64, or gsplat absent)."""
PATHS = ("ray", "gsplat", *COMPOSITORS)
"""The names :func:`choose_path` returns."""
NO_GSPLAT_ENV = "DIFF4SPLAT_NO_GSPLAT"
"""Environment variable: a value other than ``0`` keeps gsplat out even where it is installed."""


@functools.lru_cache(maxsize=1)
def gsplat_available() -> bool:
    """Whether gsplat can render here (checked once per process): installed, a GPU seen, :data:`NO_GSPLAT_ENV`
    unset, and its CUDA extension builds and loads; a failed build or load warns once and gives False."""
    if os.environ.get(NO_GSPLAT_ENV, "0") not in ("", "0"):
        return False
    if importlib.util.find_spec("gsplat") is None or not torch.cuda.is_available():
        return False
    try:
        from gsplat.cuda._backend import _C  # builds the extension the first time
    except Exception as e:  # noqa: BLE001 - any build or load error means: no gsplat here
        _C, why = None, f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}"
    else:
        why = "gsplat reported no CUDA extension"
    if _C is None:
        warnings.warn(f"gsplat is installed but its CUDA extension could not be loaded ({why}); CUDA tensors are "
                      f"rendered by the PyTorch tile path (set {NO_GSPLAT_ENV}=1 to skip gsplat)", stacklevel=2)
        return False
    return True


def use_gsplat(means: Tensor) -> bool:
    """Whether gsplat can render a pinhole call on ``means`` (N, 3): CUDA, not float64, :func:`gsplat_available`."""
    return means.is_cuda and means.dtype != torch.float64 and gsplat_available()


def choose_path(means: Tensor, camera_model: str = CAMERA_MODEL, camera_params: object = None,
                compositor: str | None = None) -> str:
    """Which path renders a :func:`rasterize` call (nothing is computed; only ``means``' device and dtype are read).

    Returns one of :data:`PATHS`: "ray" for a non-pinhole ``camera_model`` or any ``camera_params``; else "gsplat"
    for ``compositor=None`` when :func:`use_gsplat` holds; else the compositor named, or for None
    :data:`DEFAULT_COMPOSITOR` on the CPU and :data:`DEVICE_COMPOSITOR` elsewhere.

    Raises:
        ValueError: ``compositor`` not None/"fused"/"torch", or "fused" with non-CPU ``means``.
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
        if device is not None and use_gsplat(means):
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
        means: (N, 3) centres, metres, world frame.  scales: (N, 3) standard deviations, metres.
        quats: (N, 4) orientations, wxyz, unnormalised (normalised here; zero norm is an error).
        opacities: (N,) in [0, 1].
        colors: (N, D) features composited as given, or with ``sh_degree`` (N, K, 3) SH coefficients,
            K ≥ (sh_degree+1)², colour = max(SH(dir) + 0.5, 0), dir = normalise(mean − camera centre) (:mod:`.sh`).
        viewmats: (C, 4, 4) world-to-camera, OpenCV frame (x right, y down, z forward).
        Ks: (C, 3, 3) pinhole intrinsics, pixels.
        width, height: image size, pixels. Pixel (i, j) is sampled at (j + 0.5, i + 0.5).
        near_plane, far_plane: Gaussians with camera z outside [near_plane, far_plane] (metres) are culled.
        eps2d: screen-space dilation added to Σ2d, pixels².  sh_degree: None, or 0..3 to evaluate SH.
        backgrounds: (C, D) colour behind the Gaussians, added as T_final·bg (0 for the depth channel).
        render_mode: "RGB", "D" (Σ w·z), "ED" (Σ w·z / alpha, 0 where alpha = 0), "RGB+D", "RGB+ED"
            (depth appended as the last channel).
        rasterize_mode: "classic", or "antialiased" (opacity × sqrt(det Σ2d / det(Σ2d + eps2d·I)),
            Mip-Splatting eq. 9, as gsplat).
        camera_model: "pinhole" or "fisheye" (ray path).  tile_size: tile edge, pixels (no effect on results).
        camera_params: None, or a camera effect of :mod:`diff4splat.cameras.lenses` (``ThinLens``, ``FisheyeKB``,
            ``FisheyePolynomial``; fisheye None → equidistant). Any effect or non-pinhole model is rendered by
            :func:`diff4splat.render.raytrace.raytrace`, which lists its differences.
        compositor: "fused" (:mod:`.fused`, CPU tensors only), "torch" (:mod:`.projection`, :mod:`.tiles`, any
            device) or None (:func:`choose_path`). Same image and gradients either way (float rounding).

    Rules (3DGS, Kerbl et al. 2023; gsplat CUDA kernels): projection and culling of
    :func:`diff4splat.render.projection.project_gaussians`; alpha = min(0.99, o·exp(−σ)), skipped if σ < 0 or
    alpha < 1/255; front to back by depth from T = 1, a Gaussian with T·(1 − alpha) < 1e-4 stops the pixel and
    is not included, else it adds alpha·T·feat. Tiles cover each Gaussian's alpha ≥ 1/255 support, so the image
    equals :func:`rasterize_dense`'s. Computed in the dtype of ``means`` (float16/bfloat16 in float32, outputs
    float32 then) with autocast off, forward and backward; the gsplat backend differs as
    :func:`rasterize_gsplat` lists.

    Returns:
        render_colors: (C, H, W, D) for "RGB", (C, H, W, 1) for "D"/"ED", (C, H, W, D + 1) otherwise.
        render_alphas: (C, H, W, 1) = 1 − T_final.
        meta: dict — the :class:`~diff4splat.render.projection.Projection` fields (radii, means2d, depths,
            conics, opacities, compensations, covars2d; (C, N, …)), width, height, tile_size, tile_width,
            tile_height, n_cameras, per_camera: list of C dicts (gaussian_ids of the visible Gaussians,
            tiles_per_gauss, flatten_ids (into gaussian_ids), tile_counts, isect_offsets).

    Raises:
        ValueError: a bad argument (:func:`~diff4splat.render.settings.validate_inputs`), zero-norm quaternions,
            an unknown ``compositor`` or ``compositor="fused"`` with non-CPU tensors.
    """
    settings = RasterSettings(near_plane=near_plane, far_plane=far_plane, eps2d=eps2d, sh_degree=sh_degree,
                              backgrounds=backgrounds, render_mode=render_mode, rasterize_mode=rasterize_mode,
                              camera_model=camera_model, tile_size=tile_size, camera_params=camera_params)
    path = choose_path(means, camera_model, camera_params, compositor)
    args = (means, quats, scales, opacities, colors, viewmats, Ks, width, height, settings)
    if path == "ray":
        return render_rays(*args)
    if path == "gsplat":
        return rasterize_gsplat(*args)
    project, composite = COMPOSITORS[path]
    return render_pipeline(composite, *args, project=project)


def rasterize_dense(
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
) -> tuple[Tensor, Tensor, dict]:
    """Brute-force reference renderer (:func:`~diff4splat.render.tiles.composite_dense`, memory O(H·W·N)), the
    oracle of the tile paths; same arguments, outputs and errors as :func:`rasterize` (``tile_size`` is only
    reported in ``meta``)."""
    settings = RasterSettings(near_plane=near_plane, far_plane=far_plane, eps2d=eps2d, sh_degree=sh_degree,
                              backgrounds=backgrounds, render_mode=render_mode, rasterize_mode=rasterize_mode,
                              camera_model=camera_model, tile_size=tile_size)
    return render_pipeline(composite_dense, means, quats, scales, opacities, colors, viewmats, Ks, width, height,
                           settings)


@full_precision
def render_pipeline(
    compositor: Compositor,
    means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, colors: Tensor,
    viewmats: Tensor, Ks: Tensor, width: int, height: int, settings: RasterSettings, *,
    project: Callable[..., Projection] = project_gaussians,
) -> tuple[Tensor, Tensor, dict]:
    """Validate, project (``project``: ``project_gaussians`` or a drop-in), build the features of gsplat's
    ``rasterization`` (colours, then camera z for a depth mode, background 0), composite each camera with
    ``compositor`` and apply the render mode. Arguments, outputs and errors: :func:`rasterize`'s, with its keywords
    in ``settings``."""
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


@full_precision
def rasterize_gsplat(
    means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, colors: Tensor, viewmats: Tensor, Ks: Tensor,
    width: int, height: int, settings: RasterSettings,
) -> tuple[Tensor, Tensor, dict]:
    """Render with gsplat's ``rasterization`` (Ye et al. 2024; extra ``[cuda]``, gsplat 1.4.0 … 1.5.3), the CUDA
    backend of :func:`rasterize`: its arguments, outputs (float32) and checks, with its keywords in ``settings``.

    Called with ``packed=False``, so ``meta`` keeps the (camera, Gaussian) layout of the PyTorch path (gsplat's
    keys; radii per axis from 1.5; no ``per_camera``, ``covars2d`` or ``compensations``), and with
    ``backgrounds=None``: the background is added here as (1 − alpha)·bg (:func:`mode_backgrounds`), the PyTorch
    path's formula, independent of how a gsplat release shapes backgrounds.

    Differences from the PyTorch path:
      * alpha is clamped to 0.999 (gsplat), not 0.99 (INRIA); a pixel stops at next_T ≤ 1e-4 (ours < 1e-4);
      * tiles: gsplat 1.4 bins by the 3σ radius, dropping the faint rim between 3σ and the 1/255 contour where
        o ≳ 0.35; ≥ 1.5 uses opacity-aware boxes as ours, but culls off-image Gaussians by that box (ours: the
        3σ box), so a rim (alpha ≤ 0.011) of a Gaussian just outside the image is drawn by gsplat only;
        Gaussians with o (× compensation) < 1/255 are culled by gsplat ≥ 1.5 (no image difference);
      * float32 throughout (float64 inputs stay on the PyTorch path); the SH camera centre is
        ``inverse(viewmat)[:3, 3]`` (ours −Rᵀt); gradients use float32 atomics (not bitwise reproducible);
      * det Σ2d = σxx·σyy − σxy² in float32 cancels a very elongated Gaussian's long axis (ours: squared minors),
        so a 100 m × 1 cm Gaussian may lose a few % of its alpha and a 1 km × 1 cm one be culled.

    Raises:
        ValueError: as :func:`rasterize`.
        ImportError: gsplat is not installed.
    """
    validate_inputs(means, quats, scales, opacities, colors, viewmats, Ks, width, height, settings)
    quat_normalize(quats)  # zero-norm → ValueError naming quats (gsplat would return NaN)
    from gsplat import rasterization  # optional dependency (extra [cuda])

    dtype = compute_dtype(means.dtype)
    cast = lambda t: t.to(dtype)  # noqa: E731
    render_colors, render_alphas, meta = rasterization(
        cast(means), cast(quats), cast(scales), cast(opacities), cast(colors), cast(viewmats), cast(Ks), width, height,
        **{**settings.gsplat_keywords(), "backgrounds": None}, packed=False,
    )
    # (C, F): colour, then 0 for depth
    bgs = mode_backgrounds(settings.backgrounds, settings.render_mode, viewmats.shape[0], dtype)
    if bgs is not None:
        render_colors = render_colors + (1.0 - render_alphas) * bgs[:, None, None, :]
    return render_colors, render_alphas, meta
