"""Dynamic Replica → scene format: one sequence of a split, its stereo cameras, ground-truth depth.

Source: Karaev et al., "DynamicStereo: Consistent Dynamic Depth from Stereo Videos", CVPR 2023
(``datasets/dynamic_stereo_datasets.py``). Layout and conventions: ``data_prep/CONVERTERS.md``, "Dynamic Replica".
"""
from __future__ import annotations

import os
from collections import defaultdict
from pathlib import Path

import numpy as np

from .camera_conventions import P3D_TO_CV, camera_path, intrinsics, rigid
from .common import (
    finite_positive_or_inf,
    float16_bits_to_float,
    load_gzip_json,
    read_rgb_uint8,
    read_uint16_png,
    require_file,
    select_frames,
    write_scene,
)

__all__ = ["convert_dynamic_replica", "pytorch3d_to_opencv", "load_frame_annotations"]


def load_frame_annotations(root: str | os.PathLike, split: str) -> list[dict]:
    """The list of frame annotations of ``<root>/frame_annotations_<split>.jgz`` (gzipped JSON)."""
    p = require_file(Path(root) / f"frame_annotations_{split}.jgz", "Dynamic Replica annotations")
    data = load_gzip_json(p, "Dynamic Replica annotations")
    if not isinstance(data, list):
        raise ValueError(f"{p}: expected a JSON list of frame annotations")
    return data


def pytorch3d_to_opencv(viewpoint: dict, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """A PyTorch3D viewpoint → (viewmat (4, 4) OpenCV world-to-camera, K (3, 3) pixels): R_cv = diag(−1, −1, 1)·Rᵀ,
    t_cv = diag(−1, −1, 1)·T, focal and principal point from NDC. Raises ValueError: unknown ``intrinsics_format``."""
    R = np.asarray(viewpoint["R"], dtype=np.float64)
    T = np.asarray(viewpoint["T"], dtype=np.float64)
    fmt = str(viewpoint.get("intrinsics_format", "ndc_norm_image_bounds")).lower()
    half = np.array([width, height], dtype=np.float64) / 2.0
    if fmt == "ndc_isotropic":
        scale = np.array([half.min(), half.min()])
    elif fmt == "ndc_norm_image_bounds":
        scale = half
    else:
        raise ValueError(f"unknown intrinsics_format {fmt!r}")
    f = np.asarray(viewpoint["focal_length"], dtype=np.float64) * scale
    c = half - np.asarray(viewpoint["principal_point"], dtype=np.float64) * scale
    return rigid(P3D_TO_CV @ R.T, P3D_TO_CV @ T), intrinsics(f[0], f[1], c[0], c[1])[0]


def convert_dynamic_replica(src: str | os.PathLike, out: str | os.PathLike, *, sequence: str | None = None,
                            split: str = "train", sides: tuple[str, ...] = ("left", "right"), start: int = 0,
                            stride: int = 1, max_frames: int | None = None, replace: bool = False) -> Path:
    """Convert one Dynamic Replica sequence (None: the split's only one) of the dataset root ``src`` to the scene
    ``out`` and return it (dynamic, ground-truth depth, timestamps = ``frame_timestamp``). ``sides``: ``camera_name``
    values, stored as ``cam00``, ``cam01`` in order; ``start``, ``stride``, ``max_frames``: the selection over the
    frames sorted by ``frame_number``. Raises ValueError: unknown/ambiguous sequence, a side missing, unequal frame
    numbers between sides; FileNotFoundError: missing annotation or frame files."""
    src = Path(src)
    by_seq: dict[str, dict[str, list[dict]]] = defaultdict(lambda: defaultdict(list))
    for a in load_frame_annotations(src, split):
        by_seq[a["sequence_name"]][a.get("camera_name") or "left"].append(a)
    if sequence is None:
        if len(by_seq) != 1:
            raise ValueError(f"sequence must be given: the split has {len(by_seq)} sequences ({sorted(by_seq)[:5]}…)")
        sequence = next(iter(by_seq))
    if sequence not in by_seq:
        raise ValueError(f"unknown sequence {sequence!r}")
    per_side = {}
    for s in sides:
        if s not in by_seq[sequence]:
            raise ValueError(f"sequence {sequence!r} has no camera {s!r} (has {sorted(by_seq[sequence])})")
        per_side[s] = sorted(by_seq[sequence][s], key=lambda a: a["frame_number"])
    numbers = [a["frame_number"] for a in per_side[sides[0]]]
    for s in sides[1:]:
        if [a["frame_number"] for a in per_side[s]] != numbers:
            raise ValueError(f"cameras {sides[0]!r} and {s!r} of {sequence!r} have different frames")
    idx = select_frames(len(numbers), start, stride, max_frames)
    ref = [per_side[sides[0]][f] for f in idx]
    ts = np.asarray([a.get("frame_timestamp", a["frame_number"] / 30.0) for a in ref], dtype=np.float64)
    fps = (len(ts) - 1) / (ts[-1] - ts[0]) if len(ts) > 1 and ts[-1] > ts[0] else 30.0 / stride
    cams = {}
    for k, s in enumerate(sides):
        annots = [per_side[s][f] for f in idx]
        H, W = (int(v) for v in annots[0]["image"]["size"])
        conv = [pytorch3d_to_opencv(a["viewpoint"], H, W) for a in annots]
        cams[f"cam{k:02d}"] = camera_path(np.stack([c[0] for c in conv]), np.stack([c[1] for c in conv]), W, H, ts)

    def frames(name: str):
        for a in (per_side[sides[int(name[3:])]][f] for f in idx):
            raw = read_uint16_png(src / split / a["depth"]["path"])
            depth = float16_bits_to_float(raw) * float(a["depth"].get("scale_adjustment") or 1.0)
            yield (read_rgb_uint8(src / split / a["image"]["path"]),
                   finite_positive_or_inf(np.where(depth < 1e-5, np.inf, depth)))

    return write_scene(out, source="dynamic_replica", dynamic=True, depth_source="ground_truth", fps=fps,
                       cameras=cams, timestamps=ts, frames=frames, replace=replace,
                       extra={"source_id": sequence, "source_frames": [numbers[f] for f in idx],
                              "source_cameras": list(sides)})
