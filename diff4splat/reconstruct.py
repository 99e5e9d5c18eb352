"""``diff4splat reconstruct`` as a library function: a real monocular video → a 4D scene that moves as the video
does (:meth:`Diff4SplatPipeline.reconstruct`; its layers: :mod:`diff4splat.assembly.layers`), written with
:func:`diff4splat.request.write`::

    from diff4splat.reconstruct import reconstruct
    from diff4splat.request import write

    write(reconstruct("clip.mp4", frames=17, stride=2), "out")
"""
from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterable
from pathlib import Path

import torch

from diff4splat import request
from diff4splat.assembly.layers import (
    DEFAULT_LAYERS,
    LAYER_ORDER_OFFSET,
    check_layer_knobs,
    check_layers,
    layer_frames,
    layer_slots,
)
from diff4splat.cameras import CameraPath, intrinsics_from_fov
from diff4splat.io.image import preprocess_image
from diff4splat.io.inputs import check_input_file
from diff4splat.io.video import DEFAULT_FPS
from diff4splat.io.video_input import check_clip_request, read_video_clip
from diff4splat.pipeline import Diff4SplatPipeline
from diff4splat.request import LoadedPipeline, SceneOutput
from diff4splat.runtime import TorchRuntime
from diff4splat.utils.costs import reconstruct_memory

__all__ = ["reconstruct", "still_cameras", "clip_cameras", "memory_estimate", "RECONSTRUCT_KIND"]

RECONSTRUCT_KIND = "reconstruct"
"""Marker kind of a ``reconstruct`` output folder (the layout is ``generate``'s)."""


def still_cameras(pipe: Diff4SplatPipeline, num_frames: int, width: int, height: int) -> CameraPath:
    """``num_frames`` identity cameras at the model's vertical field of view and ``width`` × ``height``."""
    K = intrinsics_from_fov(width, height, fov_y_deg=pipe.config.fov_y_deg)
    eye = torch.eye(4, device=K.device)
    return CameraPath(eye.expand(num_frames, 4, 4).clone(), K.expand(num_frames, 3, 3).clone(), width, height)


def clip_cameras(cameras: CameraPath, indices: list[int], source: object = "cameras",
                 total: int | None = None) -> CameraPath:
    """The clip's cameras: ``cameras`` when there is one per clip frame, else those at its video frames
    ``indices`` when there is one per video frame (``total`` of them; None: a video that does not state its count,
    at least up to its last frame); times i/(T−1). ValueError naming ``--cameras`` ``source`` when there are
    neither."""
    T = len(indices)
    if len(cameras) == T:
        index = list(range(T))
    elif len(cameras) == total or (total is None and len(cameras) > indices[-1]):
        index = indices
    else:
        per_video = f"{total} (one per video frame)" if total is not None else \
            f"one per video frame up to frame {indices[-1]}"
        raise ValueError(f"--cameras {source}: {len(cameras)} cameras, but the clip needs {T} (one per clip frame) "
                         f"or {per_video}")
    return CameraPath(cameras.viewmats[index], cameras.Ks[index], cameras.width, cameras.height)


def memory_estimate(pipe: Diff4SplatPipeline, width: int, height: int, frames: int, num_layers: int) -> int:
    """Upper bound of ``reconstruct``'s peak host memory, bytes, for ``frames`` frames at ``width`` × ``height`` and
    ``num_layers`` photo layers (:func:`diff4splat.utils.costs.reconstruct_memory`)."""
    return reconstruct_memory(
        slots=layer_slots(width, height, num_layers), frames=frames, width=width, height=height,
        weights=pipe.runtime.host_weight_bytes() if isinstance(pipe.runtime, TorchRuntime) else 0)


