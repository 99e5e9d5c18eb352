"""Gaussian-splatting renderer (gsplat-compatible API): projection, SH colours, rasterizers (docs/DESIGN.md
"The renderer").

``rasterize`` is the fast tile path, ``rasterize_dense`` the brute-force reference it is tested against; camera
effects (fisheye, thin lens) go through the ray path ``raytrace``; ``render_rolling_shutter`` renders row bands of
a dynamic scene at their own times. Every entry point runs on the device of its inputs.
"""
from diff4splat.render.projection import Projection, project_gaussians
from diff4splat.render.rasterize import rasterize, rasterize_dense
from diff4splat.render.raytrace import raytrace
from diff4splat.render.sequence import render_rolling_shutter
from diff4splat.render.sh import sh_basis, sh_to_color, spherical_harmonics

eval_sh = spherical_harmonics
"""Alias of :func:`spherical_harmonics`."""

__all__ = ["rasterize", "rasterize_dense", "raytrace", "render_rolling_shutter", "project_gaussians", "Projection",
           "spherical_harmonics", "eval_sh", "sh_basis", "sh_to_color"]
