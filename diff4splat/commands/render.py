"""``diff4splat render`` (flags: :func:`register`; the library function: :func:`rerender`): re-render an output
folder of ``generate`` or ``fit`` along any camera path and time.

The folder is read as untrusted input (:func:`load_scene_folder`). With a ``field.safetensors`` (``fit``) the
deformation is queried at exactly the new path's times (:func:`path_scene`), else ``deformation.npz`` is interpolated
between its key times. The path is a ``cameras.json`` (used as is, in the scene's world frame), a RealEstate10K file
(placed at the folder's first camera) or a preset (:func:`trajectory_cameras`); frame i is rendered at
``cameras.times[i]`` on the device :func:`rerender` is given. The output folder (kind ``"render"``, written atomically;
docs/DESIGN.md, "Output folder of generate")::

    rgb/0000.png …      8-bit RGB, lossless: round(255 · clamp(colour, 0, 1))
    video.mp4           the same frames (an odd width/height padded by repeating the last column/row)
    depth/0000.exr …    float32 expected depth "Z" (metres; empty pixels filled as generate does) and coverage "A"
    cameras.json        the path rendered
    viewer.html         the interactive viewer of the source scene, opening at the path's first camera
    meta.json           source folder, camera source, deformation source, frames, size, fps, device, timings
"""
from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from diff4splat.cameras import TRAJECTORIES, CameraPath, make_trajectory
from diff4splat.cameras.path import check_field_of_view
from diff4splat.cameras.trajectories import check_amplitude
from diff4splat.commands.options import add_out_flags
from diff4splat.io import load_cameras_json, load_depth_exr, load_realestate10k
from diff4splat.io.inputs import check_input_file
from diff4splat.io.output_folders import MARKER, check_output_dir, read_marker
from diff4splat.io.scene_folder import (
    SceneFolder,
    folder_file,
    layout_frame,
    load_scene_folder,
    meta_background,
    meta_eps2d,
    scene_meta,
    write_scene_folder,
)
from diff4splat.io.video import DEFAULT_FPS, check_fps, check_video_size
from diff4splat.render.sequence import render_path
from diff4splat.render.settings import NEAR_PLANE
from diff4splat.scene.dynamic import DynamicGaussians
from diff4splat.utils.checks import check_positive_int
from diff4splat.utils.constants import ALPHA_MIN
from diff4splat.utils.costs import render_memory
from diff4splat.utils.devices import AUTO, DEVICE_HELP, resolve_device
from diff4splat.utils.limits import check_limit, check_memory, check_output_size, held_memory
from models.hexplane import load_field

__all__ = ["register", "run", "RENDER_KIND", "path_scene", "placed_at", "load_camera_file", "trajectory_cameras",
           "resize_cameras", "render_memory_estimate", "rerender", "estimate_scene_depth", "scene_depth"]

RENDER_KIND = "render"
"""Output-folder kind of ``diff4splat render`` (:data:`diff4splat.io.MARKER`)."""
COVERED = 0.5
"""Pixels of ``depth/0000.exr`` with coverage "A" above this give the scene depth (:func:`scene_depth`)."""


def path_scene(folder: SceneFolder, times: Tensor) -> DynamicGaussians:
    """The scene to render at ``times`` (T,) in [0, 1], on the device of ``folder.scene``: with a field, its
    deformation sampled at exactly the distinct ``times``; without, the folder's scene."""
    if folder.field is None:
        return folder.scene
    s = folder.scene
    keys = torch.unique(times.detach().float().cpu()).to(s.canonical.means)  # sorted, strictly increasing
    d_means, d_quats, d_scales = folder.field.deformations_at(s.canonical.means, keys)
    return DynamicGaussians(s.canonical, keys, d_means, d_quats, d_scales, s.t_means, s.t_scales, s.t_ramps)


def render_memory_estimate(folder: SceneFolder, path: CameraPath) -> int:
    """Upper bound of ``render``'s peak host memory, bytes, once ``folder`` is loaded
    (:func:`diff4splat.utils.costs.render_memory`: a field is sampled at the path's distinct times)."""
    times = len(torch.unique(path.times)) if folder.field is not None else 0
    return render_memory(held=held_memory(), gaussians=folder.scene.num_gaussians, sampled_times=times,
                         frames=len(path), width=path.width, height=path.height)


