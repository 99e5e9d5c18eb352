"""Dense 3D tracks of every pixel from per-object poses (``objects.npz``, FORMAT.md): where each pixel's surface point
is at every frame, the dense scene-flow supervision DGS-LRM (Lin et al. 2025, §3.2) trains its deformable Gaussians
with, instead of a few hundred sampled tracks.

A scene's ``objects.npz`` gives each object k an affine world map per frame, x_f = A_f·p + b_f of its canonical points
p (``poses`` (O, F, 3, 4) = [A_f | b_f]), and each camera an id map per frame (0: the static background, k + 1: object
k, :data:`NO_SURFACE`: nothing). A point seen at frame s on object k is at A_t·A_s⁻¹·(x − b_s) + b_t at frame t; on
the background it stays where it is.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from .scene_files import NO_SURFACE

__all__ = ["pixel_tracks", "homogeneous", "id_boundaries"]


def homogeneous(poses: Tensor) -> Tensor:  # (..., 3, 4) → (..., 4, 4)
    """(..., 4, 4) homogeneous matrices of affine maps ``poses`` (..., 3, 4) [A | b]."""
    bottom = torch.zeros(*poses.shape[:-2], 1, 4, dtype=poses.dtype, device=poses.device)
    bottom[..., 0, 3] = 1
    return torch.cat([poses, bottom], dim=-2)


def pixel_tracks(
    points: Tensor,  # (H, W, 3) metres, world frame: frame ``source``'s pixels' surface points
    ids: Tensor,  # (H, W) integer: 0 background, k + 1 object k, NO_SURFACE nothing
    poses: Tensor,  # (O, F, 3, 4) affine world maps of the O objects at the F frames
    source: int,
    frames: Tensor,  # (T,) long frame indices into poses
) -> Tensor:
    """(T, H, W, 3) positions in metres (world frame, ``points``' dtype) at ``frames`` of the surface points seen at
    frame ``source``: each object's points carried by its poses, the background's and NO_SURFACE pixels' (the caller
    masks these) unchanged. Computed in float64.

    Raises:
        ValueError: shapes that do not match, an id above O that is not NO_SURFACE, or a frame outside [0, F).
    """
    H, W = ids.shape
    num_objects, F = poses.shape[:2]
    if points.shape != (H, W, 3) or poses.shape[2:] != (3, 4) or frames.dim() != 1:
        raise ValueError(f"points (H, W, 3), ids (H, W), poses (O, F, 3, 4) and frames (T,) must agree, got "
                         f"{tuple(points.shape)}, {tuple(ids.shape)}, {tuple(poses.shape)}, {tuple(frames.shape)}")
    ids = ids.long()
    bad = (ids > num_objects) & (ids != NO_SURFACE)
    if bad.any():
        raise ValueError(f"object id {int(ids[bad].max())} in the id map, but the poses have {num_objects} object(s)")
    if not (0 <= source < F) or ((frames < 0) | (frames >= F)).any():
        raise ValueError(f"source {source} and frames must lie in [0, {F}), got frames {frames.tolist()}")
    x = points.double()
    out = x.expand(len(frames), H, W, 3).clone()
    if num_objects == 0:
        return out.to(points.dtype)
    maps = homogeneous(poses.double())
    carry = maps[:, frames.to(poses.device)] @ torch.linalg.inv(maps[:, source])[:, None]  # (O, T, 4, 4): s → t
    for k in range(num_objects):
        sel = ids == k + 1
        if sel.any():
            m = carry[k]  # (T, 4, 4)
            out[:, sel] = torch.einsum("tij,pj->tpi", m[:, :3, :3], x[sel]) + m[:, None, :3, 3]
    return out.to(points.dtype)


def id_boundaries(ids: Tensor) -> Tensor:  # (H, W) → (H, W) bool
    """(H, W) bool: pixels whose 3×3 neighbourhood (inside the image) holds more than one id of ``ids`` (H, W). Their
    rendered depth blends two surfaces, so their point belongs to neither: a blended point labelled with a rotating
    object swings about the object's pivot from where no surface is."""
    f = ids.double()[None, None]
    return (F.max_pool2d(f, 3, 1, 1) != -F.max_pool2d(-f, 3, 1, 1))[0, 0]
