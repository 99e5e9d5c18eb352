"""Shared by the ``data_prep`` engine tests: a dataset tree read back whole, and tiny D-NeRF clips to convert."""
from __future__ import annotations

import json
import os
from pathlib import Path

import cv2
import numpy as np


def tree(root: Path) -> dict[str, bytes | str]:
    """Every entry under ``root`` (hidden ones too) by relative path: a file's bytes, a symlink's target (not
    followed)."""
    out: dict[str, bytes | str] = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            p = Path(dirpath) / name
            rel = str(p.relative_to(root))
            if p.is_symlink():
                out[rel] = "-> " + os.readlink(p)
            elif p.is_file():
                out[rel] = p.read_bytes()
    return out


def dnerf_clip(root: Path, times: tuple[float, ...], size: int = 16, seed: int = 0) -> None:
    """A D-NeRF (Blender) clip in ``root``: ``transforms_train.json`` and one RGBA PNG of seeded noise per time,
    cameras 4 m from the origin along +z (Blender: looking down −z), shifted sideways 0.1 m per frame."""
    rng = np.random.default_rng(seed)
    frames = []
    (root / "train").mkdir(parents=True)
    for i, t in enumerate(times):
        img = np.concatenate([rng.integers(0, 255, (size, size, 3)), np.full((size, size, 1), 255)], -1)
        cv2.imwrite(str(root / "train" / f"r_{i:03d}.png"), img.astype(np.uint8))
        c2w = np.eye(4)
        c2w[:3, 3] = (0.1 * i, 0.0, 4.0)
        frames.append({"file_path": f"./train/r_{i:03d}", "time": t, "transform_matrix": c2w.tolist()})
    (root / "transforms_train.json").write_text(json.dumps({"camera_angle_x": 0.8, "frames": frames}))