def placed_at(path: CameraPath, first: Tensor) -> CameraPath:
    """A path relative to its first camera placed at the (4, 4) world-to-camera pose ``first``: V_i' = V_i · ``first``,
    V_0' = ``first`` exactly."""
    first = first.to(path.viewmats.dtype)
    viewmats = path.viewmats @ first
    viewmats[0] = first
    return CameraPath(viewmats, path.Ks.clone(), path.width, path.height, path.times.clone())


def load_camera_file(path: str | os.PathLike, folder: SceneFolder) -> CameraPath:
    """``--cameras``: a ``cameras.json`` as is, or (any other suffix) a RealEstate10K file at the folder's size and
    first camera. FileNotFoundError / ValueError: missing, not a regular file or malformed (named)."""
    path = check_input_file(path, "cameras")
    if path.suffix.lower() == ".json":
        return load_cameras_json(path)
    cams = load_realestate10k(path, folder.cameras.width, folder.cameras.height, relative=True)
    return placed_at(cams, folder.cameras.viewmats[0])


def estimate_scene_depth(folder: SceneFolder) -> float | None:
    """:func:`scene_depth` (metres, > 0), or None when none of its sources exists.

    Raises:
        ValueError: ``depth/0000.exr`` unreadable, without "Z", or with "Z" and "A" of different sizes.
    """
    value = folder.meta.get("scene_depth")  # checked by load_output_scene: a finite number > 0, or absent
    if value is not None:
        return float(value)
    exr = folder_file(folder.path, layout_frame("depth", 0))
    if exr is not None:
        z, a = load_depth_exr(exr, return_alpha=True)
        if a is not None and a.shape != z.shape:
            raise ValueError(f"{exr}: channels 'Z' {z.shape} and 'A' {a.shape} differ in size")
        keep = np.isfinite(z) & (z > 0) & (a > COVERED if a is not None else True)
        if keep.any():
            return float(np.median(z[keep]))
    means = folder.scene.canonical.means.double()
    vm = folder.cameras.viewmats[0].to(means)
    z = means @ vm[2, :3] + vm[2, 3]  # camera-0 depth of each mean
    z = z[z > NEAR_PLANE]
    return float(z.median()) if z.numel() else None


def scene_depth(folder: SceneFolder) -> float:
    """Distance from the folder's first camera to the scene centre, metres: where presets look.

    The first of: meta.json's ``scene_depth``; the median "Z" of ``depth/0000.exr`` over pixels with "A" >
    :data:`COVERED` (every finite Z > 0 without "A"); the median depth of the canonical means in front of the
    first camera (z > NEAR_PLANE).

    Raises:
        ValueError: none of the three exists; ``depth/0000.exr`` unreadable or without "Z".
    """
    depth = estimate_scene_depth(folder)
    if depth is None:
        raise ValueError(f"scene folder {folder.path}: cannot estimate the scene depth (no depth/0000.exr coverage "
                         "and no Gaussian in front of the first camera)")
    return depth


def trajectory_cameras(folder: SceneFolder, name: str, frames: int | None = None,
                       amplitude: float | None = None) -> tuple[CameraPath, float]:
    """Preset ``name`` (:func:`~diff4splat.cameras.make_trajectory`; ``frames`` default: the folder's) at the folder's
    frame-0 intrinsics and size, around the scene centre :func:`scene_depth` metres ahead, from its first camera;
    returns (the path, the scene depth in metres). ValueError: unknown preset, bad ``amplitude``, ``frames`` not a
    positive int or above its limit, no scene depth."""
    c = folder.cameras
    T = _check_frames(len(c) if frames is None else frames)
    depth = scene_depth(folder)
    preset = make_trajectory(name, T, c.Ks[0], c.width, c.height, scene_depth=depth, amplitude=amplitude)
    return placed_at(preset, c.viewmats[0]), depth


def _check_frames(frames: object) -> int:
    """``frames`` if it is a positive int within the ``frames`` limit."""
    return check_limit("frames", check_positive_int("--frames", frames), "--frames")


