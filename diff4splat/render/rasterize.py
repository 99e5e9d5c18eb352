"""``rasterize``: the Gaussian rasterizer's entry point (gsplat ``rasterization`` signature), its dispatch and paths.

:func:`rasterize` packs its keywords into one :class:`~diff4splat.render.settings.RasterSettings`, which every
path takes. Which path renders a call is decided by :func:`choose_path` (docs/DESIGN.md "The renderer",
diff4splat/utils/devices.py "the device rule"):

- "ray": a non-pinhole camera model or a camera effect (:func:`diff4splat.render.raytrace.raytrace`), any
  device and dtype;
- "gsplat": pinhole, non-CPU, not float64, gsplat installed, ``compositor=None`` (:func:`rasterize_gsplat`);
- "fused": the numba JIT path (:mod:`diff4splat.render.fused`), CPU tensors only — numpy and numba never see a
  device tensor;
- "torch": the pure-PyTorch tile path (:func:`diff4splat.render.tiles.composite_tiles`), the reference and
  fallback, on every device (the default for non-CPU tensors without gsplat, and for float64 there).

The tile paths and the dense reference :func:`rasterize_dense` are compositors of one pipeline,
:func:`render_pipeline` (validation, projection, colour and depth features, render modes, meta), so they differ
only in how Gaussians are projected and composited. Everything before compositing (SH, gathers) is plain autograd.
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
"""A compositor renders one camera: (means2d (M, 2), conics (M, 3), opacities (M,), depths (M,), feats (M, F),
covars2d (M, 3), background (F,) or None, width, height, tile_size) → (colors (H·W, F), alphas (H·W,), info
dict). Only the M visible Gaussians are passed."""
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
NO_GSPLAT_ENV = "DIFF4SPLAT_NO_GSPLAT"
"""Environment variable: set to a value other than ``0`` to keep gsplat out even where it is installed (the
PyTorch tile path then renders CUDA tensors)."""


@functools.lru_cache(maxsize=1)
def gsplat_available() -> bool:
    """Whether gsplat can render here, checked once per process: the package is installed, torch sees a GPU,
    :data:`NO_GSPLAT_ENV` is unset, and gsplat's CUDA extension loads. gsplat builds that extension on first use
    (then cached by torch's extension cache); when the build or the load fails (no CUDA toolkit, a compiler the
    CUDA release refuses) this warns once and returns False, so renders fall back to the PyTorch tile path instead
    of failing at the first ``rasterize``."""
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
    """Whether gsplat can render a pinhole ``rasterize`` call: ``means`` (N, 3) on a CUDA device and not float64,
    and gsplat importable (:func:`gsplat_available`). Reads only the device and dtype of ``means``;
    :func:`choose_path` makes the whole decision."""
    return means.is_cuda and means.dtype != torch.float64 and gsplat_available()


def choose_path(means: Tensor, camera_model: str = CAMERA_MODEL, camera_params: object = None,
                compositor: str | None = None) -> str:
    """Which path renders a :func:`rasterize` call (a pure decision: nothing is computed or imported).

    Args:
        means: (N, 3) the call's centres; only ``device`` and ``dtype`` are read (a meta tensor will do).
        camera_model, camera_params, compositor: as :func:`rasterize`.

    Returns:
        One of :data:`PATHS`: "ray" for a non-pinhole ``camera_model`` or any ``camera_params`` (every device);
        else "gsplat" for ``compositor=None`` when :func:`use_gsplat` holds (non-CPU, not float64, gsplat
        importable); else the compositor named, or for None :data:`DEFAULT_COMPOSITOR` ("fused") on the CPU and
        :data:`DEVICE_COMPOSITOR` ("torch") elsewhere. An explicit "torch" is honoured on every device (the
        PyTorch reference on CUDA, even with gsplat).

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
        compositor: tile path, "fused" (projection and compositing :mod:`diff4splat.render.fused`; CPU tensors
            only) or "torch" (:mod:`diff4splat.render.projection`, :mod:`diff4splat.render.tiles`: the reference,
            any device); None: gsplat for CUDA tensors when installed, else :data:`DEFAULT_COMPOSITOR` on the CPU,
            :data:`DEVICE_COMPOSITOR` elsewhere (:func:`choose_path`). Same image and gradients either way (float
            rounding).

    Rules (3DGS, Kerbl et al. 2023; gsplat CUDA kernels): EWA projection and culling as
    :func:`diff4splat.render.projection.project_gaussians`; alpha = min(0.99, o·exp(−σ)), skipped
    if σ < 0 or alpha < 1/255; front to back by depth from T = 1, a Gaussian with
    T·(1 − alpha) < 1e-4 stops the pixel and is not included, otherwise it adds alpha·T·feat.
    A Gaussian contributes at every pixel where its alpha ≥ 1/255 (the tiles cover that support,
    like gsplat's opacity-aware boxes), so the image equals :func:`rasterize_dense`'s.

    Precision: computed in the dtype of ``means`` — float16/bfloat16 inputs in float32 (outputs are
    float32 then) — with ``torch.autocast`` turned off inside, forward and backward, so a bfloat16
    autocast region gives exactly the float32 result.

    Backend (:func:`choose_path`): CUDA tensors (not float64) with gsplat installed (extra ``[cuda]``) and
    ``compositor=None`` are rendered by ``gsplat.rasterization`` (:func:`rasterize_gsplat`, which lists the
    differences, e.g. gsplat's 0.999 alpha clamp); other non-CPU tensors by the PyTorch tile
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
    """Brute-force reference renderer, the oracle the tile paths are tested against; same arguments and outputs
    as :func:`rasterize`.

    Every visible Gaussian is evaluated at every pixel (memory O(H·W·N)) by
    :func:`~diff4splat.render.tiles.composite_dense`, which sorts the Gaussians globally by depth and composites
    them one after the other exactly as gsplat's ``rasterize_to_pixels`` kernel loop does. Use for tests and tiny
    images only; ``tile_size`` is accepted for signature compatibility and only reported in ``meta``.

    Returns:
        render_colors (C, H, W, D[+1]), render_alphas (C, H, W, 1), meta (see :func:`rasterize`).

    Raises:
        ValueError: as :func:`rasterize`.
    """
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
    """Validate, project, build per-Gaussian features, composite each camera, apply the render mode.

    Features follow gsplat's ``rasterization``: colours (SH evaluated along mean − camera centre,
    then max(·+0.5, 0)); "D"/"ED" replace them by camera-space depth z, "RGB+D"/"RGB+ED" append it;
    the depth channel's background is 0. "ED" divides the accumulated depth by max(alpha, 1e-10)
    (so it is 0 where alpha is 0). ``means`` … ``height`` as in :func:`rasterize`,
    ``settings`` its keywords (:class:`~diff4splat.render.settings.RasterSettings`);
    ``compositor`` composites one camera (:data:`Compositor`); ``project`` is
    :func:`~diff4splat.render.projection.project_gaussians` or a drop-in replacement with its signature
    (:func:`diff4splat.render.fused.project_fused`).

    Returns:
        render_colors (C, H, W, F), render_alphas (C, H, W, 1), meta (see :func:`rasterize`).

    Raises:
        ValueError: as :func:`~diff4splat.render.settings.validate_inputs`.
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


@full_precision
def rasterize_gsplat(
    means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, colors: Tensor, viewmats: Tensor, Ks: Tensor,
    width: int, height: int, settings: RasterSettings,
) -> tuple[Tensor, Tensor, dict]:
    """Render with gsplat's ``rasterization``, the optional CUDA backend of :func:`rasterize` (its arguments and
    outputs; ``settings`` holds its keywords, :class:`~diff4splat.render.settings.RasterSettings`).

    With the ``[cuda]`` extra installed (``pip install diff4splat[cuda]``, gsplat 1.5.x; written against the
    sources of gsplat 1.4.0 … 1.5.3) and the tensors on a CUDA device, ``rasterize(compositor=None)`` hands
    pinhole calls to gsplat's fused CUDA kernels (Ye et al. 2024, "gsplat: An Open-Source Library for Gaussian
    Splatting"; :func:`choose_path` decides; the PyTorch tile path is the reference and runs on every device).
    Inputs are validated exactly as on the PyTorch path (same ``ValueError`` messages: shapes, devices,
    non-finite values, zero-norm quaternions, modes), then cast to float32 and passed to gsplat with autocast
    off. The argument names, shapes, render modes, rasterize modes and camera model name ("pinhole") are
    gsplat's own, so they are passed through unchanged — except ``backgrounds`` and ``packed`` (below).

    Two choices make the backend version-proof (gsplat 1.4 … 1.5.3):

    * ``packed=False``: gsplat's ``rasterization`` defaults to its packed layout (meta tensors (nnz, …) over the
      visible (camera, Gaussian) pairs); unpacked, ``meta`` has the PyTorch path's layout, indexed
      (camera, Gaussian) — means2d (C, N, 2), depths, opacities (C, N), conics (C, N, 3), radii (C, N) in 1.4 and
      (C, N, 2) per axis from 1.5 — which the callers read (training/fit.py takes ``meta["means2d"][0]`` and
      ``meta["radii"][0]`` for its densification statistics). It costs (C, N) arrays, as the PyTorch projection.
    * Backgrounds are composited here, not by gsplat: gsplat gets ``backgrounds=None`` and the result becomes
      ``colors + (1 − alphas)·bg`` with the background of :func:`~diff4splat.render.settings.mode_backgrounds`
      (the colour for the colour channels, 0 for the depth channel), i.e. T_final·bg, the formula of the PyTorch
      path. gsplat ≥ 1.5 asserts ``backgrounds.shape == image_dims + (channels,)`` in ``rasterize_to_pixels``
      with ``image_dims = means2d.shape[:-2]``, which is () in the packed layout, so any background fails
      ("torch.Size([1, 4])") under gsplat's default; 1.4 wants (C, channels) instead. Compositing here does not
      depend on how a version shapes backgrounds or on the layout, gives the PyTorch path's value (the depth
      channel's 0 background adds exactly 0, so "ED" = Σ w·z / max(alpha, 1e-10) is unchanged) and its
      background gradient by autograd.

    Same as the PyTorch path (checked in the 1.4.0–1.5.3 sources): culling z < near_plane or z > far_plane;
    Σ2d + eps2d·I with compensation sqrt(max(0, det Σ2d / det(Σ2d + eps2d·I))) for "antialiased" (opacity ×
    compensation); gsplat's clamped perspective Jacobian; σ < 0 or alpha < 1/255 skipped; SH (INRIA constants)
    along the normalised mean − camera centre, colour max(SH + 0.5, 0); "ED" divides by max(alpha, 1e-10);
    ``radius_clip`` left at gsplat's 0 (cull radius ≤ 0, as ours).

    Known differences of the gsplat backend from the PyTorch path:
      * alpha is clamped to 0.999 (``min(0.999f, …)`` in ``rasterize_to_pixels``), not 0.99 (INRIA);
      * a pixel stops at next_T ≤ 1e-4 (PyTorch path: < 1e-4; differs only on exact ties);
      * tile bound and image cull. gsplat 1.4 assigns tiles by the 3σ radius ceil(3·sqrt(λmax)) (our radii),
        so where o·exp(−4.5) ≥ 1/255 (o ≳ 0.35) the faint rim between 3σ and the 1/255 contour is dropped,
        which the PyTorch path renders (its tiles cover the opacity-aware box). gsplat ≥ 1.5 passes the
        opacities to the projection: boxes of half-size ceil(min(3.33, sqrt(2 ln(255·o)))·sqrt(Σxx)) (and Σyy;
        1.5.0–1.5.1 also cap by sqrt(λmax)), the opacity-aware support as ours up to float32 rounding, so the
        images agree inside the frame; but gsplat's off-image cull uses that box while ours uses the 3σ box, so
        a Gaussian with o ≳ 0.35 whose centre lies outside the image by between the two is culled by the
        PyTorch path and its rim (alpha < o·exp(−4.5) ≤ 0.011) is drawn by gsplat. Gaussians with
        o (× compensation) < 1/255 are culled by gsplat ≥ 1.5 (radius 0); ours keeps them in ``meta`` but their
        alpha never reaches 1/255 (no image difference);
      * computation is float32 (float64 inputs therefore stay on the PyTorch path), float16/bfloat16 inputs
        are cast to float32 as on the PyTorch path; the camera centre for SH is gsplat's
        ``inverse(viewmat)[:3, 3]`` (ours −Rᵀt: rounding only);
      * ``meta`` holds gsplat's keys (radii, means2d, depths, conics, opacities, tile_width, tile_height,
        tiles_per_gauss, isect_ids, flatten_ids, isect_offsets, …, unpacked: see above; radii are per axis from
        1.5 on and use gsplat's boxes), not ``per_camera``, ``covars2d`` or ``compensations``;
      * gradients are gsplat's (float32 atomics: not bitwise reproducible);
      * gsplat computes det Σ2d as σxx·σyy − σxy² in float32, which cancels an elongated Gaussian's long axis (ours
        sums the squared minors of J·R·S: :func:`~diff4splat.render.projection.project_gaussians`), so a 100 m ×
        1 cm Gaussian may lose a few % of its alpha and a 1 km × 1 cm one be culled there (float64 inputs stay on
        the PyTorch path).

    Args:
        means … height: as :func:`rasterize` (metres, pixels; CUDA tensors): means (N, 3),
            quats (N, 4), scales (N, 3), opacities (N,), colors (N, D) or (N, K, 3) SH, viewmats (C, 4, 4),
            Ks (C, 3, 3).
        settings: the call's keywords; ``settings.backgrounds`` (C, D) or None is composited here, with the
            depth channel's background 0.

    Returns:
        render_colors (C, H, W, D[+1]) float32, render_alphas (C, H, W, 1) float32 = 1 − T_final, gsplat's
        meta dict in the unpacked (C, N, …) layout.

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
