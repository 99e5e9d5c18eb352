"""Spring → scene format: one train scene folder, left and right cameras, depth from disparity.

Source: Mehl et al., "Spring: A High-Resolution High-Detail Dataset and Benchmark for Scene Flow, Optical Flow and
Stereo", CVPR 2023 (``flow_library`` ``readDsp5Disp``). Layout and conventions (depth = fx·0.065 m / disparity):
``data_prep/CONVERTERS.md``, "Spring".
"""
from __future__ import annotations

import os
from pathlib import Path

import h5py
import numpy as np

from .camera_conventions import camera_path, intrinsics
from .common import disparity_to_depth, load_number_rows, read_rgb_uint8, require_file, select_frames, write_scene

__all__ = ["convert_spring", "read_dsp5", "SPRING_BASELINE", "SPRING_FPS"]

SPRING_BASELINE = 0.065
"""Stereo baseline of the Spring cameras, metres."""

SPRING_FPS = 24.0
"""Nominal frame rate, Hz (the Blender film's rate; not stated in the data files, see CONVERTERS.md)."""


def read_dsp5(path: str | os.PathLike) -> np.ndarray:
    """Read a Spring ``.dsp5`` disparity file (HDF5 dataset ``"disparity"``) as float32 (2H, 2W). Raises
    FileNotFoundError: missing file; ValueError: no ``"disparity"`` dataset."""
    p = require_file(path, "Spring disparity")
    with h5py.File(p, "r") as f:
        if "disparity" not in f:
            raise ValueError(f"{p} has no 'disparity' dataset; is it a .dsp5 file?")
        return np.asarray(f["disparity"][()], dtype=np.float32)


def _read_rows(path: Path, ncols: int) -> np.ndarray:
    return load_number_rows(path, "Spring camera file", ncols)


def convert_spring(src: str | os.PathLike, out: str | os.PathLike, *, sides: tuple[str, ...] = ("left", "right"),
                   start: int = 0, stride: int = 1, max_frames: int | None = None, fps: float = SPRING_FPS,
                   replace: bool = False) -> Path:
    """Convert one Spring train scene folder ``src`` to the scene ``out`` and return it (dynamic, ground-truth depth).
    ``sides``: stored as ``cam00``, ``cam01`` in order; ``start``, ``stride``, ``max_frames``: selection over frame
    indices 0…T−1 (file number = index + 1); ``fps``: nominal, Hz. Raises FileNotFoundError / ValueError: missing files,
    malformed camera files, or a disparity map that is not twice the image size."""
    src = Path(src)
    intr = _read_rows(src / "cam_data" / "intrinsics.txt", 4)
    extr = _read_rows(src / "cam_data" / "extrinsics.txt", 16).reshape(-1, 4, 4)
    idx = select_frames(min(len(intr), len(extr)), start, stride, max_frames)
    ts = np.asarray(idx, dtype=np.float64) / fps
    H, W = read_rgb_uint8(src / f"frame_{sides[0]}" / f"frame_{sides[0]}_{idx[0] + 1:04d}.png").shape[:2]
    K = intrinsics(*intr[idx].T)
    cams = {}
    for k, s in enumerate(sides):
        V = extr[idx].copy()
        if s == "right":
            V[:, 0, 3] -= SPRING_BASELINE
        elif s != "left":
            raise ValueError(f"sides must be 'left' and/or 'right', got {s!r}")
        cams[f"cam{k:02d}"] = camera_path(V, K, W, H, ts)

    def frames(name: str):
        s = sides[int(name[3:])]
        for j, f in enumerate(idx):
            disp = read_dsp5(src / f"disp1_{s}" / f"disp1_{s}_{f + 1:04d}.dsp5")
            if disp.shape != (2 * H, 2 * W):
                raise ValueError(f"Spring disparity {f + 1} ({s}) has shape {disp.shape}, expected {(2 * H, 2 * W)}")
            yield (read_rgb_uint8(src / f"frame_{s}" / f"frame_{s}_{f + 1:04d}.png"),
                   disparity_to_depth(disp[::2, ::2], K[j, 0, 0], SPRING_BASELINE))

    return write_scene(out, source="spring", dynamic=True, depth_source="ground_truth", fps=fps / stride,
                       cameras=cams, timestamps=ts, frames=frames, replace=replace,
                       extra={"source_id": src.resolve().name, "source_frames": [f + 1 for f in idx],
                              "source_cameras": list(sides)})
