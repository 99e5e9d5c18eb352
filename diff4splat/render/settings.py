"""The renderer's settings: their defaults (the one home of each), :class:`RasterSettings` and their checks.

The defaults are gsplat's ``rasterization`` defaults (1.4.0 … 1.5.3) except :data:`RENDER_MODE` ("RGB+ED", gsplat
"RGB"). Why one settings object travels behind the entry points: docs/DESIGN.md "The renderer".
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from diff4splat.render.sh import num_sh_bases
from diff4splat.scene.quaternions import ROTATION_TOL, rotation_errors
from diff4splat.utils.checks import check_finite, check_positive_int
from diff4splat.utils.constants import CAMERA_MODEL

__all__ = [
    "NEAR_PLANE", "FAR_PLANE", "EPS2D", "SH_DEGREE", "RENDER_MODE", "RASTERIZE_MODE", "CAMERA_MODEL", "TILE_SIZE",
    "BACKGROUND", "GSPLAT_KEYWORDS", "RasterSettings", "RENDER_MODES", "RASTERIZE_MODES", "VIEWMAT_TOL",
    "validate_inputs", "LOW_PRECISION", "compute_dtype", "mode_backgrounds", "expected_depth",
]

NEAR_PLANE = 0.01
"""Gaussians (or ray hits) nearer than this, metres along the camera z (the ray), are culled (gsplat 0.01)."""
FAR_PLANE = 1e10
"""Gaussians (or ray hits) farther than this, metres, are culled (gsplat 1e10)."""
EPS2D = 0.3
"""Screen-space dilation added to each projected covariance, pixels² (gsplat / INRIA 0.3)."""
SH_DEGREE = None
"""``colors`` are composited as given unless an SH degree is named (gsplat None)."""
RENDER_MODE = "RGB+ED"
"""Colour plus expected depth as the last channel (gsplat's default is "RGB"; this project's is "RGB+ED")."""
RASTERIZE_MODE = "classic"
"""No Mip-Splatting opacity compensation (gsplat "classic")."""
# CAMERA_MODEL: pinhole (gsplat "pinhole"), at home in diff4splat.utils.constants (the camera models default to it)
TILE_SIZE = 16
"""Tile edge, pixels (gsplat 16); a performance knob, the image does not depend on it."""
BACKGROUND = (0.0, 0.0, 0.0)
"""RGB in [0, 1] behind the Gaussians for the scene renderers (render_path, render_rolling_shutter)."""

GSPLAT_KEYWORDS = ("near_plane", "far_plane", "eps2d", "sh_degree", "backgrounds", "render_mode", "rasterize_mode",
                   "camera_model", "tile_size")
"""The fields of :class:`RasterSettings` that are gsplat ``rasterization`` keywords (all but ``camera_params``)."""


@dataclass(frozen=True, eq=False)
class RasterSettings:
    """A render call's keywords (everything but the Gaussians, cameras and image size), as
    :func:`diff4splat.render.rasterize` documents them. Stored unchecked (:func:`validate_inputs` checks them where
    a render starts); compared by identity (``backgrounds`` is a tensor)."""

    near_plane: float = NEAR_PLANE
    far_plane: float = FAR_PLANE
    eps2d: float = EPS2D
    sh_degree: int | None = SH_DEGREE
    backgrounds: Tensor | None = None
    render_mode: str = RENDER_MODE
    rasterize_mode: str = RASTERIZE_MODE
    camera_model: str = CAMERA_MODEL
    tile_size: int = TILE_SIZE
    camera_params: object = None

    @property
    def antialiased(self) -> bool:
        """``rasterize_mode == "antialiased"`` (Mip-Splatting opacity compensation)."""
        return self.rasterize_mode == "antialiased"

    def gsplat_keywords(self) -> dict:
        """{name: value} for :data:`GSPLAT_KEYWORDS` (gsplat ``rasterization``'s keyword arguments)."""
        return {name: getattr(self, name) for name in GSPLAT_KEYWORDS}

    def projection_keywords(self) -> dict:
        """The keyword arguments of :func:`diff4splat.render.projection.project_gaussians` (and ``project_fused``)."""
        return {"near_plane": self.near_plane, "far_plane": self.far_plane, "eps2d": self.eps2d,
                "antialiased": self.antialiased, "camera_model": self.camera_model}


RENDER_MODES = ("RGB", "D", "ED", "RGB+D", "RGB+ED")
"""gsplat's render modes: colour, accumulated depth, expected depth, colour + either depth."""
RASTERIZE_MODES = ("classic", "antialiased")
"""gsplat's rasterize modes (antialiased: Mip-Splatting opacity compensation)."""
VIEWMAT_TOL = {torch.float64: ROTATION_TOL, torch.float32: ROTATION_TOL, torch.float16: 1e-2, torch.bfloat16: 2e-2}
"""Largest :func:`~diff4splat.scene.quaternions.rotation_errors` accepted in viewmats, per dtype (rounding passes)."""


def _check_shape(name: str, t: Tensor, shape: tuple) -> None:
    """Raise ValueError naming ``name`` unless ``t`` has ``shape`` (None = any size)."""
    if not isinstance(t, Tensor):
        raise ValueError(f"{name} must be a torch.Tensor, got {type(t).__name__}")
    ok = t.dim() == len(shape) and all(s is None or s == d for s, d in zip(shape, t.shape, strict=False))
    if not ok:
        want = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"
        raise ValueError(f"{name} must have shape {want}, got {tuple(t.shape)}")


def validate_inputs(
    means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, colors: Tensor, viewmats: Tensor, Ks: Tensor,
    width: int, height: int, settings: RasterSettings, *, camera_models: tuple[str, ...] = ("pinhole",),
) -> None:
    """Check every argument of a render call (every entry point calls this, so each gives the same message).

    ``means`` … ``height`` as :func:`diff4splat.render.rasterize`, ``settings`` its keywords (``camera_params`` is
    the ray path's to check); ``camera_models``: those the calling path renders.

    Checked, in order: shapes (means (N, 3), quats (N, 4), scales (N, 3), opacities (N,), colors (N, D) or
    (N, K ≥ (sh_degree+1)², 3), viewmats (C ≥ 1, 4, 4), Ks (C, 3, 3), backgrounds (C, D)); every tensor on
    ``means``' device; width, height, tile_size positive ints (pixels); 0 ≤ near_plane < far_plane (metres); eps2d
    finite ≥ 0 (pixels²); modes and camera model known; tensors floating point and finite; opacities in [0, 1],
    scales ≥ 0; Ks pinhole (fx, fy > 0, no skew, last row (0, 0, 1)); viewmats rigid (RᵀR = I within
    :data:`VIEWMAT_TOL`, last row (0, 0, 0, 1)).

    Raises:
        ValueError: naming the first bad argument and its value (or shape).
    """
    sh_degree, backgrounds, tile_size = settings.sh_degree, settings.backgrounds, settings.tile_size
    near_plane, far_plane, eps2d = settings.near_plane, settings.far_plane, settings.eps2d
    render_mode, rasterize_mode, camera_model = settings.render_mode, settings.rasterize_mode, settings.camera_model
    _check_shape("means", means, (None, 3))
    n = means.shape[0]
    _check_shape("quats", quats, (n, 4))
    _check_shape("scales", scales, (n, 3))
    _check_shape("opacities", opacities, (n,))
    if sh_degree is None:
        _check_shape("colors", colors, (n, None))
    else:
        k = num_sh_bases(sh_degree)
        _check_shape("colors", colors, (n, None, 3))
        if colors.shape[1] < k:
            raise ValueError(f"colors holds {colors.shape[1]} SH coefficients, sh_degree={sh_degree} needs {k}")
    _check_shape("viewmats", viewmats, (None, 4, 4))
    c = viewmats.shape[0]
    if c == 0:
        raise ValueError("viewmats holds no camera (shape (0, 4, 4)); render at least one")
    _check_shape("Ks", Ks, (c, 3, 3))
    if backgrounds is not None:
        _check_shape("backgrounds", backgrounds, (c, colors.shape[-1]))
    tensors = {"means": means, "quats": quats, "scales": scales, "opacities": opacities, "colors": colors,
               "viewmats": viewmats, "Ks": Ks, "backgrounds": backgrounds}
    for name, t in tensors.items():
        if t is not None and t.device != means.device:
            raise ValueError(f"{name} is on {t.device} but means on {means.device}: pass every tensor on one device")
    check_positive_int("width", width, "pixels")
    check_positive_int("height", height, "pixels")
    check_positive_int("tile_size", tile_size, "pixels")
    if not 0 <= near_plane < far_plane:
        raise ValueError(f"need 0 <= near_plane < far_plane, got near_plane={near_plane}, far_plane={far_plane}")
    if isinstance(eps2d, bool) or not isinstance(eps2d, (int, float)) or not 0 <= eps2d < math.inf:
        raise ValueError(f"eps2d must be a finite number >= 0 pixels², got {eps2d!r}")
    if render_mode not in RENDER_MODES:
        raise ValueError(f"render_mode must be one of {RENDER_MODES}, got {render_mode!r}")
    if rasterize_mode not in RASTERIZE_MODES:
        raise ValueError(f"rasterize_mode must be one of {RASTERIZE_MODES}, got {rasterize_mode!r}")
    if camera_model not in camera_models:
        raise ValueError(f"camera_model must be one of {camera_models} (others are not supported yet), "
                         f"got {camera_model!r}")
    for name, t in tensors.items():
        if t is not None:
            if not t.is_floating_point():
                raise ValueError(f"{name} must be a floating-point tensor, got dtype {t.dtype}")
            check_finite(name, t)
    # values the paths assume (else the compositors disagree: the fused one clamps an opacity above 1)
    if n:
        lo, hi = torch.aminmax(opacities.detach())
        if not 0 <= float(lo) <= float(hi) <= 1:
            raise ValueError(f"opacities must be in [0, 1], got values from {float(lo):.6g} to {float(hi):.6g}")
        if float(scales.detach().min()) < 0:
            raise ValueError(f"scales must be >= 0 metres, got a minimum of {float(scales.detach().min()):.6g}")
    focal = Ks.detach()[:, [0, 1], [0, 1]]
    if not bool((focal > 0).all()):
        raise ValueError(f"Ks need focal lengths fx, fy > 0 pixels, got a minimum of {float(focal.min()):.6g}")
    # the tile paths read fx, fy, cx, cy only, the ray path inverts K: other entries must be the pinhole's
    pinhole = Ks.new_tensor([[1.0, 0.0, 1.0], [0.0, 1.0, 1.0], [0.0, 0.0, 0.0]])  # 1: free entry
    fixed = Ks.new_tensor([0.0, 0.0, 1.0])
    if bool(((Ks.detach() * (1 - pinhole))[:, :2] != 0).any()) or bool((Ks.detach()[:, 2] != fixed).any()):
        raise ValueError("Ks must be pinhole intrinsics [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (pixels): no skew, "
                         "last row (0, 0, 1)")
    # world-to-camera must be rigid: the SH view direction uses the camera centre −Rᵀt
    ortho_err, det_err = (float(e.max()) for e in rotation_errors(viewmats[:, :3, :3]))
    tol = VIEWMAT_TOL.get(viewmats.dtype, ROTATION_TOL)
    bottom = viewmats.detach()[:, 3] != viewmats.new_tensor([0.0, 0.0, 0.0, 1.0])
    if max(ortho_err, det_err) > tol or bool(bottom.any()):
        raise ValueError(f"viewmats must be rigid world-to-camera transforms [R | t; 0 0 0 1] with R a rotation, "
                         f"got max |RᵀR − I| {ortho_err:.3g}, |det R − 1| {det_err:.3g} (tolerance {tol:g}) or "
                         "another last row")


LOW_PRECISION = (torch.float16, torch.bfloat16)
"""Input dtypes the renderer computes in float32 instead (outputs are float32 then)."""


def compute_dtype(dtype: torch.dtype) -> torch.dtype:
    """The dtype the renderer computes in for inputs of ``dtype``: float16/bfloat16 → float32, else itself (every
    path also turns autocast off, :func:`diff4splat.utils.devices.full_precision`, as gsplat computes in float32)."""
    return torch.float32 if dtype in LOW_PRECISION else dtype


def mode_backgrounds(backgrounds: Tensor | None, render_mode: str, C: int, dtype: torch.dtype) -> Tensor | None:
    """Backgrounds (C, F) of the features for ``render_mode``: the colour, then 0 for a depth channel; None stays."""
    if backgrounds is None:
        return None
    bgs = backgrounds.to(dtype)
    if render_mode in ("D", "ED"):
        return bgs.new_zeros(C, 1)
    if render_mode != "RGB":
        return torch.cat([bgs, bgs.new_zeros(C, 1)], dim=-1)
    return bgs


def expected_depth(render_colors: Tensor, render_alphas: Tensor, render_mode: str) -> Tensor:
    """"ED"/"RGB+ED": the last channel divided by max(alpha, 1e-10) (0 where alpha is 0); other modes unchanged.
    (C, H, W, F), (C, H, W, 1) → (C, H, W, F)."""
    if render_mode not in ("ED", "RGB+ED"):
        return render_colors
    return torch.cat([render_colors[..., :-1], render_colors[..., -1:] / render_alphas.clamp(min=1e-10)], dim=-1)
