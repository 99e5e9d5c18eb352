"""A generated scene whose photo layer moves by a dense motion of the photograph's pixels: a user's drags
(docs/DESIGN.md, "Drags": :func:`diff4splat.geometry.drags.drag_motion`) or the motion generator's
(:mod:`diff4splat.assembly.generated_motion`); everything else stays still.

The generated frames were sampled without that motion, so they show the moving object where the photograph does;
their Gaussians on it (seen from the first camera inside a moving region, within :data:`ON_OBJECT_DEPTH` of the
photo layer's depth there) are dropped, or the object would stay behind as a still copy of itself.
"""
from __future__ import annotations

import dataclasses

import torch
from torch import Tensor

from diff4splat.geometry.drags import Drags, drag_motion
from diff4splat.scene.dynamic import DynamicGaussians
from models.deformation import IDENTITY_QUAT

__all__ = ["dragged_scene", "moved_scene", "ON_OBJECT_DEPTH"]

ON_OBJECT_DEPTH = 0.15
"""Relative depth band, |z − z_photo| / z_photo, within which a generated Gaussian seen in a moving region is taken
to lie on the moving object."""


def dragged_scene(
    scene: DynamicGaussians,  # the assembled scene: H·W front disks, ⌈H/2⌉·⌈W/2⌉ backing disks, then the rest
    source: Tensor,  # (M,) long, each Gaussian's source frame, 0 for the photo layer and backdrop
    drags: Drags,  # at the photograph's size
    image: Tensor,  # (H, W, 3) in [0, 1], the photograph
    photo_depth: Tensor,  # (H, W) the photo layer's z-depth, metres
    K: Tensor,  # (3, 3) the first camera's intrinsics at H × W (its viewmat is the identity: the world frame)
    times: Tensor,  # (Kt,) the scene's key times, clip times in [0, 1]
) -> tuple[DynamicGaussians, Tensor]:
    """The scene moved by the drags' motion at ``times`` (:func:`moved_scene`); drag times are normalised to
    [times[0], times[-1]]. Returns as :func:`moved_scene`."""
    span = float(times[-1] - times[0]) or 1.0
    motion, moving = drag_motion(drags, image, photo_depth, K, (times - times[0]) / span)  # (Kt, H, W, 3), (H, W)
    return moved_scene(scene, source, motion, moving, photo_depth, K, times)


def moved_scene(
    scene: DynamicGaussians,  # the assembled scene: H·W front disks, ⌈H/2⌉·⌈W/2⌉ backing disks, then the rest
    source: Tensor,  # (M,) long, each Gaussian's source frame, 0 for the photo layer and backdrop
    motion: Tensor,  # (Kt, H, W, 3) metres in the first camera's frame: each pixel's displacement at ``times``
    moving: Tensor,  # (H, W) bool, the pixels that move
    photo_depth: Tensor,  # (H, W) the photo layer's z-depth, metres
    K: Tensor,  # (3, 3) the first camera's intrinsics at H × W (its viewmat is the identity: the world frame)
    times: Tensor,  # (Kt,) the scene's key times, clip times in [0, 1]
) -> tuple[DynamicGaussians, Tensor]:
    """The scene with the photo layer's front disks moved by their pixels' ``motion`` at ``times``, each backing
    disk by its 2×2 block's top-left pixel's, the rest still (keeping its temporal support).

    Returns:
        (the moved scene, (M,) bool, the Gaussians kept: all but the generated ones on a moving region).
    """
    H, W = photo_depth.shape
    dev = scene.canonical.means.device
    n_front, back = H * W, motion[:, ::2, ::2]  # a backing disk follows its 2×2 block's top-left pixel
    d_means = torch.zeros(len(times), scene.num_gaussians, 3, device=dev, dtype=scene.canonical.means.dtype)
    d_means[:, :n_front] = motion.reshape(len(times), n_front, 3).to(d_means)
    d_means[:, n_front:n_front + back.shape[1] * back.shape[2]] = back.reshape(len(times), -1, 3).to(d_means)
    keep = (source == 0) | ~_on_moving_region(scene.canonical.means, moving, photo_depth, K)
    d_quats = torch.tensor(IDENTITY_QUAT, device=dev, dtype=d_means.dtype).expand(len(times), scene.num_gaussians, 4)
    moved = dataclasses.replace(scene, times=times.to(dev, d_means.dtype), d_means=d_means,
                                d_quats=d_quats.contiguous(), d_scales=torch.zeros_like(d_means))
    return moved.select(keep), keep


def _on_moving_region(means: Tensor, moving: Tensor, depth: Tensor, K: Tensor) -> Tensor:
    """(M,) bool: ``means`` (M, 3) in the first camera's frame that project into ``moving`` (H, W) within
    :data:`ON_OBJECT_DEPTH` of ``depth`` there."""
    H, W = moving.shape
    z = means[:, 2]
    uv = (means @ K.to(means).T)[:, :2] / z.clamp_min(1e-6)[:, None]
    col, row = uv[:, 0].floor().long(), uv[:, 1].floor().long()
    inside = (z > 0) & (col >= 0) & (col < W) & (row >= 0) & (row < H)
    col, row = col.clamp(0, W - 1), row.clamp(0, H - 1)
    surface = depth.to(means)[row, col]
    return inside & moving[row, col] & ((z - surface).abs() <= ON_OBJECT_DEPTH * surface)
