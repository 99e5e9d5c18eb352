"""``diff4splat reconstruct``: a real monocular video → a 4D scene that moves as the video does.

The LDRM reads the video's own latents (the VAE encodes the clip; nothing is sampled) and places the pixel-aligned
Gaussians of its source frames (docs/DESIGN.md, "Data flow of generate", step 6); the video is observed, not
generated, so it is kept as ``generate`` keeps the photograph: frame 0 becomes the photo layer at the output
resolution, the later source frames' Gaussians carry the video's own pixels (``assemble.video_colors`` of the
real frames), and the scene's motion is measured from the frames (:func:`diff4splat.scene_flow.source_frame_motion`:
OpenCV's DIS optical flow, chained and lifted to 3D with the LDRM's depth of the source frames) at every frame's
time, so the deformation interpolates between consecutive frames. A still video gives a static scene (the rigidity
gate keeps every static point at rest; no deformation is written).

Library use mirrors :mod:`diff4splat.generate`::

    from diff4splat.generate import write
    from diff4splat.reconstruct import reconstruct

    write(reconstruct("clip.mp4", frames=17, stride=2), "out")
"""
from __future__ import annotations

import os
import time
from collections.abc import Callable
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor

from models.deformation import IDENTITY_QUAT
from models.ldrm import source_frame_indices

from .assemble import assemble_scene, z_depth
from .cameras import CameraPath, intrinsics_from_fov
from .checks import check_positive_int
from .devices import Stopwatch
from .generate import Generation, LoadedPipeline, cameras_from_file, generation_meta, load_pipeline
from .io.image import preprocess_image
from .io.inputs import check_input_file
from .io.video_input import check_clip_request, read_video_clip
from .limits import check_limit, check_memory, check_output_size
from .photo import PHOTO_EPS2D
from .pipeline import DEFAULT_RESOLUTION, Diff4SplatPipeline, GenerationResult
from .render.sequence import render_path
from .scene_flow import source_frame_motion

__all__ = ["reconstruct", "reconstruct_scene", "still_cameras", "RECONSTRUCT_KIND"]

RECONSTRUCT_KIND = "reconstruct"
"""Marker kind of a ``reconstruct`` output folder (the layout is ``generate``'s)."""


def still_cameras(pipe: Diff4SplatPipeline, num_frames: int, width: int, height: int) -> CameraPath:
    """A camera that does not move: every frame the identity viewmat, the model's vertical field of view at
    ``width`` × ``height``; times i/(T−1)."""
    K = intrinsics_from_fov(width, height, fov_y_deg=pipe.config.fov_y_deg)
    return CameraPath(torch.eye(4).expand(num_frames, 4, 4).clone(), K.expand(num_frames, 3, 3).clone(), width,
                      height)


def _check_frames(pipe: Diff4SplatPipeline, frames: Tensor, cameras: CameraPath) -> None:
    cfg = pipe.config
    if frames.dim() != 4 or frames.shape[-1] != 3 or not frames.is_floating_point():
        raise ValueError(f"frames must be a float tensor (T, H, W, 3), got {tuple(frames.shape)} {frames.dtype}")
    T, H, W = frames.shape[:3]
    if not bool(((frames >= 0) & (frames <= 1)).all()):
        raise ValueError("frames must lie in [0, 1]")
    if H * cfg.width != W * cfg.height:
        raise ValueError(f"frames are {W}×{H}; the model's aspect ratio is {cfg.width}:{cfg.height}")
    if len(cameras) != T or (cameras.width, cameras.height) != (W, H):
        raise ValueError(f"cameras: {len(cameras)} at {cameras.width}×{cameras.height}, the frames: {T} at {W}×{H}")
    try:
        pipe.runtime.latent.num_latent_frames(T)
    except ValueError:
        raise ValueError(f"--frames {T}: the frame count must be {pipe.runtime.latent.frames_rule}") from None


