"""TartanAir → scene format: one trajectory folder, left and right cameras, ground-truth depth.

Source: Wang et al., "TartanAir: A Dataset to Push the Limits of Visual SLAM", IROS 2020 (``tartanair_tools``).
Layout and conventions (NED world kept, camera axes to OpenCV: c2w_cv = [R_ned · NED_TO_CVᵀ | t]):
``data_prep/CONVERTERS.md``, "TartanAir".
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .camera_conventions import NED_TO_CV, c2w_cv_to_viewmat, camera_path, intrinsics, quat_xyzw_to_rotmat, rigid
from .common import finite_positive_or_inf, load_npy, load_number_rows, read_rgb_uint8, select_frames, write_scene

__all__ = ["convert_tartanair", "read_tartanair_poses", "TARTANAIR_K", "TARTANAIR_FPS"]

TARTANAIR_K = (320.0, 320.0, 320.0, 240.0)
"""(fx, fy, cx, cy) in pixels of every TartanAir camera (640 × 480)."""

TARTANAIR_FPS = 10.0
"""Nominal frame rate, Hz (TartanAir does not define one; see CONVERTERS.md)."""


def read_tartanair_poses(path: str | os.PathLike) -> np.ndarray:
    """``pose_<side>.txt`` → (T, 4, 4) OpenCV world-to-camera viewmats in the NED world frame, metres. Raises
    FileNotFoundError: missing file; ValueError: a line without 7 numbers or a zero quaternion."""
    rows = load_number_rows(path, "TartanAir pose file", 7, "tx ty tz qx qy qz qw")
    R_ned = quat_xyzw_to_rotmat(rows[:, 3:])  # camera body (NED) → world (NED)
    return c2w_cv_to_viewmat(rigid(R_ned @ NED_TO_CV.T, rows[:, :3]))


def convert_tartanair(src: str | os.PathLike, out: str | os.PathLike, *, sides: tuple[str, ...] = ("left", "right"),
                      start: int = 0, stride: int = 1, max_frames: int | None = None, max_depth: float = 1000.0,
                      fps: float = TARTANAIR_FPS, replace: bool = False) -> Path:
    """Convert one TartanAir trajectory folder ``src`` to the static scene ``out`` and return it. ``sides``: stored as
    ``cam00``, ``cam01`` in order; ``max_depth``: metres beyond which depth (the sky) is +inf; ``fps``: nominal, Hz
    (meta fps = fps / stride). Raises FileNotFoundError: missing pose/frame files; ValueError: malformed poses,
    frame-count mismatch between pose file and images, or a depth map of another size."""
    src = Path(src)
    views = {s: read_tartanair_poses(src / f"pose_{s}.txt") for s in sides}
    n_total = min(len(v) for v in views.values())
    idx = select_frames(n_total, start, stride, max_frames)
    ts = np.asarray(idx, dtype=np.float64) / fps
    H, W = read_rgb_uint8(src / f"image_{sides[0]}" / f"{idx[0]:06d}_{sides[0]}.png").shape[:2]
    K = intrinsics(*TARTANAIR_K)[0]
    cams = {f"cam{k:02d}": camera_path(views[s][idx], K, W, H, ts) for k, s in enumerate(sides)}

    def frames(name: str):
        s = sides[int(name[3:])]
        for f in idx:
            depth = load_npy(src / f"depth_{s}" / f"{f:06d}_{s}_depth.npy", "TartanAir depth")
            if depth.shape != (H, W):
                raise ValueError(f"TartanAir depth frame {f} ({s}) has shape {depth.shape}, images are {(H, W)}")
            yield (read_rgb_uint8(src / f"image_{s}" / f"{f:06d}_{s}.png"),
                   finite_positive_or_inf(np.where(depth > max_depth, np.inf, depth)))

    return write_scene(out, source="tartanair", dynamic=False, depth_source="ground_truth", fps=fps / stride,
                       cameras=cams, timestamps=ts, frames=frames, replace=replace,
                       extra={"source_id": "/".join(src.resolve().parts[-3:]), "source_frames": idx,
                              "source_cameras": list(sides), "world_frame": "NED (x north, y east, z down)"})
