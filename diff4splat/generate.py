"""``generate`` as a library function: a photograph (+ a camera path, a prompt) → a 4D scene rendered along the path
(:func:`generate`), and its output folder (:func:`write`), e.g. ``write(generate("photo.jpg", frames=17), "out")``.
Every argument is checked once, by the function it enters, before the model loads (limits before the networks run).
"""
from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor

from diff4splat.assembly.assemble import DEPTH_KINDS
from diff4splat.cameras import DEFAULT_TRAJECTORY, TRAJECTORIES, CameraPath
from diff4splat.cameras.trajectories import check_amplitude
from diff4splat.io import load_cameras_json, load_realestate10k
from diff4splat.io.depth_maps import fit_depth_map, read_depth_map
from diff4splat.io.image import preprocess_image, read_image
from diff4splat.io.inputs import check_input_file
from diff4splat.io.output_folders import check_output_dir
from diff4splat.io.scene_folder import scene_meta, write_scene_folder
from diff4splat.io.video import DEFAULT_FPS, check_fps
from diff4splat.pipeline import DEFAULT_RESOLUTION, Diff4SplatPipeline, GenerationResult, check_prompt, check_seed
from diff4splat.render.sequence import render_path
from diff4splat.runtime import ATTENTION_KERNELS, DTYPES, check_offload
from diff4splat.utils.checks import check_positive_int
from diff4splat.utils.costs import TIME_ESTIMATE_PRINTED
from diff4splat.utils.devices import AUTO, resolve_device
from diff4splat.utils.limits import check_limit, check_memory, check_output_size
from models.bundle import DEFAULT_CONFIG
from models.flow_matching import check_guidance

__all__ = ["LoadedPipeline", "Generation", "load_pipeline", "generate", "write", "RUNTIMES", "cameras_from_file",
           "generation_meta", "resolve_pipeline", "check_frame_count", "check_destination", "GENERATE_KIND"]

RUNTIMES = ("torch", "onnxruntime")
"""What runs the networks: PyTorch, or onnxruntime over an ``export-onnx`` folder."""
GENERATE_KIND = "generate"
"""Marker kind of a ``generate`` output folder (:mod:`diff4splat.io.output_folders`)."""


@dataclass(frozen=True)
class LoadedPipeline:
    """A pipeline and what meta.json records of where it came from: its :attr:`source`, ``load_seconds`` (wall time,
    seconds), a torch runtime's ``dtype`` name and ``offload`` mode (None for onnxruntime), extra package ``versions``
    and the folders the networks were read from (``files``: no output folder may be or hold one)."""

    pipeline: Diff4SplatPipeline
    source: str
    load_seconds: float = 0.0
    dtype: str | None = "float32"
    offload: str | None = "none"
    versions: dict = field(default_factory=dict)
    files: tuple[Path, ...] = ()


