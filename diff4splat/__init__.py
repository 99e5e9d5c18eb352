"""diff4splat: one photograph + a camera path + an optional prompt → an explicit 4D Gaussian scene.

Implements Diff4Splat (Pan et al., 2025) on CPU: canonical 3D Gaussians plus per-time deformation maps,
rendered along any camera path by a pure-PyTorch rasterizer.

The top-level package exports the foundation (scene containers and the renderer), which never imports
the networks. The generation pipeline, which does, is imported from its module::

    from diff4splat.pipeline import Diff4SplatPipeline
"""
from diff4splat.render import rasterize, rasterize_dense
from diff4splat.scene.dynamic import DynamicGaussians
from diff4splat.scene.gaussians import Gaussians
from diff4splat.utils import devices  # noqa: F401  first: sets the OpenMP runtime's environment before torch loads it

__version__ = "0.1.0"

__all__ = ["Gaussians", "DynamicGaussians", "rasterize", "rasterize_dense", "__version__"]