def reconstruct(video: str | os.PathLike, cameras: str | os.PathLike | CameraPath | None = None, *,
                pipeline: LoadedPipeline | Diff4SplatPipeline | Callable[[], LoadedPipeline] | None = None,
                frames: int | None = None, stride: int = 1, start: int = 0, resolution: int | None = None,
                layers: str = DEFAULT_LAYERS, order_offset: float = LAYER_ORDER_OFFSET, unchecked: int | None = None,
                progress: bool = False, out: str | os.PathLike | None = None,
                overwrite: bool = False, inputs: Iterable[str | os.PathLike | None] = (), fps: float = DEFAULT_FPS,
                frame_plys: bool = True) -> SceneOutput:
    """A 4D scene of a video clip, rendered at its own cameras (``diff4splat reconstruct``): a
    :class:`~diff4splat.request.SceneOutput` of kind :data:`RECONSTRUCT_KIND` (write it with
    :func:`diff4splat.request.write`).

    Args:
        video: a video file (any format OpenCV reads) or a folder of frames (images, in name order).
        cameras: a camera file (one camera per clip frame or per video frame, :func:`clip_cameras`), a
            :class:`CameraPath` at the output resolution, or None: a still camera (:func:`still_cameras`).
        frames, stride, start: the clip is T = 1 + 4k (default: the config's) frames ``start + stride·i`` of the video.
        resolution: output height, pixels (default as ``generate``'s); frames are cropped and resized as its photo.
        layers: which frames become photo layers (:data:`~diff4splat.assembly.layers.LAYERS`).
        order_offset, unchecked: as :func:`~diff4splat.assembly.layers.layered_scene` (the layers' order and how far
            their tracks are followed unchecked).
        pipeline, progress, out, overwrite, inputs, fps, frame_plys: as :func:`diff4splat.generate.generate`.

    Raises FileNotFoundError for a missing video or camera file, FileExistsError as ``check_output_dir``, ValueError for
    an ``out`` that may not be written, a bad ``fps`` or clip request, a malformed video or camera file, limits exceeded
    (before the networks run) and everything :meth:`Diff4SplatPipeline.reconstruct` raises.
    """
    t_start = time.perf_counter()
    read = [Path(p) for p in (video, cameras, *inputs) if isinstance(p, (str, os.PathLike))]
    request.check_request(out, fps, frames, resolution, cameras, inputs=read, overwrite=overwrite,
                          kind=RECONSTRUCT_KIND)
    if not Path(video).is_dir():
        check_input_file(video, "video")
    check_clip_request(frames, stride, start)
    check_layers(layers)
    check_layer_knobs(order_offset, unchecked)
    loaded = request.resolve_pipeline(pipeline)
    pipe, cfg = loaded.pipeline, loaded.pipeline.config
    T = frames or cfg.num_frames
    pipe.check_frame_count(T)
    width, height = request.output_size(pipe, resolution)
    clip = read_video_clip(video, T, stride, start)
    shape = clip.frames[0].shape[:2]
    images = torch.stack([preprocess_image(f, (height, width)) for f in clip.frames])  # (T, H, W, 3)
    if cameras is None:
        path = still_cameras(pipe, T, width, height)
    elif isinstance(cameras, CameraPath):
        path = cameras
    else:
        path = clip_cameras(request.cameras_from_file(Path(cameras), None, shape, width, height), clip.indices,
                            cameras, clip.total)
    num_layers = len(layer_frames(pipe.source_frames(T), T, layers))
    memory = memory_estimate(pipe, width, height, T, num_layers)
    request.check_budget(path, layer_slots(width, height, num_layers), memory,
                         knobs="--frames, --resolution or --layers source", out=out, frame_plys=frame_plys)
    result = pipe.reconstruct(images, path, layers=layers, order_offset=order_offset, unchecked=unchecked)
    settings = {"cameras_file": request.file_argument(cameras), "video": str(video), "video_frames": clip.indices,
                "video_fps": clip.fps, "kind": RECONSTRUCT_KIND, "layers": layers}
    return request.render_output(loaded, result, settings, kind=RECONSTRUCT_KIND, fps=fps, frame_plys=frame_plys,
                                 inputs=read, started=t_start, progress=progress)