def load_pipeline(checkpoint: str | os.PathLike | None = None, config: str | None = None, *, runtime: str | None = None,
                  onnx: str | os.PathLike | None = None, device: str | torch.device = AUTO, dtype: str = "float32",
                  offload: str = "none", attention: str = "auto", compile: bool = False) -> LoadedPipeline:
    """Load the networks ``generate`` runs: ``checkpoint`` and ``config`` as
    :meth:`Diff4SplatPipeline.from_pretrained`; ``runtime`` one of :data:`RUNTIMES` (None: "onnxruntime" when ``onnx``,
    the export folder, is given, where the torch options do not apply); ``device`` "auto", "cpu", "cuda:1", …; ``dtype``
    a :data:`diff4splat.runtime.DTYPES` name; ``offload``, ``attention``, ``compile`` as :class:`TorchRuntime`.

    Raises:
        ValueError: an unknown runtime or dtype, options that do not apply to the runtime, an unavailable device,
            a malformed model folder or export.
        FileNotFoundError: ``checkpoint`` or ``onnx`` is not a folder; an unknown config name.
    """
    if runtime is None:
        runtime = "torch" if onnx is None else "onnxruntime"
    if runtime not in RUNTIMES:
        raise ValueError(f"--runtime must be one of {RUNTIMES}, got {runtime!r}")
    if runtime == "onnxruntime":
        if onnx is None:
            raise ValueError("--runtime onnxruntime needs --onnx DIR (a folder written by `diff4splat export-onnx`)")
        if (checkpoint is not None or config is not None or device != AUTO or dtype != "float32" or offload != "none"
                or attention != "auto" or compile):
            raise ValueError("--checkpoint, --config, --device, --dtype, --offload, --attention and --compile do not "
                             "apply to --runtime onnxruntime (the export's manifest fixes the model; onnxruntime "
                             "picks CUDA or CPU)")
        if not Path(onnx).is_dir():
            raise FileNotFoundError(f"--onnx: {onnx} is not a folder")
        import onnxruntime  # lazy: optional, and it would slow every command's start; only --runtime onnxruntime

        t0 = time.perf_counter()
        pipe = Diff4SplatPipeline.from_onnx(onnx)
        return LoadedPipeline(pipe, pipe.source, time.perf_counter() - t0, None, None,
                              {"onnxruntime": onnxruntime.__version__}, (Path(onnx),))
    if onnx is not None:
        raise ValueError("--onnx runs the export with onnxruntime, not --runtime torch")
    if dtype not in DTYPES:
        raise ValueError(f"--dtype must be one of {sorted(DTYPES)}, got {dtype!r}")
    if attention not in ATTENTION_KERNELS:
        raise ValueError(f"--attention must be one of {tuple(ATTENTION_KERNELS)}, got {attention!r}")
    check_offload(offload, compile)
    device = resolve_device(device, "--device")  # before any model is loaded
    if checkpoint is not None and not Path(checkpoint).is_dir():
        raise FileNotFoundError(f"--checkpoint: {checkpoint} is not a folder")
    t0 = time.perf_counter()
    pipe = Diff4SplatPipeline.from_pretrained(checkpoint, config or DEFAULT_CONFIG, device, dtype=DTYPES[dtype],
                                              offload=offload, attention=attention, compile=compile)
    return LoadedPipeline(pipe, pipe.source, time.perf_counter() - t0, dtype, offload,
                          files=() if checkpoint is None else (Path(checkpoint),))


@dataclass
class Generation:
    """What :func:`generate` made: the scene, its rendering along the path, and the meta.json of the request.

    Attributes:
        result: the pipeline's :class:`~diff4splat.pipeline.GenerationResult`.
        colors, depths, alphas: (T, H, W, 3) in [0, 1], (T, H, W) z-depth in metres (0 where nothing is seen) and
            (T, H, W) in [0, 1], the scene rendered along ``result.cameras``.
        meta, seconds: meta.json (the settings used, timings in seconds) and the wall time of :func:`generate`.
        inputs: the files the request read (no output folder may be or hold one).
        depth_fallback: depth written where nothing is seen, metres (the config's scene depth).
        kind: the output folder's marker kind: :data:`GENERATE_KIND` or "reconstruct".
    """

    result: GenerationResult
    colors: Tensor
    depths: Tensor
    alphas: Tensor
    meta: dict
    inputs: list[Path]
    depth_fallback: float
    seconds: float
    kind: str = GENERATE_KIND


def resolve_pipeline(pipeline: LoadedPipeline | Diff4SplatPipeline | Callable[[], LoadedPipeline] | None
                     ) -> LoadedPipeline:
    """The networks a request runs on: a :class:`LoadedPipeline` as given, a bare pipeline wrapped (source
    "pipeline"), a zero-argument loader called now, or None for the shipped model on the ``auto`` device."""
    loaded = pipeline() if callable(pipeline) and not isinstance(pipeline, Diff4SplatPipeline) else pipeline
    if loaded is None:
        return load_pipeline()
    if isinstance(loaded, Diff4SplatPipeline):
        return LoadedPipeline(loaded, "pipeline", dtype=None, offload=None)
    return loaded


def check_destination(out: str | os.PathLike | None, fps: float, *, inputs: Iterable[str | os.PathLike | None],
                      overwrite: bool, kind: str) -> None:
    """Check before any work that ``out`` (when given) may be written as a folder of ``kind``
    (:func:`diff4splat.io.output_folders.check_output_dir`: OutputDirError, FileExistsError) and ``fps`` is a frame
    rate (ValueError naming ``--fps``)."""
    if out is not None:
        check_output_dir(out, inputs=inputs, overwrite=overwrite, kind=kind)
    check_fps(fps, "--fps")


