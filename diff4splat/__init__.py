"""diff4splat: one photograph + a camera path + an optional prompt → an explicit 4D Gaussian scene.

Implements Diff4Splat (Pan et al., 2025) on CPU: canonical 3D Gaussians plus per-time deformation maps,
rendered along any camera path by a pure-PyTorch rasterizer.
"""
from .gaussians import Gaussians
from .render import rasterize, rasterize_dense
from .scene import DynamicGaussians

__version__ = "0.1.0"

__all__ = ["Gaussians", "DynamicGaussians", "rasterize", "rasterize_dense", "Diff4SplatPipeline", "__version__"]


def __getattr__(name: str):
    # The pipeline imports the networks (``models``), which import ``diff4splat`` submodules: load it lazily.
    if name == "Diff4SplatPipeline":
        from .pipeline import Diff4SplatPipeline

        return Diff4SplatPipeline
    raise AttributeError(f"module 'diff4splat' has no attribute {name!r}")
