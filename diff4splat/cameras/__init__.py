"""Cameras: intrinsics, trajectories, camera paths, rays and physical camera models (OpenCV frame,
world-to-camera viewmats)."""
from diff4splat.cameras.intrinsics import (
    center_crop_box,
    fov_from_intrinsics,
    intrinsics_from_focal,
    intrinsics_from_fov,
)
from diff4splat.cameras.lenses import FisheyeKB, FisheyePolynomial, RollingShutter, ThinLens
from diff4splat.cameras.path import CameraPath, camera_centers, invert_rigid
from diff4splat.cameras.rays import (
    camera_rays,
    pack_plucker,
    plucker_rays,
    project_points,
    unproject_depth,
    unproject_pixels,
)
from diff4splat.cameras.trajectories import (
    DEFAULT_AMPLITUDES,
    DEFAULT_TRAJECTORY,
    TRAJECTORIES,
    look_at,
    make_trajectory,
)

__all__ = ["camera_rays", "plucker_rays", "unproject_depth", "project_points", "unproject_pixels", "pack_plucker",
           "intrinsics_from_fov", "intrinsics_from_focal", "fov_from_intrinsics", "center_crop_box", "CameraPath",
           "FisheyePolynomial", "FisheyeKB", "ThinLens", "RollingShutter", "invert_rigid", "camera_centers", "look_at",
           "make_trajectory", "TRAJECTORIES", "DEFAULT_TRAJECTORY", "DEFAULT_AMPLITUDES"]
