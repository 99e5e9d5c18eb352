"""Default arguments of the render entry points (one home for each value).

:func:`~diff4splat.render.rasterize`, :func:`~diff4splat.render.rasterize_dense` and
:func:`~diff4splat.render.raytrace` keep gsplat's ``rasterization`` argument list (so calls port unchanged) and
take their default values from here, as do :class:`~diff4splat.render.settings.RasterSettings` (which carries
them behind those entry points) and :func:`~diff4splat.render.projection.project_gaussians`;
:func:`~diff4splat.render.sequence.render_path` and
:func:`~diff4splat.render.render_rolling_shutter` take :data:`BACKGROUND` and :data:`NEAR_PLANE`.

The values are gsplat's ``rasterization`` defaults (the same in 1.4.0 … 1.5.3), except :data:`RENDER_MODE`:
this project renders colour and expected depth together ("RGB+ED") by default, where gsplat's default is "RGB".
"""
from __future__ import annotations

from ..constants import CAMERA_MODEL

__all__ = [
    "NEAR_PLANE", "FAR_PLANE", "EPS2D", "SH_DEGREE", "RENDER_MODE", "RASTERIZE_MODE", "CAMERA_MODEL", "TILE_SIZE",
    "BACKGROUND",
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
# CAMERA_MODEL: pinhole projection (gsplat "pinhole"); its home is diff4splat.constants because the camera models
# (diff4splat.cameras.lenses), below the renderer, default to it too.
TILE_SIZE = 16
"""Tile edge, pixels (gsplat 16); a performance knob, the image does not depend on it."""
BACKGROUND = (0.0, 0.0, 0.0)
"""RGB in [0, 1] behind the Gaussians for the scene renderers (render_path, render_rolling_shutter); an output
folder's own colour is :func:`diff4splat.io.scene_folder.meta_background`."""

