"""``generate`` as a library function: a photograph (+ a camera path, a prompt) → a 4D scene rendered along the path
(:func:`generate`), written with :func:`diff4splat.request.write`, e.g. ``write(generate("photo.jpg", frames=17),
"out")``. Every argument is checked once, before the model loads (limits before the networks run): the files and
the request's flags here, the sampling settings by :meth:`Diff4SplatPipeline.check_settings`.
"""
from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path

import numpy as np
from torch import Tensor

from diff4splat import request
from diff4splat.assembly.assemble import DEPTH_KINDS
from diff4splat.assembly.photo import layer_sizes
from diff4splat.cameras import DEFAULT_TRAJECTORY, CameraPath, center_crop_box
from diff4splat.cameras.trajectories import check_amplitude, check_trajectory
from diff4splat.geometry.drags import Drags, drags_from_flags, drags_from_tracks
from diff4splat.io.depth_maps import fit_depth_map, read_depth_map
from diff4splat.io.image import preprocess_image, read_image
from diff4splat.io.inputs import check_input_file
from diff4splat.io.tracks import read_tracks
from diff4splat.io.video import DEFAULT_FPS
from diff4splat.pipeline import Diff4SplatPipeline
from diff4splat.request import LoadedPipeline, SceneOutput
from diff4splat.runtime import TorchRuntime
from diff4splat.utils.costs import MEMORY_MAP_COPIES, TIME_ESTIMATE_PRINTED, generate_memory, generate_seconds

__all__ = ["generate", "scene_slots", "memory_estimate", "GENERATE_KIND"]

GENERATE_KIND = "generate"
"""Marker kind of a ``generate`` output folder (:mod:`diff4splat.io.output_folders`)."""


def scene_slots(pipe: Diff4SplatPipeline, width: int, height: int, num_frames: int) -> int:
    """``GenerationResult.num_slots`` for a ``width`` × ``height`` output of ``num_frames`` frames: photo layer and
    backdrop plus h·w per later source frame. ValueError: ``num_frames`` not 1 + 4k."""
    c = pipe.config
    return sum(layer_sizes(width, height)) + (len(pipe.source_frames(num_frames)) - 1) * c.height * c.width


def memory_estimate(pipe: Diff4SplatPipeline, width: int, height: int, num_frames: int) -> int:
    """Upper bound of ``generate``'s peak host memory, bytes, for a ``width`` × ``height`` output of ``num_frames``
    frames, from the config alone (:func:`diff4splat.utils.costs.generate_memory`; the LDRM's maps count on the
    CPU). ValueError: ``num_frames`` not 1 + 4k."""
    c, runtime = pipe.config, pipe.runtime
    n = runtime.latent.num_latent_frames(num_frames)
    return generate_memory(
        slots=scene_slots(pipe, width, height, num_frames), keys=num_frames if runtime.has_deformation else 0,
        maps=MEMORY_MAP_COPIES * n * c.height * c.width if pipe.device.type == "cpu" else 0,
        weights=runtime.host_weight_bytes() if isinstance(runtime, TorchRuntime) else 0,
        frames=num_frames, width=width, height=height)


def _check_request(image, cameras, trajectory, amplitude, steps, sampler, seed, prompt, depth, depth_kind,
                   guidance, drags, tracks) -> None:
    """The request's own checks, made before any model loads (messages name the command's flags)."""
    if drags and tracks is not None:
        raise ValueError("--drag and --tracks: give the motion one way (a tracks file holds any number of points)")
    if isinstance(image, (str, os.PathLike)):
        check_input_file(image, "image")
    if isinstance(depth, (str, os.PathLike)):
        check_input_file(depth, "--depth")
    if depth_kind not in DEPTH_KINDS:
        raise ValueError(f"--depth-kind must be one of {DEPTH_KINDS}, got {depth_kind!r}")
    if depth is None and depth_kind != "metric":
        raise ValueError(f"--depth-kind {depth_kind} describes a --depth file; none was given (the network's depth is "
                         "metric)")
    Diff4SplatPipeline.check_settings(prompt, steps, sampler, guidance, seed, flags=True)
    if cameras is not None:
        if amplitude is not None:
            raise ValueError("--amplitude scales a --trajectory preset; it does not apply to --cameras "
                             "(the camera file fixes the path)")
    else:
        check_trajectory(trajectory, "--trajectory")
        check_amplitude(trajectory, amplitude, "--amplitude")