@torch.no_grad()
def reconstruct_scene(pipe: Diff4SplatPipeline, frames: Tensor, cameras: CameraPath) -> GenerationResult:
    """The 4D scene of a video clip (module docstring).

    Args:
        pipe: the networks (their VAE encoder and LDRM run; no text encoder, no DiT).
        frames: (T, H, W, 3) RGB in [0, 1] at the output resolution and the model's aspect ratio, T = 1 + 4k.
        cameras: the T cameras at the output resolution (re-expressed relative to the first).

    Returns:
        :class:`~diff4splat.pipeline.GenerationResult` (``steps`` 0, ``sampler`` "none": nothing sampled;
        ``latents``: the video's own; key times of the deformation: the frames' times).

    Raises:
        ValueError: frames not (T, H, W, 3) in [0, 1] at the model's aspect ratio, T ≠ 1 + 4k, cameras not T at
            (W, H); a camera path that sees none of the scene.
    """
    _check_frames(pipe, frames, cameras)
    cfg, runtime, dev = pipe.config, pipe.runtime, pipe.device
    T, H, W = frames.shape[:3]
    cameras = cameras.relative_to_first().to(dtype=torch.float32, device=dev)
    cameras_model = cameras.resized(cfg.width, cfg.height)
    clock, timings = Stopwatch(dev), {}
    small = frames.to(dev, torch.float32).permute(0, 3, 1, 2)  # (T, 3, H, W)
    if (H, W) != (cfg.height, cfg.width):
        small = F.interpolate(small, size=(cfg.height, cfg.width), mode="area")
    video = (small * 2 - 1).transpose(0, 1)[None]  # (1, 3, T, h, w) in [−1, 1]
    latents = runtime.encode_image(video)  # the clip's own latents (posterior mean)
    timings["encode_video"] = clock.lap()
    out = runtime.reconstruct(latents, pipe.packed_plucker(cameras_model), None, video[:, :, 0])
    runtime.release()
    n = runtime.latent.num_latent_frames(T)
    indices = source_frame_indices(cfg.ldrm.gaussian_frames, n, runtime.latent.temporal_factor)
    sources = torch.tensor(indices, device=dev)
    timings["reconstruct"] = clock.lap()
    z = z_depth(out.distance[0], cameras_model.viewmats[sources], cameras_model.Ks[sources])  # (S, h, w)
    d_means = source_frame_motion(small.clamp(0, 1), z, indices, cameras_model.Ks, cameras_model.viewmats)
    maps = d_means.shape[:-1]  # (T, S, h, w)
    out.d_means = d_means[None]
    out.d_quats = d_means.new_tensor(IDENTITY_QUAT).expand(1, *maps, 4)
    out.d_scales = d_means.new_zeros(1, *maps, 3)
    timings["motion"] = clock.lap()
    scene, grid, photo = assemble_scene(out, sources, cameras_model, cameras, frames[0].to(dev, torch.float32),
                                        cameras.times, video=video, footprint=cfg.generated_footprint)
    scene = scene.without_deformation(cfg.static_atol)
    timings["assemble"] = clock.lap()
    scene, index, stats = pipe.settle_and_prune(scene, grid, cameras, sources, photo)
    timings["prune"] = clock.lap()
    return GenerationResult(scene=scene, cameras=cameras, latents=latents, steps=0, sampler="none", guidance=1.0,
                            shift=cfg.sampling.shift, timings=timings,
                            high_water=dict(zip(timings, clock.high_water, strict=False)), prune_stats=stats,
                            source_frames=sources, gaussian_index=index, eps2d=PHOTO_EPS2D,
                            background=photo["background"], photo_psnr_db=photo["photo_psnr_db"],
                            num_slots=int(grid.shape[0]), photo_gaussians=photo["photo_gaussians"])


