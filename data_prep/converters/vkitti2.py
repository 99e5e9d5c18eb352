"""Virtual KITTI 2 → scene format: one ``<SceneXX>/<variation>`` folder, stereo cameras, ground-truth depth.

Source: Cabon, Murray, Humenberger, "Virtual KITTI 2", arXiv:2001.10773 (2020), and the dataset's README. Layout
and conventions (principal point + 0.5: the dataset counts pixel centres at integers): ``data_prep/CONVERTERS.md``,
"Virtual KITTI 2".
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from diff4splat.io.structured import read_text

from .camera_conventions import INTEGER_CENTRE_SHIFT, camera_path, intrinsics
from .common import (
    decode_scaled_uint16,
    read_rgb_uint8,
    read_uint16_png,
    require_dir,
    require_file,
    select_frames,
    write_scene,
)

__all__ = ["convert_vkitti2", "read_vkitti2_table", "VKITTI2_FPS", "VKITTI2_DEPTH_M_PER_UNIT"]

VKITTI2_FPS = 10.0
"""Frame rate of the Virtual KITTI 2 sequences (the KITTI camera rate), Hz."""

VKITTI2_DEPTH_M_PER_UNIT = 0.01
"""Depth PNG unit: centimetres."""

_SKY = 65535


def read_vkitti2_table(path: str | os.PathLike, ncols: int) -> dict[tuple[int, int], np.ndarray]:
    """Parse a VKITTI2 text table (one header line, ``ncols`` whitespace-separated columns): {(frame, cameraID): values
    (ncols − 2,) float64}. Raises FileNotFoundError: missing file; ValueError: a row (named by line) of another width or
    not numbers."""
    p = require_file(path, "VKITTI2 table")
    table = {}
    for lineno, line in enumerate(read_text(p, "VKITTI2 table").splitlines()[1:], start=2):
        words = line.split()
        if not words:
            continue
        if len(words) != ncols:
            raise ValueError(f"{p}:{lineno}: expected {ncols} columns, got {len(words)}")
        try:
            vals = [float(w) for w in words]
        except ValueError:
            raise ValueError(f"{p}:{lineno}: non-numeric value") from None
        table[(int(vals[0]), int(vals[1]))] = np.asarray(vals[2:])
    return table


def convert_vkitti2(src: str | os.PathLike, out: str | os.PathLike, *, cameras: tuple[int, ...] = (0, 1),
                    start: int = 0, stride: int = 1, max_frames: int | None = None,
                    replace: bool = False) -> Path:
    """Convert one Virtual KITTI 2 scene/variation folder ``src`` to the dynamic scene ``out`` and return it.
    ``cameras``: camera IDs (0 left, 1 right) stored as ``cam00``, ``cam01``… in order, the first the reference; fps =
    10 / stride. Raises FileNotFoundError: a missing table, folder or frame file; ValueError: malformed tables, a frame
    missing from a table, or invalid output."""
    src = Path(src)
    K_tab = read_vkitti2_table(src / "intrinsic.txt", 6)
    E_tab = read_vkitti2_table(src / "extrinsic.txt", 18)
    rgb_dirs = {c: require_dir(src / "frames" / "rgb" / f"Camera_{c}", "VKITTI2 rgb") for c in cameras}
    depth_dirs = {c: require_dir(src / "frames" / "depth" / f"Camera_{c}", "VKITTI2 depth") for c in cameras}
    n_total = len(sorted(rgb_dirs[cameras[0]].glob("rgb_*.jpg")))
    idx = select_frames(n_total, start, stride, max_frames)
    ts = np.asarray(idx, dtype=np.float64) / VKITTI2_FPS
    H, W = read_rgb_uint8(rgb_dirs[cameras[0]] / f"rgb_{idx[0]:05d}.jpg").shape[:2]
    paths = {}
    for k, c in enumerate(cameras):
        try:
            intr = np.stack([K_tab[(f, c)] for f in idx])
            ext = np.stack([E_tab[(f, c)] for f in idx])
        except KeyError as e:
            raise ValueError(f"{src}: (frame, camera) {e.args[0]} missing from intrinsic.txt/extrinsic.txt") from None
        viewmats = ext.reshape(-1, 4, 4)  # world-to-camera, OpenCV axes already
        fx, fy, cx, cy = intr.T
        Ks = intrinsics(fx, fy, cx + INTEGER_CENTRE_SHIFT, cy + INTEGER_CENTRE_SHIFT)
        paths[f"cam{k:02d}"] = camera_path(viewmats, Ks, W, H, ts)

    def frames(name: str):
        c = cameras[int(name[3:])]
        for f in idx:
            rgb = read_rgb_uint8(rgb_dirs[c] / f"rgb_{f:05d}.jpg")
            raw = read_uint16_png(depth_dirs[c] / f"depth_{f:05d}.png")
            yield rgb, decode_scaled_uint16(raw, VKITTI2_DEPTH_M_PER_UNIT, invalid=(0, _SKY))

    return write_scene(out, source="vkitti2", dynamic=True, depth_source="ground_truth", fps=VKITTI2_FPS / stride,
                       cameras=paths, timestamps=ts, frames=frames, replace=replace,
                       extra={"source_id": "/".join(src.resolve().parts[-2:]), "source_frames": idx,
                              "source_cameras": [f"Camera_{c}" for c in cameras]})
