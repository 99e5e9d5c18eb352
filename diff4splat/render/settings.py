"""The renderer's settings as one value: :class:`RasterSettings`, built once per call by a public entry point.

The public entry points (:func:`~diff4splat.render.rasterize`, :func:`~diff4splat.render.rasterize_dense`,
:func:`~diff4splat.render.raytrace`) keep gsplat's ``rasterization`` keyword list, so calls port unchanged; each
packs its keywords into a :class:`RasterSettings` and every function behind it (the dispatch, input validation,
the render pipeline, the gsplat backend, the ray path) takes that object instead of re-listing the keywords.
Its defaults are those of :mod:`diff4splat.render.defaults`, the one home of each value.
"""
from __future__ import annotations

from dataclasses import dataclass

from torch import Tensor

from diff4splat.render import defaults

__all__ = ["RasterSettings", "GSPLAT_KEYWORDS"]

GSPLAT_KEYWORDS = ("near_plane", "far_plane", "eps2d", "sh_degree", "backgrounds", "render_mode", "rasterize_mode",
                   "camera_model", "tile_size")
"""The fields of :class:`RasterSettings` that are keywords of gsplat's ``rasterization`` (all but
``camera_params``, this project's camera effects), in gsplat's order."""


@dataclass(frozen=True, eq=False)
class RasterSettings:
    """How to render (everything of a render call but the Gaussians, the cameras and the image size).

    Values are stored as given: :func:`diff4splat.render.validate.validate_inputs` checks them, with the
    tensors, where a render starts (so a bad value gives the same ``ValueError`` from every entry point).
    Compared by identity (``backgrounds`` is a tensor).

    Attributes:
        near_plane, far_plane: Gaussians with camera z (on the ray path: ray hits with distance along the ray)
            outside [near_plane, far_plane] are culled, metres.
        eps2d: screen-space dilation added to each projected covariance, pixels².
        sh_degree: None (``colors`` composited as given) or 0..3 (``colors`` are SH coefficients).
        backgrounds: (C, D) colour behind the Gaussians, or None.
        render_mode: "RGB", "D", "ED", "RGB+D" or "RGB+ED".
        rasterize_mode: "classic" or "antialiased" (Mip-Splatting opacity compensation).
        camera_model: "pinhole" or "fisheye" (ray path).
        tile_size: tile edge, pixels (a performance knob).
        camera_params: None, or a camera effect of :mod:`diff4splat.cameras.lenses` (ray path).
    """

    near_plane: float = defaults.NEAR_PLANE
    far_plane: float = defaults.FAR_PLANE
    eps2d: float = defaults.EPS2D
    sh_degree: int | None = defaults.SH_DEGREE
    backgrounds: Tensor | None = None
    render_mode: str = defaults.RENDER_MODE
    rasterize_mode: str = defaults.RASTERIZE_MODE
    camera_model: str = defaults.CAMERA_MODEL
    tile_size: int = defaults.TILE_SIZE
    camera_params: object = None

    @property
    def antialiased(self) -> bool:
        """Whether opacities are multiplied by the Mip-Splatting compensation (``rasterize_mode="antialiased"``)."""
        return self.rasterize_mode == "antialiased"

    def gsplat_keywords(self) -> dict:
        """gsplat ``rasterization``'s keyword arguments for these settings: {name: value} for
        :data:`GSPLAT_KEYWORDS`."""
        return {name: getattr(self, name) for name in GSPLAT_KEYWORDS}

    def projection_keywords(self) -> dict:
        """The keyword arguments of :func:`diff4splat.render.projection.project_gaussians` (and its drop-in
        :func:`diff4splat.render.fused_projection.project_fused`) for these settings."""
        return {"near_plane": self.near_plane, "far_plane": self.far_plane, "eps2d": self.eps2d,
                "antialiased": self.antialiased, "camera_model": self.camera_model}