def reconstruct(
    video: str | os.PathLike,
    cameras: str | os.PathLike | CameraPath | None = None,
    *,
    pipeline: LoadedPipeline | Diff4SplatPipeline | Callable[[], LoadedPipeline] | None = None,
    frames: int | None = None,
    stride: int = 1,
    start: int = 0,
    resolution: int | None = None,
    progress: bool = False,
    out: str | os.PathLike | None = None,
    frame_plys: bool = True,
) -> Generation:
    """A 4D scene of a video clip, rendered at its own cameras (the ``diff4splat reconstruct`` command).

    Args:
        video: a video file (any format OpenCV reads) or a folder of frames (images, in name order).
        cameras: a camera file (cameras.json or RealEstate10K .txt, one camera per chosen frame), a
            :class:`CameraPath` at the output resolution, or None: a still camera (:func:`still_cameras`).
        pipeline: as :func:`diff4splat.generate.generate`.
        frames: T = 1 + 4k frames of the clip (default: the config's).
        stride, start: the clip is frames ``start + stride·i`` of the video.
        resolution: output height, pixels (default: 256, or the model's height if larger); every frame is
            centre-cropped to the model's aspect ratio and resized (as ``generate``'s photograph).
        progress: tqdm progress bar while rendering.
        out, frame_plys: as :func:`diff4splat.generate.generate`.

    Returns:
        :class:`~diff4splat.generate.Generation` (write it with :func:`diff4splat.generate.write`; its folder's
        marker kind is :data:`RECONSTRUCT_KIND`).

    Raises:
        FileNotFoundError: a missing video or camera file.
        ValueError: a bad clip request or one the video is too short for, a malformed video or camera file,
            limits exceeded (before the networks run), everything :func:`reconstruct_scene` raises.
    """
    t_start = time.perf_counter()
    if not Path(video).is_dir():
        check_input_file(video, "video")
    if frames is not None:
        check_limit("frames", check_positive_int("--frames", frames), "--frames")
    check_clip_request(frames or 1, stride, start)
    if isinstance(cameras, (str, os.PathLike)):
        check_input_file(cameras, "--cameras")
    if resolution is not None:
        check_limit("resolution", check_positive_int("--resolution", resolution), "--resolution")
    loaded = pipeline() if callable(pipeline) and not isinstance(pipeline, Diff4SplatPipeline) else pipeline
    if loaded is None:
        loaded = load_pipeline()
    elif isinstance(loaded, Diff4SplatPipeline):
        loaded = LoadedPipeline(loaded, "pipeline", dtype=None, offload=None)
    pipe, cfg = loaded.pipeline, loaded.pipeline.config
    T = frames or cfg.num_frames
    try:
        cfg.vae.num_latent_frames(T)
    except ValueError:
        raise ValueError(f"--frames {T}: the frame count must be {pipe.runtime.latent.frames_rule}") from None
    width, height = pipe.output_size(resolution if resolution is not None else max(DEFAULT_RESOLUTION, cfg.height))
    clip = read_video_clip(video, T, stride, start)
    shape = clip.frames[0].shape[:2]
    images = torch.stack([preprocess_image(f, (height, width)) for f in clip.frames])  # (T, H, W, 3)
    if cameras is None:
        path = still_cameras(pipe, T, width, height)
    elif isinstance(cameras, CameraPath):
        path = cameras
    else:
        path = cameras_from_file(Path(cameras), T, shape, width, height)
    check_output_size(T, width, height, pipe.scene_slots(width, height, T), knobs="--frames or --resolution", out=out,
                      frame_plys=frame_plys)
    check_memory(pipe.memory_estimate(width, height, T), f"{T} frames at {width}×{height}", "--frames or --resolution")
    result = reconstruct_scene(pipe, images, path)
    t0 = time.perf_counter()
    colors, depths, alphas = render_path(result.scene, result.cameras, eps2d=result.eps2d,
                                         background=result.background, progress=progress)
    timings = {"load_model": loaded.load_seconds, **result.timings, "render": time.perf_counter() - t0}
    files = {"image": None, "cameras_file": cameras, "depth_file": None}
    meta = generation_meta(loaded, result, "", None, files, "metric", 0, timings)
    for key in ("image", "prompt", "trajectory", "seed", "steps", "sampler", "guidance", "shift", "depth_file",
                "depth_kind"):
        meta.pop(key)
    meta.update(video=str(video), video_frames=clip.indices, video_fps=clip.fps, kind=RECONSTRUCT_KIND,
                frame_plys=bool(frame_plys) and result.scene.changes_with_time)
    inputs = [Path(video)] + ([Path(cameras)] if isinstance(cameras, (str, os.PathLike)) else []) + list(loaded.files)
    return Generation(result, colors, depths, alphas, meta, inputs, cfg.scene_depth, time.perf_counter() - t_start,
                      kind=RECONSTRUCT_KIND)
