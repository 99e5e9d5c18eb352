"""The output folder of ``diff4splat generate`` (docs/DESIGN.md, "Output folder of generate"), written atomically.

::

    scene.ply           canonical Gaussians, INRIA layout
    deformation.npz     times (T,), d_means (T,M,3), d_quats (T,M,4), d_scales (T,M,3) (absent if static),
                        t_means (M,), t_scales (M,) (4D temporal support, when present); no file if neither
    frames/0000.ply …   the Gaussians deformed to each frame's time
    video.mp4           RGB along the camera path
    depth/0000.exr …    float32 expected depth "Z" (metres) and coverage "A"
    cameras.json        Ks, viewmats, width, height, times
    viewer.html         the interactive 4D viewer, self-contained (diff4splat.viewer)
    meta.json           model, seed, steps, timings, counts
"""
from __future__ import annotations

import json
import os
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from ..cameras.path import CameraPath
from ..constants import ALPHA_MIN
from ..render.defaults import meta_background, meta_eps2d
from ..scene import DynamicGaussians
from ..viewer.page import VIEWER_NAME, write_viewer
from .atomic import atomic_output_path
from .cameras import save_cameras_json
from .exr import save_depth_exr
from .outdir import output_dir
from .ply import save_ply
from .video import save_image, save_video, to_uint8

__all__ = ["write_scene_folder", "fill_empty_depth", "save_deformation", "load_deformation", "json_default"]



def fill_empty_depth(depths: Tensor, alphas: Tensor, fallback: float) -> Tensor:
    """Give pixels without geometry the far distance of the scene, so every depth is finite and > 0.

    Empty pixels (alpha < :data:`~diff4splat.constants.ALPHA_MIN` = 1/255) get the largest depth rendered
    anywhere on the path (the scene's far bound along these views), or ``fallback`` metres if no pixel is
    covered; the "A" channel of the EXR keeps the coverage so users can mask them.

    Args:
        depths: (T, H, W) expected depth, metres (0 where empty).
        alphas: (T, H, W) coverage in [0, 1].
        fallback: metres > 0.

    Returns:
        (T, H, W) depth, metres, finite and > 0.
    """
    covered = alphas >= ALPHA_MIN
    far = float(depths[covered].max()) if bool(covered.any()) else float(fallback)
    return torch.where(covered & (depths > 0), depths, torch.full_like(depths, far))


_DEFORMATION_KEYS = ("times", "d_means", "d_quats", "d_scales")
_TEMPORAL_KEYS = ("t_means", "t_scales")


def save_deformation(path: str | os.PathLike, scene: DynamicGaussians) -> None:
    """Write ``deformation.npz``: float32 times, d_means, d_quats, d_scales when the scene deforms and
    t_means (M,), t_scales (M,) (clip time) when it has temporal support.

    Raises:
        ValueError: the scene has neither a deformation nor temporal support (nothing to write).
    """
    if scene.is_static and not scene.has_temporal:
        raise ValueError("a static scene without temporal support has no deformation to save")
    keys = (() if scene.is_static else _DEFORMATION_KEYS) + (_TEMPORAL_KEYS if scene.has_temporal else ())
    arrays = {k: getattr(scene, k).detach().cpu().float().numpy() for k in keys}
    with atomic_output_path(Path(path)) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)


def load_deformation(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Read ``deformation.npz`` → numpy arrays {"times", "d_means", "d_quats", "d_scales"} and/or
    {"t_means", "t_scales"}, whichever the file holds (keyword arguments of ``DynamicGaussians``).

    Raises:
        ValueError: the file holds a partial set of either group.
    """
    with np.load(path) as data:
        out = {k: data[k] for k in _DEFORMATION_KEYS + _TEMPORAL_KEYS if k in data.files}
    for group in (_DEFORMATION_KEYS, _TEMPORAL_KEYS):
        if 0 < sum(k in out for k in group) < len(group):
            raise ValueError(f"{path}: needs all of {group} or none, got {sorted(out)}")
    return out


def write_scene_folder(
    out_dir: str | os.PathLike,
    scene: DynamicGaussians,
    cameras: CameraPath,
    colors: Tensor,  # (T, H, W, 3) in [0, 1]
    depths: Tensor,  # (T, H, W) metres
    alphas: Tensor,  # (T, H, W)
    meta: dict,
    *,
    fps: int = 8,
    depth_fallback: float = 1.0,
    inputs: Iterable[str | os.PathLike | None] = (),
    overwrite: bool = False,
    kind: str = "generate",
    extra: Callable[[Path], None] | None = None,
) -> Path:
    """Write the whole output folder into a temporary folder, then rename it onto ``out_dir``
    (:func:`~diff4splat.io.outdir.output_dir`, marker kind ``kind``: "generate", or "fit" for
    ``diff4splat fit``, whose ``extra`` writes field.safetensors and metrics.json).

    ``extra(tmp)`` is called with the temporary folder after the standard files, to add files of its own.

    A failure part-way leaves no ``out_dir`` (or the previous one untouched). An existing ``out_dir`` is
    replaced only if it is empty or an earlier ``generate`` output (or ``overwrite``), never if it holds
    one of ``inputs``.

    Raises:
        ValueError: frame counts of colours/depths/alphas/cameras differ.
        OutputDirError: ``out_dir`` may not be written (a file, holds inputs, not an output, …).
    """
    T = len(cameras)
    if not (colors.shape[0] == depths.shape[0] == alphas.shape[0] == T):
        raise ValueError(f"colors/depths/alphas must have {T} frames (one per camera), got "
                         f"{colors.shape[0]}/{depths.shape[0]}/{alphas.shape[0]}")
    depths = fill_empty_depth(depths, alphas, depth_fallback)
    rgb = to_uint8(colors.cpu(), "colors")  # (T, H, W, 3): rgb/*.png lossless beside the lossy video
    with output_dir(out_dir, kind=kind, inputs=inputs, overwrite=overwrite, parents=True) as tmp:
        save_ply(tmp / "scene.ply", scene.canonical)
        if not scene.is_static or scene.has_temporal:
            save_deformation(tmp / "deformation.npz", scene)
        for i in range(T):
            save_ply(tmp / "frames" / f"{i:04d}.ply", scene.at(float(cameras.times[i])))
            save_depth_exr(tmp / "depth" / f"{i:04d}.exr", depths[i].cpu(), alphas[i].clamp(0, 1).cpu())
            save_image(tmp / "rgb" / f"{i:04d}.png", rgb[i])
        save_video(tmp / "video.mp4", rgb, fps=fps)
        save_cameras_json(tmp / "cameras.json", cameras.to("cpu"))
        write_viewer(tmp / VIEWER_NAME, scene, cameras.to("cpu"), fps=fps, background=meta_background(meta),
                     eps2d=meta_eps2d(meta))
        (tmp / "meta.json").write_text(json.dumps(meta, indent=2, default=json_default))
        if extra is not None:
            extra(tmp)
    return Path(out_dir)


def json_default(obj):
    """``json.dumps`` ``default=``: numpy scalars → Python numbers, paths → strings."""
    if isinstance(obj, (np.generic,)):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")