def generate(image: str | os.PathLike | Tensor, cameras: str | os.PathLike | CameraPath | None = None, *,
             pipeline: LoadedPipeline | Diff4SplatPipeline | Callable[[], LoadedPipeline] | None = None,
             trajectory: str = DEFAULT_TRAJECTORY, amplitude: float | None = None, frames: int | None = None,
             resolution: int | None = None, prompt: str = "", steps: int | None = None, sampler: str | None = None,
             guidance: float | None = None, seed: int = 0, depth: str | os.PathLike | Tensor | None = None,
             depth_kind: str = "metric", progress: bool = False, notes: Callable[[str], None] | None = None,
             out: str | os.PathLike | None = None, overwrite: bool = False,
             inputs: Iterable[str | os.PathLike | None] = (), fps: float = DEFAULT_FPS,
             frame_plys: bool = True, drags: Sequence[str] = (),
             tracks: str | os.PathLike | None = None) -> SceneOutput:
    """A 4D scene from one photograph, rendered along its camera path (``diff4splat generate``); write the returned
    :class:`~diff4splat.request.SceneOutput` with :func:`~diff4splat.request.write`.

    Args:
        image: a photo file (EXIF orientation applied, centre-cropped to the model's aspect ratio, resized) or an
            (H, W, 3) tensor in [0, 1] at the output resolution and the model's aspect ratio.
        cameras: a camera file (``cameras.json`` or RealEstate10K ``.txt``), a :class:`CameraPath` at the output
            resolution, or None for the ``trajectory`` preset (:func:`diff4splat.cameras.make_trajectory`).
        pipeline: a :class:`~diff4splat.request.LoadedPipeline`, a bare pipeline, a zero-argument loader called
            after the request's checks, or None for the shipped model on the ``auto`` device.
        frames: T = 1 + 4k frames (default: the config's, or a camera file's count, which it must match).
        resolution: output height, pixels (default :data:`~diff4splat.pipeline.DEFAULT_RESOLUTION` or the model's
            height if larger); with a tensor image, None or its height.
        prompt, steps, sampler, guidance, seed: as :meth:`Diff4SplatPipeline.__call__`.
        depth: the photograph's depth map of ``depth_kind`` (:data:`DEPTH_KINDS`): a file (EXR channel Z, .npy,
            16-bit PNG/TIFF in millimetres) or an (H, W) tensor at the output resolution.
        notes: called with one-line notes for the user (e.g. a depth map resized).
        out, overwrite: the folder :func:`write` will fill, if known, checked first
            (:func:`~diff4splat.request.check_request`) and against its disk's free space; ``overwrite``: it may
            replace a folder that is not a ``generate`` output.
        inputs: further paths the request reads (e.g. ``--checkpoint``): no output folder may be or hold one.
        fps, frame_plys: meta.json's frame rate (1 … 1000) and whether :func:`write` writes frames/NNNN.ply.
        drags: ``"X,Y:DX,DY[@T]"`` texts (:func:`~diff4splat.geometry.drags.parse_drag`): the point (X, Y), pixels of
            the photograph as given (a file's before its crop; a tensor's own), moves by (DX, DY) pixels by
            normalised clip time T (default 1); the scene then moves only where dragged
            (:mod:`diff4splat.assembly.drag_scene`).
        tracks: instead of ``drags``, an (N, T, 2) ``.npy`` of point tracks in the same pixels
            (:func:`~diff4splat.io.tracks.read_tracks`).

    Raises:
        ValueError: an argument out of range, a limit exceeded (:class:`diff4splat.utils.limits.LimitError`), an
            ``out`` that may not be written (``OutputDirError``), a malformed input file (named); everything
            :class:`~diff4splat.pipeline.Diff4SplatPipeline` raises.
        FileNotFoundError, FileExistsError: a missing input file; as ``check_output_dir``.
    """
    t_start = time.perf_counter()
    files = {"image": image, "cameras_file": cameras, "depth_file": depth, "tracks_file": tracks}  # for meta.json
    read = [Path(p) for p in (*files.values(), *inputs) if isinstance(p, (str, os.PathLike))]
    request.check_request(out, fps, frames, resolution, cameras, inputs=read, overwrite=overwrite, kind=GENERATE_KIND)
    drags = list(drags)
    _check_request(image, cameras, trajectory, amplitude, steps, sampler, seed, prompt, depth, depth_kind, guidance,
                   drags, tracks)
    if isinstance(image, Tensor) and resolution is not None and resolution != image.shape[0]:
        raise ValueError(f"resolution={resolution} but the image tensor is {image.shape[0]} pixels high: a tensor "
                         "is used at its own resolution (resize it, or pass a photo file)")
    raw_depth = read_depth_map(depth, depth_kind) if isinstance(depth, (str, os.PathLike)) else None  # before the model
    photo = None if isinstance(image, Tensor) else read_image(image)
    moves = _drags(drags, None if tracks is None else read_tracks(tracks),
                   tuple(photo.shape[:2]) if photo is not None else tuple(image.shape[:2]))
    loaded = request.resolve_pipeline(pipeline)
    pipe, cfg = loaded.pipeline, loaded.pipeline.config
    if frames is not None:  # T = 1 + 4k, before any decoding
        pipe.check_frame_count(frames)
    if isinstance(image, Tensor):
        height, width = int(image.shape[0]), int(image.shape[1])
        pipe.output_size(height)  # the resolution limit
        photo_shape = (height, width)
    else:
        width, height = request.output_size(pipe, resolution)
    if photo is not None:
        photo_shape = photo.shape[:2]
        image = preprocess_image(photo, (height, width))
        if moves is not None:
            y0, x0, ch, cw = center_crop_box(*photo_shape, height, width)
            try:
                moves = moves.resized((x0, y0, x0 + cw, y0 + ch), width, height)
            except ValueError as e:
                raise ValueError(f"{'--drag' if drags else '--tracks'}: {e}") from None
    if raw_depth is not None:
        depth, note = fit_depth_map(raw_depth, photo_shape, (height, width))
        if note is not None and notes is not None:
            notes(f"--depth: {note}")
    if cameras is None:
        path = pipe.default_cameras(trajectory, frames, amplitude, resolution=height)
    elif isinstance(cameras, CameraPath):
        path = cameras
    else:
        path = request.cameras_from_file(Path(cameras), frames, photo_shape, width, height)
        try:  # the frame count the VAE needs, named by the file (else "video: T=7 frames" from the sampler)
            cfg.vae.num_latent_frames(len(path))
        except ValueError as e:
            raise ValueError(f"--cameras {cameras}: {len(path)} cameras, one per frame: {e}") from None
    request.check_budget(path, scene_slots(pipe, path.width, path.height, len(path)),  # before any network runs
                         memory_estimate(pipe, path.width, path.height, len(path)), knobs="--frames or --resolution",
                         out=out, frame_plys=frame_plys)
    seconds = generate_seconds(path.width, path.height, len(path))
    if seconds > TIME_ESTIMATE_PRINTED and notes is not None and pipe.device.type == "cpu":
        notes(f"{len(path)} frames at {path.width}×{path.height}: estimated {seconds:.0f} s on this CPU (lower "
              "--resolution or --frames for less)")
    result = pipe(image, path, prompt, steps=steps, sampler=sampler, guidance=guidance, seed=seed, progress=progress,
                  depth=depth if isinstance(depth, Tensor) else None, depth_kind=depth_kind, drags=moves)
    file = {key: request.file_argument(value) for key, value in files.items()}
    settings = {"image": file["image"], "prompt": prompt, "trajectory": None if cameras is not None else trajectory,
                "cameras_file": file["cameras_file"], "depth_file": file["depth_file"],
                "depth_kind": depth_kind if file["depth_file"] is not None else None, "seed": seed,
                "steps": result.steps, "sampler": result.sampler, "guidance": result.guidance, "shift": result.shift,
                "drags": drags, "tracks_file": file["tracks_file"]}
    return request.render_output(loaded, result, settings, kind=GENERATE_KIND, fps=fps, frame_plys=frame_plys,
                                 inputs=read, started=t_start, progress=progress)



def _drags(texts: list[str], tracks: np.ndarray | None, shape: tuple[int, int]) -> Drags | None:
    """The request's drags on a photograph of ``shape`` = (height, width), or None. ValueError: a point outside it
    (naming ``--drag`` or ``--tracks``)."""
    height, width = shape
    if texts:
        return drags_from_flags(texts, width, height)
    if tracks is not None:
        try:
            return drags_from_tracks(tracks, width, height)
        except ValueError as e:
            raise ValueError(f"--tracks: {e}") from None
    return None
