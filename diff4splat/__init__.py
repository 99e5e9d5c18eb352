"""diff4splat: one photograph + a camera path + an optional prompt → an explicit 4D Gaussian scene
(Diff4Splat, Pan et al., 2025). The top level exports the foundation (scene containers and the renderer), which never
imports the networks; the pipeline is ``diff4splat.pipeline.Diff4SplatPipeline``.
"""
from diff4splat.utils import preflight  # noqa: F401  first: refuses a ulimit -v under which torch's imports crash

# isort: split
from diff4splat.utils import devices  # noqa: F401  sets the OpenMP runtime's environment before torch loads it

# isort: split
from diff4splat.render import rasterize, rasterize_dense
from diff4splat.scene.dynamic import DynamicGaussians
from diff4splat.scene.gaussians import Gaussians

__version__ = "0.1.0"

__all__ = ["Gaussians", "DynamicGaussians", "rasterize", "rasterize_dense", "__version__"]
