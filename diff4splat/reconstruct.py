"""``diff4splat reconstruct``: a real monocular video → a 4D scene that moves as the video does.

The VAE encodes the clip and the LDRM gives its source frames' depth (nothing is sampled); every frame (or the source
frames alone) becomes a photo layer (:func:`diff4splat.assembly.photo.photo_layer`) on that depth carried along the
optical flow (:func:`carried_depth`), moved by the motion measured from the frames
(:func:`diff4splat.geometry.scene_flow.source_motion`) and shown only between its neighbours' times, where the
two layers around a time cross-fade exactly (:func:`layer_support`), so only there is it tracked
(:func:`layer_spans`; frame 0's layer over the whole clip); a still clip gives a static scene
(docs/DESIGN.md, "Motion measured from frames …")::

    from diff4splat.generate import write
    from diff4splat.reconstruct import reconstruct

    write(reconstruct("clip.mp4", frames=17, stride=2), "out")
"""
from __future__ import annotations

import math
import os
import time
from collections.abc import Callable, Iterable
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor

from diff4splat.assembly.assemble import z_depth
from diff4splat.assembly.photo import PHOTO_EPS2D, backdrop_layer, layer_sizes, photo_layer, upsample_depth
from diff4splat.assembly.prune import prune_mask, settle_and_prune
from diff4splat.cameras import CameraPath, intrinsics_from_fov
from diff4splat.cameras.path import camera_centers
from diff4splat.generate import (
    Generation,
    LoadedPipeline,
    cameras_from_file,
    check_destination,
    check_frame_count,
    generation_meta,
    resolve_pipeline,
)
from diff4splat.geometry.scene_flow import chain_flows, consecutive_flows, sample_pixels, source_motion
from diff4splat.io.image import preprocess_image
from diff4splat.io.inputs import check_input_file
from diff4splat.io.video import DEFAULT_FPS
from diff4splat.io.video_input import check_clip_request, read_video_clip
from diff4splat.pipeline import DEFAULT_RESOLUTION, Diff4SplatPipeline, GenerationResult
from diff4splat.render.sequence import render_path
from diff4splat.runtime import TorchRuntime
from diff4splat.scene.dynamic import DynamicGaussians
from diff4splat.scene.gaussians import Gaussians
from diff4splat.utils.checks import check_positive_int
from diff4splat.utils.costs import (
    MEMORY_BASE_BYTES,
    MEMORY_BYTES_PER_GAUSSIAN,
    MEMORY_CUDA_BUILD_BYTES,
    MEMORY_SCENE_COPIES,
)
from diff4splat.utils.devices import Stopwatch
from diff4splat.utils.limits import check_limit, check_memory, check_output_size
from models.deformation import IDENTITY_QUAT
from models.ldrm import source_frame_indices

__all__ = ["reconstruct", "reconstruct_scene", "still_cameras", "clip_cameras", "carried_depth", "check_layers",
           "layer_frames", "check_layer_knobs", "scene_slots", "memory_estimate", "layer_support", "RECONSTRUCT_KIND",
           "LAYER_ORDER_OFFSET", "layer_spans", "FLOW_SIZE", "GATE_PX", "FB_TOLERANCE_PX", "MOVING_FRACTION", "LAYERS",
           "DEFAULT_LAYERS"]

RECONSTRUCT_KIND = "reconstruct"
"""Marker kind of a ``reconstruct`` output folder (the layout is ``generate``'s)."""
LAYER_ORDER_OFFSET = 0.015
"""The odd layers lie this fraction farther along their camera's rays than the even ones (more than a photo layer's
backing, :data:`~diff4splat.assembly.photo.BACKING_OFFSET`), so an even layer fading in front of an opaque odd
one cross-fades the two (:func:`layer_support`)."""
GATE_PX = 0.5
"""Rigidity gate of the motion, pixels of the output frames (``scene_flow.lift_tracks``)."""
FB_TOLERANCE_PX = 1.5
"""Forward-backward tolerance of the tracking, pixels of the output frames."""
MOVING_FRACTION = 0.005
"""A clip is dynamic when, at some frame, more than this fraction of a layer's pixels has moved by more than the
config's ``static_atol`` (so codec noise does not make a still video move)."""
LAYERS = ("every", "source")
"""Which frames of the clip become photo layers (``--layers``, :func:`reconstruct_scene`)."""
DEFAULT_LAYERS = "every"
"""Every frame (T·1.25 Gaussians per output pixel): an in-between time is drawn from its two neighbours' pixels."""
FLOW_SIZE = 256
"""Pixels of height the frames are tracked at (the output upsampled by the nearest whole factor)."""


