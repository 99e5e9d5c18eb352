"""Pruning of Gaussians that never contribute to a camera path."""
from __future__ import annotations

import torch
from torch import Tensor

from .cameras.path import CameraPath
from .render.defaults import NEAR_PLANE
from .render.projection import project_gaussians
from .scene import DynamicGaussians

__all__ = ["visibility_mask", "prune_scene"]


def visibility_mask(scene: DynamicGaussians, cameras: CameraPath, near_plane: float = NEAR_PLANE) -> Tensor:
    """Which Gaussians any camera of ``cameras`` sees, each at its own frame time.

    A Gaussian is seen by camera i when, deformed to time ``cameras.times[i]``, it passes the
    renderer's culling (:func:`diff4splat.render.project_gaussians`: in front of the near plane and
    its 3σ screen footprint overlapping the image); exactly the Gaussians the rasterizer would skip
    for every frame are reported unseen. With temporal support, a Gaussian gated out at a frame's
    time (:meth:`DynamicGaussians.active_indices`, o·p(t) < 1/255) is not seen by that camera.

    Returns:
        (M,) bool.
    """
    seen = torch.zeros(scene.num_gaussians, dtype=torch.bool, device=scene.canonical.means.device)
    for i in range(len(cameras)):
        t = float(cameras.times[i])
        idx, g = scene.active_indices(t), scene.at(t)
        proj = project_gaussians(g.means, g.quats, g.scales, g.opacities, cameras.viewmats[i:i + 1],
                                 cameras.Ks[i:i + 1], cameras.width, cameras.height, near_plane=near_plane)
        vis = proj.radii[0] > 0
        if idx is None:
            seen |= vis
        else:
            seen[idx[vis]] = True
    return seen


def prune_scene(scene: DynamicGaussians, cameras: CameraPath | None = None, min_opacity: float = 0.005,
                near_plane: float = NEAR_PLANE) -> tuple[DynamicGaussians, dict[str, int]]:
    """Drop Gaussians with opacity below ``min_opacity`` or that no camera of ``cameras`` sees.

    A Gaussian with opacity o < 1/255 can never pass the 3DGS alpha threshold (alpha ≤ o), so
    ``min_opacity`` ≤ 1/255 prunes only Gaussians that provably never contribute.

    Args:
        scene: the scene (deformation arrays follow the kept Gaussians).
        cameras: the path the scene will be rendered along, or None to prune by opacity only.
        min_opacity: opacity threshold in [0, 1).

    Returns:
        The pruned scene and counts {"before", "low_opacity", "unseen", "after"}.

    Raises:
        ValueError: ``min_opacity`` outside [0, 1).
    """
    if not 0.0 <= min_opacity < 1.0:
        raise ValueError(f"min_opacity must lie in [0, 1), got {min_opacity}")
    opaque = scene.canonical.opacities >= min_opacity
    seen = visibility_mask(scene, cameras, near_plane) if cameras is not None else torch.ones_like(opaque)
    keep = opaque & seen
    stats = {"before": scene.num_gaussians, "low_opacity": int((~opaque).sum()),
             "unseen": int((opaque & ~seen).sum()), "after": int(keep.sum())}
    return scene.select(keep), stats
