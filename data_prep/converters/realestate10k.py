"""RealEstate10K → scene format, with optional depth estimates aligned to a sparse reference.

Source: Zhou et al., "Stereo Magnification: Learning View Synthesis using Multiplane Images", SIGGRAPH 2018, and
the dataset README. Layout and conventions: ``data_prep/CONVERTERS.md``, "RealEstate10K". Poses are only defined
up to scale, so depth is written only when estimates are aligned to a reference in the camera file's units
(:func:`diff4splat.geometry.depth_alignment.align_video`).
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from diff4splat.geometry.depth_alignment import align_video, valid_depth_mask
from diff4splat.io import load_realestate10k
from diff4splat.io.cameras import read_realestate10k_lines

from .camera_conventions import camera_path
from .common import load_npy, only_stem, read_rgb_uint8, require_dir, require_file, select_frames, write_scene

__all__ = ["convert_realestate10k", "read_realestate10k_timestamps"]


def read_realestate10k_timestamps(path: str | os.PathLike) -> list[int]:
    """The integer timestamps (µs) of the frame lines of a RealEstate10K camera file, in file order. Raises
    FileNotFoundError / ValueError as :func:`diff4splat.io.cameras.read_realestate10k_lines`."""
    return read_realestate10k_lines(require_file(path, "RealEstate10K camera file"))[0]


def _frame_file(folder: Path, stamp: int) -> Path:
    for ext in (".png", ".jpg", ".jpeg"):
        if (folder / f"{stamp}{ext}").is_file():
            return folder / f"{stamp}{ext}"
    raise FileNotFoundError(f"no frame {stamp}.png/.jpg in {folder}")


def convert_realestate10k(src: str | os.PathLike, out: str | os.PathLike, *, clip: str | None = None,
                          estimates_dir: str | os.PathLike | None = None,
                          reference_dir: str | os.PathLike | None = None, space: str = "disparity",
                          metres_per_unit: float | None = None, start: int = 0, stride: int = 1,
                          max_frames: int | None = None, replace: bool = False, **robust_kwargs) -> Path:
    """Convert one RealEstate10K clip (None: the only ``.txt`` of ``src``) to the static scene ``out``; return it.

    Args:
        estimates_dir: per-frame relative depth/disparity ``.npy`` (``space``: ``"disparity"`` or ``"depth"``);
            None → no depth.
        reference_dir: per-frame sparse reference depth ``.npy`` in camera-file units (required with estimates).
        metres_per_unit: metres per camera-file unit, applied to translations and depth; None keeps SfM units
            (``metric_scale: false``).
        **robust_kwargs: options of :func:`diff4splat.geometry.depth_alignment.fit_scale_shift_robust`.

    Raises ValueError: ambiguous clip, estimates without a reference, shapes that differ, or any alignment error (too
    few reference samples, negative scale, …); FileNotFoundError: missing camera file, frames or depth files.
    """
    src = Path(src)
    if clip is None:
        clip = only_stem(src, "*.txt", "clip", "camera files")
    cam_file = require_file(src / f"{clip}.txt", "RealEstate10K camera file")
    if estimates_dir is not None and reference_dir is None:
        raise ValueError("estimates_dir needs reference_dir: RealEstate10K has no metric reference, an unaligned "
                         "estimate cannot be stored as depth (convert without estimates for depth_source='none')")
    stamps = read_realestate10k_timestamps(cam_file)
    idx = select_frames(len(stamps), start, stride, max_frames, source=cam_file)
    frame_dir = require_dir(src / clip, "RealEstate10K frames")
    H, W = read_rgb_uint8(_frame_file(frame_dir, stamps[idx[0]])).shape[:2]
    full = load_realestate10k(cam_file, W, H, relative=False)
    V = full.viewmats.double().cpu().numpy()[idx].copy()
    scale = 1.0 if metres_per_unit is None else float(metres_per_unit)
    V[:, :3, 3] *= scale
    ts = np.asarray([stamps[f] for f in idx], dtype=np.float64) * 1e-6
    cams = {"cam00": camera_path(V, full.Ks.double().cpu().numpy()[idx], W, H, ts)}
    extra = {"source_id": clip, "source_frames": [stamps[f] for f in idx], "metric_scale": metres_per_unit is not None,
             "units": "metres" if metres_per_unit is not None else "RealEstate10K SfM units (not metres)"}
    depths, fit = None, None
    if estimates_dir is not None:
        est = [load_npy(Path(estimates_dir) / f"{stamps[f]}.npy", "depth estimate") for f in idx]
        ref = [load_npy(Path(reference_dir) / f"{stamps[f]}.npy", "reference depth") for f in idx]
        for e, r in zip(est, ref, strict=True):
            if e.shape != (H, W) or r.shape != (H, W):
                raise ValueError(
                    f"estimates and references must be ({H}, {W}) like the frames, got {e.shape}, {r.shape}")
        masks = [valid_depth_mask(r) & np.isfinite(e) for e, r in zip(est, ref, strict=True)]
        fit, aligned = align_video(est, ref, masks, space=space, robust=True, **robust_kwargs)
        depths = [(a * scale).astype(np.float32) for a in aligned]
        extra.update({"depth_alignment_space": space, "depth_alignment_inliers": fit.num_inliers,
                      "depth_alignment_rms": fit.rms,
                      "depth_reference": "sparse reference depth in camera-file units (reference_dir)"})

    def frames(_name: str):
        for j, f in enumerate(idx):
            yield read_rgb_uint8(_frame_file(frame_dir, stamps[f])), (depths[j] if depths is not None else None)

    fps = (len(ts) - 1) / (ts[-1] - ts[0]) if len(ts) > 1 and ts[-1] > ts[0] else 30.0
    return write_scene(out, source="realestate10k", dynamic=False,
                       depth_source="aligned_estimate" if fit is not None else "none", fps=fps, cameras=cams,
                       timestamps=ts, frames=frames, replace=replace, extra=extra,
                       depth_scale=fit.scale if fit is not None else 1.0,
                       depth_shift=fit.shift if fit is not None else 0.0)