def still_cameras(pipe: Diff4SplatPipeline, num_frames: int, width: int, height: int) -> CameraPath:
    """``num_frames`` identity cameras at the model's vertical field of view and ``width`` × ``height``."""
    K = intrinsics_from_fov(width, height, fov_y_deg=pipe.config.fov_y_deg)
    eye = torch.eye(4, device=K.device)
    return CameraPath(eye.expand(num_frames, 4, 4).clone(), K.expand(num_frames, 3, 3).clone(), width, height)


def _check_frames(pipe: Diff4SplatPipeline, frames: Tensor, cameras: CameraPath) -> None:
    """:func:`reconstruct_scene`'s checks of ``frames`` and ``cameras``."""
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
    check_frame_count(pipe, T)


def check_layers(layers: object) -> str:
    """``layers`` if it is one of :data:`LAYERS`; else ValueError naming ``--layers``."""
    if layers not in LAYERS:
        raise ValueError(f"--layers must be one of {LAYERS}, got {layers!r}")
    return layers


def check_layer_knobs(order_offset: object, unchecked: object) -> None:
    """ValueError unless ``order_offset`` is a finite number ≥ 0 and ``unchecked`` None or an int ≥ 0
    (:func:`reconstruct_scene`)."""
    if isinstance(order_offset, bool) or not isinstance(order_offset, (int, float)) or not 0 <= order_offset < math.inf:
        raise ValueError(f"order_offset must be a finite number >= 0, got {order_offset!r}")
    if unchecked is not None and (isinstance(unchecked, bool) or not isinstance(unchecked, int) or unchecked < 0):
        raise ValueError(f"unchecked must be None or an int >= 0, got {unchecked!r}")


def carried_depth(depths: Tensor, sources: list[int], frame: int, flows: tuple[Tensor, Tensor]) -> Tensor:
    """(H, W) z-depth, metres, of video frame ``frame`` in [0, T): its source frame's, or the nearest source frame's
    (the earlier on a tie) sampled bilinearly where the chained ``flows``
    (:func:`diff4splat.geometry.scene_flow.consecutive_flows`) carry each pixel; ``depths`` (S, H, W) are those of
    ``sources`` (increasing)."""
    if frame in sources:
        return depths[sources.index(frame)]
    s = min(range(len(sources)), key=lambda i: (abs(sources[i] - frame), sources[i]))
    f = sources[s]
    fw, bw = flows
    pair = (fw[frame:f], bw[frame:f]) if f > frame else (bw[f:frame].flip(0), fw[f:frame].flip(0))
    positions, _ = chain_flows(*pair, fb_tolerance=float("inf"))
    return sample_pixels(depths[s][None, ..., None], positions[-1][None])[0, ..., 0]


def layer_frames(pipe: Diff4SplatPipeline, num_frames: int, layers: str) -> tuple[list[int], list[int]]:
    """(the LDRM's source frames, the frames that become photo layers: all for "every", the source frames else)."""
    latent = pipe.runtime.latent
    sources = source_frame_indices(pipe.config.ldrm.gaussian_frames, latent.num_latent_frames(num_frames),
                                   latent.temporal_factor)
    return sources, list(range(num_frames)) if layers == "every" else sources