def check_frame_count(pipe: Diff4SplatPipeline, frames: int) -> None:
    """ValueError naming ``--frames`` unless ``frames`` is a length the pipeline's VAE takes (T = 1 + 4k)."""
    try:
        pipe.config.vae.num_latent_frames(frames)
    except ValueError:
        raise ValueError(f"--frames {frames}: the frame count must be {pipe.runtime.latent.frames_rule}") from None


def _check_request(image, cameras, trajectory, amplitude, frames, resolution, steps, seed, prompt, depth,
                   depth_kind, guidance) -> None:
    """The request's own checks, made before any model loads (messages name the command's flags)."""
    if isinstance(image, (str, os.PathLike)):
        check_input_file(image, "image")
    for name, value in (("frames", frames), ("steps", steps), ("resolution", resolution)):
        if value is not None:
            check_limit(name, check_positive_int(f"--{name}", value), f"--{name}")
    if isinstance(depth, (str, os.PathLike)):
        check_input_file(depth, "--depth")
    if depth_kind not in DEPTH_KINDS:
        raise ValueError(f"--depth-kind must be one of {DEPTH_KINDS}, got {depth_kind!r}")
    if depth is None and depth_kind != "metric":
        raise ValueError(f"--depth-kind {depth_kind} describes a --depth file; none was given (the network's depth is "
                         "metric)")
    check_seed(seed, "--seed")
    check_prompt(prompt, "--prompt")
    if guidance is not None:
        check_guidance(guidance, "--guidance")
    if cameras is not None:
        if amplitude is not None:
            raise ValueError("--amplitude scales a --trajectory preset; it does not apply to --cameras "
                             "(the camera file fixes the path)")
        if isinstance(cameras, (str, os.PathLike)):
            check_input_file(cameras, "--cameras")
    else:
        if trajectory not in TRAJECTORIES:
            raise ValueError(f"--trajectory must be one of {TRAJECTORIES}, got {trajectory!r}")
        check_amplitude(trajectory, amplitude, "--amplitude")


def cameras_from_file(path: Path, frames: int | None, photo_shape: tuple[int, int], width: int,
                       height: int) -> CameraPath:
    """``--cameras`` file → camera path at ``width`` × ``height`` (RealEstate10K intrinsics are normalised by the
    photograph's ``photo_shape`` (H, W) after EXIF orientation). ValueError: malformed, or not ``frames`` cameras."""
    if path.suffix.lower() == ".json":
        cams = load_cameras_json(path)
    else:
        cams = load_realestate10k(path, photo_shape[1], photo_shape[0])
    if frames is not None and frames != len(cams):
        raise ValueError(f"--frames {frames} differs from the {len(cams)} cameras in {path}")
    return cams.fitted(width, height)


