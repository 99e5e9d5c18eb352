"""Virtual KITTI 2 → scene format.

Source: Cabon, Murray, Humenberger, "Virtual KITTI 2", arXiv:2001.10773 (2020), and the dataset's
README (naverlabs.com, "Virtual KITTI 2 Dataset"). One converted scene = one
``<SceneXX>/<variation>`` folder (e.g. ``Scene01/clone``) of the rgb, depth and textgt archives
extracted into the same tree::

    <IN>/intrinsic.txt                                   header, then: frame cameraID K[0,0] K[1,1] K[0,2] K[1,2]
    <IN>/extrinsic.txt                                   header, then: frame cameraID r11 r12 r13 t1 r21 r22 r23 t2
                                                         r31 r32 r33 t3 0 0 0 1
    <IN>/frames/rgb/Camera_<c>/rgb_<%05d>.jpg
    <IN>/frames/depth/Camera_<c>/depth_<%05d>.png        uint16, centimetres; 65535 (655.35 m) = sky / no depth

The extrinsic rows are world-to-camera matrices; camera axes are KITTI's (x right, y down,
z forward) = OpenCV; depth is z-depth ("distance to the camera plane", README). Camera_0 is the
left and Camera_1 the right camera of the stereo rig. The sequences were generated at 10 Hz like
KITTI.

Pixel coordinates: the principal point is given with pixel centres at integers, as OpenCV and KITTI count
them: the dataset's (620.5, 187.0) for its 1242×375 frames is ((W − 1)/2, (H − 1)/2), the centre of the
rendered (symmetric) frustum. Ours puts pixel centres at +0.5 (FORMAT.md), so cx, cy get + 0.5 (621.0, 187.5);
the focal lengths are unchanged.
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
    """Parse a VKITTI2 text table (one header line, whitespace-separated rows) keyed by (frame, camera).

    Args:
        path: ``intrinsic.txt`` (6 columns) or ``extrinsic.txt`` (18 columns).
        ncols: expected number of columns per row.

    Returns:
        {(frame, cameraID): values (ncols − 2,) float64}.

    Raises:
        FileNotFoundError: missing file. ValueError: a row (named by line) with another column count
            or non-numeric values.
    """
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
    """Convert one Virtual KITTI 2 scene/variation folder (module docstring) to a scene folder.

    Args:
        src: the ``<SceneXX>/<variation>`` folder.
        out: output scene folder.
        cameras: VKITTI2 camera IDs to convert (0 = left, 1 = right); stored as ``cam00``, ``cam01``…
            in this order, the first being the reference camera.
        start, stride, max_frames: frame selection (:func:`select_frames`); fps becomes 10/stride.
        replace: replace an existing output folder.

    Returns:
        The scene folder (``depth_source="ground_truth"``, dynamic).

    Raises:
        FileNotFoundError: a missing table, folder or frame file.
        ValueError: malformed tables, a frame missing from a table, or invalid output.
    """
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
