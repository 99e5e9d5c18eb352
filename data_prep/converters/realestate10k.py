"""RealEstate10K → scene format, with optional depth estimates aligned to a sparse reference.

Source: Zhou et al., "Stereo Magnification: Learning View Synthesis using Multiplane Images",
SIGGRAPH 2018, and the dataset README. The dataset releases only camera files; frames are taken
from the YouTube videos by the user at the listed timestamps. Expected layout (the frame naming is
ours, the common one of RealEstate10K download scripts — see CONVERTERS.md)::

    <IN>/<clip>.txt                  URL line, then per frame: timestamp_µs fx fy cx cy 0 0 [R|t] (3×4 row-major)
    <IN>/<clip>/<timestamp_µs>.png   (or .jpg) the frame at that timestamp
    <ESTIMATES>/<timestamp_µs>.npy   optional (H, W) relative depth or disparity from a monocular estimator
    <REFERENCE>/<timestamp_µs>.npy   optional (H, W) sparse reference depth; NaN / inf / ≤ 0 = no sample

Camera files are parsed by :func:`diff4splat.io.load_realestate10k` (intrinsics normalised by the
image size, [R | t] world-to-camera with OpenCV axes). The poses come from ORB-SLAM2 and bundle
adjustment and are only defined up to scale: **RealEstate10K has no metric reference**. Hence:

- without estimates, no depth is written (``depth_source="none"``);
- with estimates but no reference, :func:`convert_realestate10k` refuses (an unaligned estimate is
  not a depth in any unit of the scene);
- with both, one (s, t) per clip is fitted robustly (:func:`diff4splat.geometry.depth_alignment.align_video`)
  from the estimate to the reference, ``depth_source="aligned_estimate"``. The reference must be in
  the units of the camera file (e.g. SfM points triangulated with the released poses and projected
  into the frames), so depth and poses agree. Units stay the dataset's arbitrary SfM units unless
  ``metres_per_unit`` is given (e.g. from an external metric estimate); meta records
  ``"metric_scale": false`` in that case.
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
    """The integer timestamps (µs) of the frame lines of a RealEstate10K camera file, in file order.

    Raises:
        FileNotFoundError / ValueError: :func:`diff4splat.io.cameras.read_realestate10k_lines` (the rules of
            :func:`diff4splat.io.load_realestate10k`: a FIFO or loop, non-UTF-8 text, a truncated line, a timestamp
            that is not an integer, each naming the file and line).
    """
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
    """Convert one RealEstate10K clip (module docstring) to a scene folder.

    Args:
        src: folder with ``<clip>.txt`` and ``<clip>/`` frames.
        out: output scene folder.
        clip: clip id; ``None`` when ``src`` holds exactly one ``.txt``.
        estimates_dir: per-frame relative depth/disparity ``.npy``; ``None`` → no depth.
        reference_dir: per-frame sparse reference depth ``.npy`` in camera-file units (required with
            ``estimates_dir``).
        space: ``"disparity"`` if the estimates are inverse depth (MiDaS / Depth Anything), else
            ``"depth"``.
        metres_per_unit: metres per camera-file unit, applied to translations and depth; ``None``
            keeps SfM units (flagged ``metric_scale: false``).
        start, stride, max_frames: frame selection.
        replace: replace an existing output folder.
        **robust_kwargs: options of :func:`diff4splat.geometry.depth_alignment.fit_scale_shift_robust`.

    Returns:
        The scene folder (static scene).

    Raises:
        ValueError: ambiguous clip, estimates without a reference, shapes that differ, or any
            alignment error (too few reference samples, negative scale, …).
        FileNotFoundError: missing camera file, frames or depth files.
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
