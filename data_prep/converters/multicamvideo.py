"""MultiCamVideo (ReCamMaster) → scene format: one ``<focal>_aperture<a>/sceneN`` folder, up to 10 cameras.

Source: Bai et al., "ReCamMaster: Camera-Controlled Generative Rendering from A Single Video", ICCV 2025 (dataset
card, the loaders' ``parse_matrix``). Layout and conventions (Unreal Engine poses → OpenCV, c2w =
[F·R_ue·Q | F·t_ue / 100]): ``data_prep/CONVERTERS.md``, "MultiCamVideo".
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
    """``"[a b c d] [e f g h] [i j k l] [m n o p]"`` → (4, 4) float64 (rows as written); ValueError otherwise."""
    rows = re.findall(r"\[([^\[\]]*)\]", str(text))
    try:
        M = np.array([[float(v) for v in r.split()] for r in rows], dtype=np.float64)
    except ValueError:
        raise ValueError(f"non-numeric camera matrix {text!r}") from None
    if M.shape != (4, 4):
        raise ValueError(f"expected a 4×4 matrix string, got shape {M.shape} from {text!r}")
    return M


def ue_to_opencv_c2w(M_row: np.ndarray) -> np.ndarray:
    """(…, 4, 4) UE row-vector transforms (cm) → (…, 4, 4) OpenCV camera-to-world in metres (CONVERTERS.md)."""
    c2w_ue = np.swapaxes(np.asarray(M_row, dtype=np.float64), -1, -2)
    return rigid(_F @ c2w_ue[..., :3, :3] @ _Q, (c2w_ue[..., :3, 3] @ _F.T) / 100.0)


def convert_multicamvideo(src: str | os.PathLike, out: str | os.PathLike, *, cameras: tuple[str, ...] | None = None,
                          focal_mm: float | None = None, start: int = 0, stride: int = 1,
                          max_frames: int | None = None, replace: bool = False) -> Path:
    """Convert one MultiCamVideo scene folder ``src`` to the multi-camera scene ``out`` and return it. ``cameras``:
    source names kept (``cam01`` …), first = reference (None: all of ``frame0``, sorted); ``focal_mm``: None → parsed
    from the parent folder ``f<mm>_…``; meta fps = 15 / stride. Raises ValueError: no focal length, a frame or camera
    missing in the JSON, or a bad matrix string; FileNotFoundError: missing JSON or video."""
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