def generate(image: str | os.PathLike | Tensor, cameras: str | os.PathLike | CameraPath | None = None, *,
             pipeline: LoadedPipeline | Diff4SplatPipeline | Callable[[], LoadedPipeline] | None = None,
             trajectory: str = DEFAULT_TRAJECTORY, amplitude: float | None = None, frames: int | None = None,
             resolution: int | None = None, prompt: str = "", steps: int | None = None, sampler: str | None = None,
             guidance: float | None = None, seed: int = 0, depth: str | os.PathLike | Tensor | None = None,
             depth_kind: str = "metric", progress: bool = False, notes: Callable[[str], None] | None = None,
             out: str | os.PathLike | None = None, overwrite: bool = False,
             inputs: Iterable[str | os.PathLike | None] = (), fps: float = DEFAULT_FPS,
             frame_plys: bool = True) -> Generation:
    """A 4D scene from one photograph, rendered along its camera path (``diff4splat generate``); write the returned
    :class:`Generation` with :func:`write`.

    Args:
        image: a photo file (EXIF orientation applied, centre-cropped to the model's aspect ratio, resized) or an
            (H, W, 3) tensor in [0, 1] at the output resolution and the model's aspect ratio.
        cameras: a camera file (``cameras.json`` or RealEstate10K ``.txt``), a :class:`CameraPath` at the output
            resolution, or None for the ``trajectory`` preset (:func:`diff4splat.cameras.make_trajectory`).
        pipeline: a :class:`LoadedPipeline`, a bare pipeline, a zero-argument loader called after the request's
            checks, or None for the shipped model on the ``auto`` device.
        frames: T = 1 + 4k frames (default: the config's, or a camera file's count, which it must match).
        resolution: output height, pixels (default :data:`DEFAULT_RESOLUTION` or the model's height if larger);
            with a tensor image, None or its height.
        prompt, steps, sampler, guidance, seed: as :meth:`Diff4SplatPipeline.__call__`.
        depth: the photograph's depth map of ``depth_kind`` (:data:`DEPTH_KINDS`): a file (EXR channel Z, .npy,
            16-bit PNG/TIFF in millimetres) or an (H, W) tensor at the output resolution.
        notes: called with one-line notes for the user (e.g. a depth map resized).
        out, overwrite: the folder :func:`write` will fill, if known, checked first (:func:`check_destination`) and
            against its disk's free space; ``overwrite``: it may replace a folder that is not a ``generate`` output.
        inputs: further paths the request reads (e.g. ``--checkpoint``): no output folder may be or hold one.
        fps, frame_plys: meta.json's frame rate (1 … 1000) and whether :func:`write` writes frames/NNNN.ply.

    Raises:
        ValueError: an argument out of range, a limit exceeded (:class:`diff4splat.utils.limits.LimitError`), an
            ``out`` that may not be written (``OutputDirError``), a malformed input file (named); everything
            :class:`~diff4splat.pipeline.Diff4SplatPipeline` raises.
        FileNotFoundError, FileExistsError: a missing input file; as ``check_output_dir``.
    """
    t_start = time.perf_counter()
    files = {"image": image, "cameras_file": cameras, "depth_file": depth}  # as given, for meta.json
    read = [Path(p) for p in (*files.values(), *inputs) if isinstance(p, (str, os.PathLike))]
    check_destination(out, fps, inputs=read, overwrite=overwrite, kind=GENERATE_KIND)
    _check_request(image, cameras, trajectory, amplitude, frames, resolution, steps, seed, prompt, depth, depth_kind,
                   guidance)
    if isinstance(image, Tensor) and resolution is not None and resolution != image.shape[0]:
        raise ValueError(f"resolution={resolution} but the image tensor is {image.shape[0]} pixels high: a tensor "
                         "is used at its own resolution (resize it, or pass a photo file)")
    loaded = resolve_pipeline(pipeline)
    pipe, cfg = loaded.pipeline, loaded.pipeline.config
    if frames is not None:  # T = 1 + 4k, before any decoding
        check_frame_count(pipe, frames)
    if isinstance(image, Tensor):
        height, width = int(image.shape[0]), int(image.shape[1])
        pipe.output_size(height)  # the resolution limit
        photo_shape = (height, width)
    else:
        res = resolution if resolution is not None else max(DEFAULT_RESOLUTION, cfg.height)
        width, height = pipe.output_size(res)
    raw_depth = read_depth_map(depth, depth_kind) if isinstance(depth, (str, os.PathLike)) else None  # before the photo
    if not isinstance(image, Tensor):
        photo = read_image(image)
        photo_shape = photo.shape[:2]
        image = preprocess_image(photo, (height, width))
    if raw_depth is not None:
        depth, note = fit_depth_map(raw_depth, photo_shape, (height, width))
        if note is not None and notes is not None:
            notes(f"--depth: {note}")
    if cameras is None:
        path = pipe.default_cameras(trajectory, frames, amplitude, resolution=height)
    elif isinstance(cameras, CameraPath):
        path = cameras
    else:
        path = cameras_from_file(Path(cameras), frames, photo_shape, width, height)
        try:  # the frame count the VAE needs, named by the file (else "video: T=7 frames" from the sampler)
            cfg.vae.num_latent_frames(len(path))
        except ValueError as e:
            raise ValueError(f"--cameras {cameras}: {len(path)} cameras, one per frame: {e}") from None
    check_output_size(len(path), path.width, path.height,  # before any network runs
                      pipe.scene_slots(path.width, path.height, len(path)), knobs="--frames or --resolution", out=out,
                      frame_plys=frame_plys)
    check_memory(pipe.memory_estimate(path.width, path.height, len(path)),
                 f"{len(path)} frames at {path.width}×{path.height}", "--frames or --resolution")
    seconds = pipe.time_estimate(path.width, path.height, len(path))
    if seconds > TIME_ESTIMATE_PRINTED and notes is not None and pipe.device.type == "cpu":
        notes(f"{len(path)} frames at {path.width}×{path.height}: estimated {seconds:.0f} s on this CPU (lower "
              "--resolution or --frames for less)")
    result = pipe(image, path, prompt, steps=steps, sampler=sampler, guidance=guidance, seed=seed, progress=progress,
                  depth=depth if isinstance(depth, Tensor) else None, depth_kind=depth_kind)
    t0 = time.perf_counter()
    colors, depths, alphas = render_path(result.scene, result.cameras, eps2d=result.eps2d,
                                         background=result.background, progress=progress)
    timings = {"load_model": loaded.load_seconds, **result.timings, "render": time.perf_counter() - t0}
    meta = generation_meta(loaded, result, prompt, None if cameras is not None else trajectory, files, depth_kind,
                           seed, timings, fps)
    meta["frame_plys"] = bool(frame_plys) and result.scene.changes_with_time
    return Generation(result, colors, depths, alphas, meta, read + list(loaded.files), cfg.scene_depth,
                      time.perf_counter() - t_start)


