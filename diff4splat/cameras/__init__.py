"""Cameras: intrinsics, trajectories, camera paths and rays (OpenCV frame, world-to-camera viewmats)."""
from .rays import camera_rays, pack_plucker, plucker_rays

__all__ = ["camera_rays", "plucker_rays", "pack_plucker"]