def resize_cameras(cameras: CameraPath, width: int | None = None, height: int | None = None) -> CameraPath:
    """The path at ``width`` × ``height`` (:meth:`CameraPath.fitted`); one alone keeps the aspect ratio (the other
    rounded to an even number ≥ 2). ValueError: not a positive int."""
    if width is None and height is None:
        return cameras
    if width is not None:
        width = check_positive_int("--width", width, "pixels")
    if height is not None:
        height = check_positive_int("--height", height, "pixels")
    if height is None:
        height = max(2, 2 * round(width * cameras.height / cameras.width / 2))
    if width is None:
        width = max(2, 2 * round(height * cameras.width / cameras.height / 2))
    return cameras.fitted(width, height)


def rerender(folder: str | os.PathLike, out: str | os.PathLike, *, cameras: str | os.PathLike | None = None,
             trajectory: str | None = None, amplitude: float | None = None, frames: int | None = None,
             width: int | None = None, height: int | None = None, fps: float = DEFAULT_FPS, overwrite: bool = False,
             progress: bool = False, device: str | torch.device = "cpu") -> dict:
    """Render the scene of ``folder`` along a camera path and write the ``render`` output folder ``out``; returns the
    dict written to ``out/meta.json``.

    Args:
        folder: output folder of ``generate`` or ``fit`` (:func:`load_scene_folder`).
        out, overwrite: output folder (module docstring), checked before any work, never ``folder`` or the camera
            file; ``overwrite``: it may replace a folder that is not a ``render`` output.
        cameras: camera file (:func:`load_camera_file`); exactly one of ``cameras`` and ``trajectory``.
        trajectory, amplitude, frames: preset name, amplitude and frame count (:func:`trajectory_cameras`).
        width, height, fps: optional output size in pixels (:func:`resize_cameras`); video frame rate in (0, 1000].
        device: where the scene is rendered ("cpu", "cuda", "cuda:N", "auto" or a ``torch.device``; checked first).

    Raises:
        ValueError: both or neither of ``cameras``/``trajectory``; ``amplitude``/``frames`` with ``cameras``; a bad
            ``fps``, size, preset or ``amplitude``; an ``out`` that may not be written; limits exceeded; a malformed
            file of ``folder`` or camera file; a camera narrower than 0.1°; a path that sees none of the scene
            (checked before anything is written); a ``device`` this machine does not have.
        FileNotFoundError: ``folder``, its ``scene.ply``/``cameras.json`` or the camera file is missing.
    """
    t_start = time.perf_counter()
    device = resolve_device(device, "device")
    if (cameras is None) == (trajectory is None):
        raise ValueError("give exactly one camera path: cameras (a cameras.json or RealEstate10K file) or "
                         f"trajectory (a preset name), got {'both' if cameras is not None else 'neither'}")
    if cameras is not None and (amplitude is not None or frames is not None):
        raise ValueError("--amplitude and --frames shape a trajectory preset; they do not apply to --cameras "
                         "(the file fixes the path)")
    fps = check_fps(fps, "--fps")
    if trajectory is not None:  # before the scene is read: generate's checks of a preset
        check_amplitude(trajectory, amplitude, "--amplitude")
    if frames is not None:
        _check_frames(frames)
    inputs = [folder, cameras]
    check_output_dir(out, inputs=inputs, overwrite=overwrite, kind=RENDER_KIND)
    src = load_scene_folder(folder, device, load_field=load_field)
    depth = None
    if cameras is not None:
        path = load_camera_file(cameras, src)
    else:
        path, depth = trajectory_cameras(src, trajectory, frames, amplitude)
    path = resize_cameras(path, width, height)
    check_field_of_view(path)  # as generate: a camera seeing a point of the scene has intrinsics in other units
    check_video_size(path.width, path.height, "--width or --height")
    check_output_size(len(path), path.width, path.height, knobs="--frames, --width or --height", out=out)
    check_memory(render_memory_estimate(src, path), f"{len(path)} frames at {path.width}×{path.height} of "
                 f"{src.scene.num_gaussians:,} Gaussians", "--frames, --width or --height")
    scene = path_scene(src, path.times)
    if depth is None:
        depth = estimate_scene_depth(src)  # only the fill value of pixels that no frame covers (1 m without one)
    t_load = time.perf_counter() - t_start
    t0 = time.perf_counter()
    background, eps2d = meta_background(src.meta), meta_eps2d(src.meta)
    colors, depths, alphas = render_path(scene, path.to(device), background=background, eps2d=eps2d,
                                         progress=progress)
    colors, depths, alphas = colors.cpu(), depths.cpu(), alphas.cpu()  # waits for the device: in t_render
    t_render = time.perf_counter() - t0
    _check_path_sees_the_scene(alphas, trajectory)
    depth = 1.0 if depth is None else depth
    meta = {
        "source": str(folder),
        "source_kind": read_marker(src.path) if folder_file(src.path, MARKER) is not None else None,
        "cameras_file": None if cameras is None else str(cameras),
        "trajectory": trajectory,
        "amplitude": amplitude,
        "scene_depth": depth,
        "deformation": src.deformation_source,
        "device": str(device),
        "timings_s": {"load": t_load, "render": t_render},
        **scene_meta(scene, path, fps=fps, background=background, eps2d=eps2d),
    }
    t0 = time.perf_counter()

    def timings(_tmp) -> None:  # before meta.json, which is written last
        meta["timings_s"]["write"] = time.perf_counter() - t0
        meta["timings_s"]["total"] = time.perf_counter() - t_start

    write_scene_folder(out, scene.to("cpu"), path, colors, depths, alphas, meta, fps=fps, depth_fallback=depth,
                       inputs=inputs, overwrite=overwrite, kind=RENDER_KIND, extra=timings, with_scene=False)
    return meta