def layer_support(times: Tensor, layer: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Temporal support (t_means, t_scales, t_ramps; ``DynamicGaussians``' trapezoid) of Gaussians of the layers
    ``layer`` (K,) int64 (−1: the backdrop), the layers at the equally spaced clip times ``times`` (L,), spacing Δ:

    - an even layer is the triangle 1 − |t − t_l|/Δ, in front (:data:`LAYER_ORDER_OFFSET`);
    - an odd layer is the box |t − t_l| < Δ·(1 − 10⁻³), opaque behind (the margin: off at its neighbours' times
      whatever the rounding of clip times like i/12);
    - the backdrop is there at every t ∈ [0, 1].

    Between two layers' times exactly one is even, in front at opacity (1 − α)·o (α the weight of the later time), over
    the other at o: with the photo layers' o ≈ 1, (1 − α)·front + α·back, the cross-fade of the two, each moved to t.
    At a layer's own time only that layer is shown, so the given frames come back as their photo layers render them.
    """
    L = times.shape[0]
    spacing = times[1] - times[0] if L > 1 else times.new_tensor(1.0)
    own = times[layer.clamp(min=0)]
    even = layer % 2 == 0
    back = layer < 0
    t_means = torch.where(back, times.new_tensor(0.5), own)
    t_scales = torch.where(back, times.new_tensor(1.0), torch.where(even, spacing, spacing * (1 - 1e-3)))
    t_ramps = torch.where(even & ~back, spacing.expand_as(own), times.new_zeros(()))
    return t_means, t_scales, t_ramps


def _pushed_back(layer: Gaussians, viewmat: Tensor, factor: float) -> Gaussians:
    """``layer`` scaled by ``factor`` about its camera's centre (``viewmat`` (4, 4) world-to-camera): each Gaussian
    ``factor`` times as far along its ray, and as large, so its image does not change."""
    centre = camera_centers(viewmat[None])[0]
    return Gaussians(centre + (layer.means - centre) * factor, layer.quats, layer.scales * factor, layer.opacities,
                     layer.sh)


def layer_spans(frames_of: list[int]) -> list[tuple[int, int]]:
    """Each layer's tracked frames (first, last): frame 0's layer over the whole clip (the clip's 3D tracks), every
    other from its previous layer's frame to its next one's, the only times it is shown (:func:`layer_support`)."""
    last = frames_of[-1]
    return [(0, last) if s == 0 else (frames_of[s - 1], frames_of[min(s + 1, len(frames_of) - 1)])
            for s in range(len(frames_of))]


def _layer_motion(motion: Tensor, height: int, width: int) -> Tensor:
    """Per-pixel displacements (K, H, W, 3) → the photo layer's (K, H·W + ⌈H/2⌉·⌈W/2⌉, 3) (backing: 2×2 means)."""
    K = motion.shape[0]
    block = F.avg_pool2d(motion.permute(0, 3, 1, 2), 2, ceil_mode=True).permute(0, 2, 3, 1)
    return torch.cat([motion.reshape(K, height * width, 3), block.reshape(K, -1, 3)], dim=1)


@torch.no_grad()
def reconstruct_scene(pipe: Diff4SplatPipeline, frames: Tensor, cameras: CameraPath, *,
                      layers: str = DEFAULT_LAYERS, order_offset: float = LAYER_ORDER_OFFSET,
                      unchecked: int | None = None) -> GenerationResult:
    """The 4D scene (module docstring) of a clip ``frames`` (T, H, W, 3) in [0, 1] at the output resolution and the
    model's aspect ratio, T = 1 + 4k, seen by ``cameras`` (T at the output resolution, made relative to the first),
    ``layers`` (:data:`LAYERS`) its photo layers; ``order_offset`` how far odd layers are pushed back along their rays
    (a fraction of their distance, :func:`layer_support`); ``unchecked`` how many first links of flow each layer
    follows whatever their forward-backward error (None: the spacing of layer frames, as far as the layer is seen;
    :func:`~diff4splat.geometry.scene_flow.chain_flows`). Returns a :class:`~diff4splat.pipeline.GenerationResult`
    (``steps`` 0, ``sampler`` "none", ``latents`` the video's, ``source_frames`` the layer frames; unpruned order:
    frame 0's layer, the backdrop, the other layers).

    Raises:
        ValueError: bad frames, T ≠ 1 + 4k, cameras not T at (W, H), an unknown ``layers``, an ``order_offset`` that
            is not a finite number ≥ 0, an ``unchecked`` that is not None or an int ≥ 0; a path that sees nothing.
    """
    _check_frames(pipe, frames, cameras)
    check_layers(layers)
    check_layer_knobs(order_offset, unchecked)
    cfg, runtime, dev = pipe.config, pipe.runtime, pipe.device
    T, H, W = frames.shape[:3]
    cameras = cameras.relative_to_first().to(dtype=torch.float32, device=dev)
    cameras_model = cameras.resized(cfg.width, cfg.height)
    clock, timings = Stopwatch(dev), {}
    images = frames.to(dev, torch.float32)  # (T, H, W, 3)
    small = F.interpolate(images.permute(0, 3, 1, 2), size=(cfg.height, cfg.width), mode="area")
    video = (small * 2 - 1).transpose(0, 1)[None]  # (1, 3, T, h, w) in [−1, 1]
    latents = runtime.encode_image(video)  # the clip's own latents (posterior mean)
    timings["encode_video"] = clock.lap()
    out = runtime.reconstruct(latents, pipe.packed_plucker(cameras_model), None, video[:, :, 0])
    runtime.release()
    indices, frames_of = layer_frames(pipe, T, layers)
    sources = torch.tensor(indices, device=dev)
    z_model = z_depth(out.distance[0], cameras_model.viewmats[sources], cameras_model.Ks[sources])  # (S, h, w)
    z_src = torch.stack([upsample_depth(z_model[s], images[f]) for s, f in enumerate(indices)])  # (S, H, W)
    timings["reconstruct"] = clock.lap()
    flows = consecutive_flows(images.permute(0, 3, 1, 2), upsample=max(1, round(FLOW_SIZE / H)))
    z = torch.stack([carried_depth(z_src, indices, f, flows) for f in frames_of])  # (L, H, W)
    spacing = frames_of[1] - frames_of[0] if len(frames_of) > 1 else 1  # a layer is seen this far from its frame
    # The backdrop (static, behind everything) first: when the scene moves, the only pruning is of its cells that no
    # camera sees, so the layers' motion is laid out for the kept cells alone and never copied by a selection.
    backdrop = backdrop_layer(images[0], z[0], cameras.viewmats[0], cameras.Ks[0])
    seen, stats = prune_mask(DynamicGaussians(backdrop), cameras, min_opacity=cfg.prune_opacity)
    timings["backdrop"] = clock.lap()
    photo, L = layer_sizes(W, H)[0], len(frames_of)
    kept = int(seen.sum())
    offsets = [0] + [photo + kept + (s - 1) * photo for s in range(1, L)]  # each layer's first Gaussian
    # Each layer's motion, tracked only over the frames it is shown at (layer_spans), written in place: the scene's
    # (T, N, 3) is the one copy of it.
    d_means = z.new_zeros(T, L * photo + kept, 3)
    dynamic = False
    for s, (lo, hi) in enumerate(layer_spans(frames_of)):
        motion = source_motion(flows, z, frames_of, s, cameras.Ks, cameras.viewmats, (lo, hi),
                               fb_tolerance=FB_TOLERANCE_PX, gate_px=GATE_PX,
                               unchecked=spacing if unchecked is None else unchecked)  # (hi − lo + 1, H, W, 3)
        moved = (motion.abs() > cfg.static_atol).any(dim=-1).flatten(1).float().mean(dim=-1)  # (hi − lo + 1,)
        dynamic = dynamic or bool((moved > MOVING_FRACTION).any())
        d_means[lo:hi + 1, offsets[s]:offsets[s] + photo] = _layer_motion(motion, H, W)
        del motion
    timings["motion"] = clock.lap()
    if not dynamic:  # a still world: every backdrop cell goes to settle_and_prune with the layers
        del d_means
    parts, grid = [], []  # the layers and the backdrop, in the scene's order
    for s, f in enumerate(frames_of):
        layer, history = photo_layer(images[f], z[s], cameras.viewmats[f], cameras.Ks[f])
        if dynamic and s % 2:  # odd layers behind (layer_support)
            parts.append(_pushed_back(layer, cameras.viewmats[f], 1 + order_offset))
            d_means[:, offsets[s]:offsets[s] + photo] *= 1 + order_offset
        else:
            parts.append(layer)
        grid.append(torch.full((layer.num_gaussians,), s, dtype=torch.long, device=dev))
        if s == 0:
            photo_psnr = history[-1]
            parts.append(backdrop.select(seen) if dynamic else backdrop)
            grid.append(torch.zeros(parts[-1].num_gaussians, dtype=torch.long, device=dev))
    canonical = Gaussians(*(torch.cat([getattr(g, f) for g in parts])
                            for f in ("means", "quats", "scales", "opacities", "sh")))
    grid = torch.cat(grid)
    N, n0, n_back = L * photo + backdrop.num_gaussians, parts[0].num_gaussians, parts[1].num_gaussians
    if dynamic:  # each layer between its neighbours' times, the two around a time cross-faded (layer_support)
        layer_of = grid.clone()
        layer_of[n0:n0 + n_back] = -1  # the backdrop
        support = layer_support(cameras.times[torch.tensor(frames_of, device=dev)].float(), layer_of)
        M = canonical.num_gaussians
        scene = DynamicGaussians(canonical, cameras.times, d_means,
                                 canonical.means.new_tensor(IDENTITY_QUAT).expand(T, M, 4),
                                 canonical.means.new_zeros(()).expand(T, M, 3), *support)
        timings["assemble"] = clock.lap()
        # every layer is observed: only the backdrop's unseen cells went (above)
        slots, end = torch.arange(N, device=dev), n0 + backdrop.num_gaussians
        index = torch.cat([slots[:n0], slots[n0:end][seen], slots[end:]])
        stats = {**stats, "before": N, "after": M, "duplicates": 0, "slid": 0, "occluders": 0}
    else:  # a still world: the layers of one static scene, overlaps settled as generate settles its frames
        scene = DynamicGaussians(canonical)
        timings["assemble"] = clock.lap()
        scene, index, stats = settle_and_prune(scene, grid, cameras, torch.tensor(frames_of, device=dev), z[0], n0,
                                               cfg.prune_opacity)
    timings["prune"] = clock.lap()
    return GenerationResult(scene=scene, cameras=cameras, latents=latents, steps=0, sampler="none", guidance=1.0,
                            shift=cfg.sampling.shift, timings=timings,
                            high_water=dict(zip(timings, clock.high_water, strict=False)), prune_stats=stats,
                            source_frames=torch.tensor(frames_of, device=dev), gaussian_index=index, eps2d=PHOTO_EPS2D,
                            background=tuple(float(c) for c in images[0].reshape(-1, 3).mean(0)),
                            photo_psnr_db=photo_psnr, num_slots=N, photo_gaussians=n0)


def clip_cameras(cameras: CameraPath, indices: list[int], source: object = "cameras") -> CameraPath:
    """The clip's cameras: ``cameras`` when there is one per clip frame, else those at its video frames
    ``indices``; times i/(T−1). ValueError naming ``--cameras`` ``source`` when there are neither."""
    T = len(indices)
    if len(cameras) == T:
        index = list(range(T))
    elif len(cameras) > indices[-1]:
        index = indices
    else:
        raise ValueError(f"--cameras {source}: {len(cameras)} cameras, but the clip needs {T} (one per clip frame) "
                         f"or one per video frame up to frame {indices[-1]}")
    return CameraPath(cameras.viewmats[index], cameras.Ks[index], cameras.width, cameras.height)


def scene_slots(width: int, height: int, num_layers: int) -> int:
    """``GenerationResult.num_slots``: ``num_layers`` photo layers at ``width`` × ``height`` and one backdrop."""
    photo, backdrop = layer_sizes(width, height)
    return num_layers * photo + backdrop


def memory_estimate(pipe: Diff4SplatPipeline, width: int, height: int, frames: int, num_layers: int) -> int:
    """Upper bound of ``reconstruct``'s peak host memory, bytes (constants of
    :meth:`Diff4SplatPipeline.memory_estimate`): process and weights; per slot its attributes and its Δμ, T × 3
    floats, × (copies + 1) (the rotations and scales are one row shared by every Gaussian); one layer's motion over
    the whole clip (frame 0's, :func:`layer_spans`), T × H × W × 3 floats, four times (its tracks, its lifting and
    its layer's copy); the flows; the frames, T × H × W × 5 floats, twice."""
    slots = scene_slots(width, height, num_layers)
    weights = pipe.runtime.host_weight_bytes() if isinstance(pipe.runtime, TorchRuntime) else 0
    base = MEMORY_BASE_BYTES + (MEMORY_CUDA_BUILD_BYTES if torch.backends.cuda.is_built() else 0)
    pixels = width * height
    return int(base + weights + slots * (MEMORY_BYTES_PER_GAUSSIAN + 12 * frames * (MEMORY_SCENE_COPIES + 1))
               + 4 * 12 * frames * pixels + 16 * frames * pixels + 2 * 20 * frames * pixels)


def reconstruct(video: str | os.PathLike, cameras: str | os.PathLike | CameraPath | None = None, *,
                pipeline: LoadedPipeline | Diff4SplatPipeline | Callable[[], LoadedPipeline] | None = None,
                frames: int | None = None, stride: int = 1, start: int = 0, resolution: int | None = None,
                layers: str = DEFAULT_LAYERS, order_offset: float = LAYER_ORDER_OFFSET, unchecked: int | None = None,
                progress: bool = False, out: str | os.PathLike | None = None,
                overwrite: bool = False, inputs: Iterable[str | os.PathLike | None] = (), fps: float = DEFAULT_FPS,
                frame_plys: bool = True) -> Generation:
    """A 4D scene of a video clip, rendered at its own cameras (``diff4splat reconstruct``): a
    :class:`~diff4splat.generate.Generation` of kind :data:`RECONSTRUCT_KIND` (write it with
    :func:`diff4splat.generate.write`).

    Args:
        video: a video file (any format OpenCV reads) or a folder of frames (images, in name order).
        cameras: a camera file (one camera per clip frame or per video frame, :func:`clip_cameras`), a
            :class:`CameraPath` at the output resolution, or None: a still camera (:func:`still_cameras`).
        frames, stride, start: the clip is T = 1 + 4k (default: the config's) frames ``start + stride·i`` of the video.
        resolution: output height, pixels (default as ``generate``'s); frames are cropped and resized as its photo.
        layers: which frames become photo layers (:data:`LAYERS`).
        order_offset, unchecked: as :func:`reconstruct_scene` (the layers' order and how far their tracks are
            followed unchecked).
        pipeline, progress, out, overwrite, inputs, fps, frame_plys: as :func:`diff4splat.generate.generate`.

    Raises FileNotFoundError for a missing video or camera file, FileExistsError as ``check_output_dir``, ValueError for
    an ``out`` that may not be written, a bad ``fps`` or clip request, a malformed video or camera file, limits exceeded
    (before the networks run) and everything :func:`reconstruct_scene` raises.
    """
    t_start = time.perf_counter()
    read = [Path(p) for p in (video, cameras, *inputs) if isinstance(p, (str, os.PathLike))]
    check_destination(out, fps, inputs=read, overwrite=overwrite, kind=RECONSTRUCT_KIND)
    if not Path(video).is_dir():
        check_input_file(video, "video")
    if frames is not None:
        check_limit("frames", check_positive_int("--frames", frames), "--frames")
    check_clip_request(frames or 1, stride, start)
    if isinstance(cameras, (str, os.PathLike)):
        check_input_file(cameras, "--cameras")
    if resolution is not None:
        check_limit("resolution", check_positive_int("--resolution", resolution), "--resolution")
    check_layers(layers)
    check_layer_knobs(order_offset, unchecked)
    loaded = resolve_pipeline(pipeline)
    pipe, cfg = loaded.pipeline, loaded.pipeline.config
    T = frames or cfg.num_frames
    check_frame_count(pipe, T)
    width, height = pipe.output_size(resolution if resolution is not None else max(DEFAULT_RESOLUTION, cfg.height))
    clip = read_video_clip(video, T, stride, start)
    shape = clip.frames[0].shape[:2]
    images = torch.stack([preprocess_image(f, (height, width)) for f in clip.frames])  # (T, H, W, 3)
    if cameras is None:
        path = still_cameras(pipe, T, width, height)
    elif isinstance(cameras, CameraPath):
        path = cameras
    else:
        path = clip_cameras(cameras_from_file(Path(cameras), None, shape, width, height), clip.indices, cameras)
    num_layers = len(layer_frames(pipe, T, layers)[1])
    knobs = "--frames, --resolution or --layers source"
    check_output_size(T, width, height, scene_slots(width, height, num_layers), knobs=knobs, out=out,
                      frame_plys=frame_plys)
    check_memory(memory_estimate(pipe, width, height, T, num_layers), f"{T} frames at {width}×{height}", knobs)
    result = reconstruct_scene(pipe, images, path, layers=layers, order_offset=order_offset, unchecked=unchecked)
    t0 = time.perf_counter()
    colors, depths, alphas = render_path(result.scene, result.cameras, eps2d=result.eps2d,
                                         background=result.background, progress=progress)
    timings = {"load_model": loaded.load_seconds, **result.timings, "render": time.perf_counter() - t0}
    files = {"image": None, "cameras_file": cameras, "depth_file": None}
    meta = generation_meta(loaded, result, "", None, files, "metric", 0, timings, fps)
    for key in ("image", "prompt", "trajectory", "seed", "steps", "sampler", "guidance", "shift", "depth_file",
                "depth_kind"):
        meta.pop(key)
    meta.update(video=str(video), video_frames=clip.indices, video_fps=clip.fps, kind=RECONSTRUCT_KIND, layers=layers,
                frame_plys=bool(frame_plys) and result.scene.changes_with_time)
    return Generation(result, colors, depths, alphas, meta, read + list(loaded.files), cfg.scene_depth,
                      time.perf_counter() - t_start, kind=RECONSTRUCT_KIND)
