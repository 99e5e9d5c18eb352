"""Optional CUDA backend: gsplat's ``rasterization`` serving :func:`diff4splat.render.rasterize` calls.

With the ``[cuda]`` extra installed (``pip install diff4splat[cuda]``, gsplat 1.5.x; written against the
sources of gsplat 1.4.0 … 1.5.3) and the tensors on a CUDA device, ``rasterize(compositor=None)`` hands
pinhole calls to gsplat's fused CUDA kernels (Ye et al. 2024, "gsplat: An Open-Source Library for Gaussian
Splatting"); otherwise the PyTorch paths run (docs/DESIGN.md, "The renderer": the PyTorch tile path is the
reference and runs on every device; :func:`diff4splat.render.rasterize.choose_path` decides). The argument
names, shapes, render modes ("RGB", "D", "ED", "RGB+D", "RGB+ED"), rasterize modes ("classic",
"antialiased") and camera model name ("pinhole") are gsplat's own, so they are passed through unchanged
after the same input validation — except ``backgrounds`` and ``packed`` (below).

Two choices make the backend version-proof (gsplat 1.4 … 1.5.3):

* ``packed=False``: gsplat's ``rasterization`` defaults to its packed layout (meta tensors (nnz, …) over the
  visible (camera, Gaussian) pairs); unpacked, ``meta`` has the PyTorch path's layout, indexed
  (camera, Gaussian) — means2d (C, N, 2), depths, opacities (C, N), conics (C, N, 3), radii (C, N) in 1.4 and
  (C, N, 2) per axis from 1.5 — which the callers read (training/fit.py takes ``meta["means2d"][0]`` and
  ``meta["radii"][0]`` for its densification statistics). It costs (C, N) arrays, as the PyTorch projection.
* Backgrounds are composited here, not by gsplat: gsplat gets ``backgrounds=None`` and the result becomes
  ``colors + (1 − alphas)·bg`` with the background of :func:`~diff4splat.render.stages.mode_backgrounds`
  (the colour for the colour channels, 0 for the depth channel), i.e. T_final·bg, the formula of the PyTorch
  path. gsplat ≥ 1.5 asserts ``backgrounds.shape == image_dims + (channels,)`` in ``rasterize_to_pixels``
  with ``image_dims = means2d.shape[:-2]``, which is () in the packed layout, so any background failed
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
"""
from __future__ import annotations

import functools
import importlib.util
import os
import warnings

import torch
from torch import Tensor

from diff4splat.devices import full_precision
from diff4splat.quaternions import quat_normalize
from diff4splat.render.defaults import CAMERA_MODEL
from diff4splat.render.settings import RasterSettings
from diff4splat.render.stages import compute_dtype, mode_backgrounds
from diff4splat.render.validate import validate_inputs

__all__ = ["gsplat_available", "use_gsplat", "rasterize_gsplat", "NO_GSPLAT_ENV"]


NO_GSPLAT_ENV = "DIFF4SPLAT_NO_GSPLAT"
"""Environment variable: set to a value other than ``0`` to keep gsplat out even where it is installed (the
PyTorch tile path then renders CUDA tensors)."""


@functools.lru_cache(maxsize=1)
def gsplat_available() -> bool:
    """Whether gsplat can render here, checked once per process: the package is installed, torch sees a GPU,
    :data:`NO_GSPLAT_ENV` is unset, and gsplat's CUDA extension loads. gsplat builds that extension on first use
    (about 85 s on an H100, then cached by torch's extension cache); when the build or the load fails (no CUDA
    toolkit, a compiler the CUDA release refuses) this warns once and returns False, so renders fall back to the
    PyTorch tile path instead of failing at the first ``rasterize``."""
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


def use_gsplat(means: Tensor, camera_model: str = CAMERA_MODEL) -> bool:
    """Whether gsplat can render a ``rasterize`` call: ``means`` on a CUDA device and not float64, a pinhole
    camera (other camera models go through the ray path), and gsplat importable. Reads only the device and
    dtype of ``means`` (N, 3); :func:`diff4splat.render.rasterize.choose_path` makes the whole decision."""
    return (means.is_cuda and means.dtype != torch.float64 and camera_model == "pinhole"
            and gsplat_available())


@full_precision
def rasterize_gsplat(
    means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, colors: Tensor, viewmats: Tensor, Ks: Tensor,
    width: int, height: int, settings: RasterSettings,
) -> tuple[Tensor, Tensor, dict]:
    """Render with ``gsplat.rasterization``; arguments and outputs as :func:`diff4splat.render.rasterize`,
    whose keywords ``settings`` holds (:class:`~diff4splat.render.settings.RasterSettings`).

    Inputs are validated exactly as on the PyTorch path (same ``ValueError`` messages: shapes, devices,
    non-finite values, zero-norm quaternions, modes), then cast to float32 and passed to gsplat with autocast
    off, ``packed=False`` and without ``backgrounds``, which are composited afterwards as T_final·bg (module
    docstring, which also lists the differences of the result).

    Args:
        means … height: as :func:`diff4splat.render.rasterize` (metres, pixels; CUDA tensors): means (N, 3),
            quats (N, 4), scales (N, 3), opacities (N,), colors (N, D) or (N, K, 3) SH, viewmats (C, 4, 4),
            Ks (C, 3, 3).
        settings: the call's keywords; ``settings.backgrounds`` (C, D) or None is composited here, with the
            depth channel's background 0.

    Returns:
        render_colors (C, H, W, D[+1]) float32, render_alphas (C, H, W, 1) float32 = 1 − T_final, gsplat's
        meta dict in the unpacked (C, N, …) layout.

    Raises:
        ValueError: as :func:`diff4splat.render.rasterize`.
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
