"""MultiCamVideo (ReCamMaster) → scene format.

Source: Bai et al., "ReCamMaster: Camera-Controlled Generative Rendering from A Single Video",
ICCV 2025; dataset card and README of the MultiCamVideo-Dataset, and the official loading code
(``parse_matrix`` and the c2w conversion in the ReCamMaster training/inference scripts). One
converted scene = one ``<focal>_aperture<a>/sceneN`` folder::

    <IN>/videos/cam01.mp4 … cam10.mp4          81 synchronised frames, 1280×1280, 15 fps
    <IN>/cameras/camera_extrinsics.json        {"frame0": {"cam01": "[r r r 0] [r r r 0] [r r r 0] [x y z 1]", …}, …}

The folder name gives the focal length (f18, f24, f35, f50 mm) of a 23.76 × 23.76 mm sensor, so
fx = fy = f_mm / 23.76 · W, principal point at the centre. Each matrix string is an Unreal Engine
5 transform in row-vector form (translation in the 4th row, centimetres); transposed it is the
camera-to-world [R_ue | t_ue] with the UE camera axes (x forward, y right, z up) in the UE world,
which is left-handed (x forward, y right, z up). Conversion: OpenCV camera axes
local_ue = Q·cv with Q = [[0,0,1],[1,0,0],[0,−1,0]] (ReCamMaster's column reorder [1, 2, 0] and
sign flip), world mirrored to a right-handed frame F = diag(1, −1, 1) (x forward, y left, z up),
centimetres → metres: c2w = [F·R_ue·Q | F·t_ue / 100]. Relative camera poses are identical to
ReCamMaster's (F cancels in V_i·V_0⁻¹). No depth is provided.
"""
from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from .camera_conventions import c2w_cv_to_viewmat, camera_path, intrinsics, rigid
from .common import iter_video_frames, load_json_file, select_frames, write_scene

__all__ = ["convert_multicamvideo", "parse_ue_matrix", "ue_to_opencv_c2w", "MULTICAMVIDEO_FPS", "SENSOR_MM"]

MULTICAMVIDEO_FPS = 15.0
"""Frame rate of the MultiCamVideo clips, Hz (dataset card)."""

SENSOR_MM = 23.76
"""Sensor width and height of the MultiCamVideo cameras, millimetres (dataset card)."""

_Q = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # OpenCV camera axes → UE camera axes
_F = np.diag([1.0, -1.0, 1.0])  # left-handed UE world → right-handed world


def parse_ue_matrix(text: str) -> np.ndarray:
    """``"[a b c d] [e f g h] [i j k l] [m n o p]"`` → (4, 4) float64 (rows as written).

    Raises:
        ValueError: not 4 bracketed rows of 4 numbers.
    """
    rows = re.findall(r"\[([^\[\]]*)\]", str(text))
    try:
        M = np.array([[float(v) for v in r.split()] for r in rows], dtype=np.float64)
    except ValueError:
        raise ValueError(f"non-numeric camera matrix {text!r}") from None
    if M.shape != (4, 4):
        raise ValueError(f"expected a 4×4 matrix string, got shape {M.shape} from {text!r}")
    return M


def ue_to_opencv_c2w(M_row: np.ndarray) -> np.ndarray:
    """(…, 4, 4) UE row-vector transforms (cm) → (…, 4, 4) OpenCV camera-to-world in metres (module docstring)."""
    c2w_ue = np.swapaxes(np.asarray(M_row, dtype=np.float64), -1, -2)
    return rigid(_F @ c2w_ue[..., :3, :3] @ _Q, (c2w_ue[..., :3, 3] @ _F.T) / 100.0)


def convert_multicamvideo(src: str | os.PathLike, out: str | os.PathLike, *, cameras: tuple[str, ...] | None = None,
                          focal_mm: float | None = None, start: int = 0, stride: int = 1,
                          max_frames: int | None = None, replace: bool = False) -> Path:
    """Convert one MultiCamVideo scene folder (module docstring) to a multi-camera scene folder.

    Args:
        src: scene folder (``.../f18_aperture10/scene1``).
        out: output scene folder.
        cameras: source camera names (``cam01`` …) to convert, first = reference; ``None`` → every
            camera of ``frame0`` in sorted order. Names are kept.
        focal_mm: focal length in mm; ``None`` → parsed from the parent folder name ``f<mm>_…``.
        start, stride, max_frames: frame selection; meta fps = 15/stride.
        replace: replace an existing output folder.

    Returns:
        The scene folder (dynamic, ``depth_source="none"``).

    Raises:
        ValueError: no focal length, a frame or camera missing in the JSON, or a bad matrix string.
        FileNotFoundError: missing JSON or video.
    """
    src = Path(src)
    data = load_json_file(src / "cameras" / "camera_extrinsics.json", "camera_extrinsics.json")
    n_total = sum(1 for k in data if re.fullmatch(r"frame\d+", k))
    if focal_mm is None:
        m = re.match(r"f(\d+(?:\.\d+)?)_", src.resolve().parent.name)
        if m is None:
            raise ValueError(f"focal_mm not given and parent folder {src.resolve().parent.name!r} is not 'f<mm>_…'")
        focal_mm = float(m.group(1))
    names = list(cameras) if cameras is not None else sorted(data.get("frame0", {}))
    idx = select_frames(n_total, start, stride, max_frames)
    ts = np.asarray(idx, dtype=np.float64) / MULTICAMVIDEO_FPS
    first = next(iter_video_frames(src / "videos" / f"{names[0]}.mp4", [0]))
    H, W = first.shape[:2]
    K = intrinsics(focal_mm / SENSOR_MM * W, focal_mm / SENSOR_MM * H, W / 2.0, H / 2.0)[0]
    paths = {}
    for n in names:
        try:
            M = np.stack([parse_ue_matrix(data[f"frame{f}"][n]) for f in idx])
        except KeyError as e:
            raise ValueError(f"camera_extrinsics.json misses {e.args[0]!r} for camera {n!r}") from None
        paths[n] = camera_path(c2w_cv_to_viewmat(ue_to_opencv_c2w(M)), K, W, H, ts)

    def frames(name: str):
        for rgb in iter_video_frames(src / "videos" / f"{name}.mp4", idx):
            if rgb.shape[:2] != (H, W):
                raise ValueError(f"{name}.mp4 frames are {rgb.shape[1]}×{rgb.shape[0]}, expected {W}×{H}")
            yield rgb, None

    return write_scene(out, source="multicamvideo", dynamic=True, depth_source="none", fps=MULTICAMVIDEO_FPS / stride,
                       cameras=paths, timestamps=ts, frames=frames, replace=replace,
                       extra={"source_id": "/".join(src.resolve().parts[-2:]), "source_frames": idx,
                              "focal_mm": focal_mm,
                              "world_frame": "UE world mirrored (x forward, y left, z up), metres"})