def _check_path_sees_the_scene(alphas: Tensor, trajectory: str | None) -> None:
    """ValueError, naming the likely cause, when no frame covers a pixel (every alpha < :data:`ALPHA_MIN`)."""
    if bool((alphas >= ALPHA_MIN).any()):
        return
    cause = ("the folder's first camera does not look at its scene (a cameras.json of another folder?)"
             if trajectory is not None else "the cameras look away from the scene (a camera file in another world "
                                            "frame, or intrinsics in other units)")
    raise ValueError(f"the camera path sees none of the scene: all {len(alphas)} frames would show only the "
                     f"background; likely cause: {cause}")


def register(sub) -> argparse.ArgumentParser:
    """Add ``render`` and its flags to the ``diff4splat`` subparsers; returns its parser."""
    r = sub.add_parser("render", help="re-render an output folder of generate or fit along a camera path",
                       description="Render the scene of an output folder of generate or fit along any camera path "
                                   "and time: rgb/0000.png … (lossless), video.mp4, depth/0000.exr …, cameras.json.")
    r.add_argument("folder", type=Path, metavar="DIR", help="output folder of `diff4splat generate` or `fit`")
    rcam = r.add_mutually_exclusive_group(required=True)
    rcam.add_argument("--cameras", type=Path, default=None, metavar="FILE",
                      help="cameras.json (used as is, in the scene's world frame: generate's, or a data_prep scene's "
                           "<cam>/cameras.json) or RealEstate10K .txt (placed at the folder's first camera)")
    rcam.add_argument("--trajectory", choices=TRAJECTORIES, default=None, metavar="NAME",
                      help=f"camera path preset from the folder's first camera, at its intrinsics: "
                           f"{', '.join(TRAJECTORIES)}")
    r.add_argument("--amplitude", type=float, default=None, help="preset amplitude (as generate's --amplitude)")
    r.add_argument("--frames", type=int, default=None, help="preset frame count (default: the folder's)")
    r.add_argument("--width", type=int, default=None, help="output width, pixels (default: the camera path's)")
    r.add_argument("--height", type=int, default=None, help="output height, pixels (default: the camera path's)")
    r.add_argument("--fps", type=float, default=DEFAULT_FPS, help=f"video frame rate (default: {DEFAULT_FPS:g})")
    r.add_argument("--device", default=AUTO, help=DEVICE_HELP + "; where the scene is rendered")
    r.add_argument("--quiet", action="store_true", help="no progress bar")
    add_out_flags(r)
    r.set_defaults(func=run)
    return r


def run(args: argparse.Namespace) -> int:
    """Run ``render``; prints the folder's line, returns 0."""
    meta = rerender(args.folder, args.out, cameras=args.cameras, trajectory=args.trajectory,
                    amplitude=args.amplitude, frames=args.frames, width=args.width, height=args.height,
                    fps=args.fps, overwrite=args.overwrite, progress=not args.quiet,
                    device=resolve_device(args.device, "--device"))
    print(f"wrote {args.out} ({meta['frames']} frames, {meta['width']}x{meta['height']})")
    return 0