def generation_meta(loaded: LoadedPipeline, result: GenerationResult, prompt: str, trajectory: str | None, files: dict,
                    depth_kind: str, seed: int, timings: dict, fps: float) -> dict:
    """meta.json of ``generate`` (``reconstruct`` starts from it), from the settings the pipeline actually used."""
    pipe, cfg = loaded.pipeline, loaded.pipeline.config
    path = lambda v: str(v) if isinstance(v, (str, os.PathLike)) else None  # noqa: E731
    return {
        "model": loaded.source,
        "config": cfg.name,
        "runtime": pipe.runtime.name,
        "device": str(pipe.device),
        "dtype": loaded.dtype,
        "offload": loaded.offload,
        "attention": pipe.runtime.attention,
        "compile": pipe.runtime.compiled,
        "image": path(files["image"]),
        "prompt": prompt,
        "trajectory": trajectory,
        "cameras_file": path(files["cameras_file"]),
        "model_width": cfg.width,
        "model_height": cfg.height,
        "photo_psnr_db": result.photo_psnr_db,
        "depth_file": path(files["depth_file"]),
        "depth_kind": depth_kind if files["depth_file"] is not None else None,
        "seed": seed,
        "steps": result.steps,
        "sampler": result.sampler,
        "guidance": result.guidance,
        "shift": result.shift,
        "prune": result.prune_stats,
        "timings_s": timings,
        # the device's running peak at the end of each stage (GenerationResult.high_water); CUDA only
        "peak_memory_gb": {k: round(v / 1e9, 3) for k, v in result.high_water.items()} or None,
        **scene_meta(result.scene, result.cameras, fps=fps, background=result.background, eps2d=result.eps2d,
                     versions=loaded.versions),
    }


def write(generation: Generation, out_dir: str | os.PathLike, *, fps: float | None = None,
          overwrite: bool = False) -> dict:
    """Write ``generate``'s output folder atomically (:func:`diff4splat.io.scene_folder.write_scene_folder`;
    docs/DESIGN.md, "Output folder of generate"); ``fps`` None: the one :func:`generate` was given. Returns the meta
    dict written to meta.json, with the write and total timings. ValueError: a bad ``fps``; an ``out_dir`` that may not
    be written (``OutputDirError``). OSError: writing failed (``<path>: <reason>``); nothing half-written is left."""
    if fps is None:
        fps = generation.meta["fps"]
    else:
        check_fps(fps, "--fps")
    meta = dict(generation.meta, fps=fps, timings_s=dict(generation.meta["timings_s"]))
    t0 = time.perf_counter()
    result = generation.result
    write_scene_folder(out_dir, result.scene, result.cameras, generation.colors, generation.depths,
                       generation.alphas, meta, fps=fps, depth_fallback=generation.depth_fallback,
                       inputs=generation.inputs, overwrite=overwrite, frame_plys=meta["frame_plys"],
                       kind=generation.kind)
    meta["timings_s"]["write"] = time.perf_counter() - t0
    meta["timings_s"]["total"] = generation.seconds + meta["timings_s"]["write"]
    return meta
