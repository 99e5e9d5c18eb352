"""``generate`` as a library function: a photograph (+ a camera path, a prompt) → a 4D scene rendered along the path
(:func:`generate`), and its output folder (:func:`write`). The ``diff4splat generate`` command parses its arguments
and calls these two; benchmarks and scripts call them directly::

    from diff4splat.generate import generate, load_pipeline, write

    gen = generate("photo.jpg", prompt="the cat turns its head", frames=17, seed=0)   # shipped model, auto device
    write(gen, "out")                                                                # scene.ply, video.mp4, …

Every argument is checked once, by the function it enters, before anything heavy runs: :func:`generate` checks the
output folder it is told of (``out``), the frame rate and the files and numbers of the request before the model
loads (``pipeline`` may be a loader that is only called then), the output size and the peak memory
(:mod:`diff4splat.utils.limits`) before the networks run; :func:`write` checks a frame rate given to it, and its folder
when it writes (:func:`diff4splat.io.output_folders.output_dir`: it may have changed since).
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
    """A pipeline and what meta.json records of where it came from.

    Attributes:
        pipeline: the :class:`~diff4splat.pipeline.Diff4SplatPipeline`.
        source: the weights' folder, ``random:<config>:seed=<s>[:cuda]`` (``:cuda``: initialised on a GPU), or
            ``onnx:<folder> (<its source>)``.
        load_seconds: wall time of loading, seconds.
        dtype: weight dtype name of a torch runtime ("float32", "bfloat16", "float16"), None for onnxruntime.
        offload: offload mode of a torch runtime, None for onnxruntime.
        versions: extra package versions for meta.json (e.g. onnxruntime's).
        files: the folders the networks were read from (an output folder may not be one of them or hold one).
    """

    pipeline: Diff4SplatPipeline
    source: str
    load_seconds: float = 0.0
    dtype: str | None = "float32"
    offload: str | None = "none"
    versions: dict = field(default_factory=dict)
    files: tuple[Path, ...] = ()


def load_pipeline(checkpoint: str | os.PathLike | None = None, config: str | None = None, *,
                  runtime: str | None = None,
                  onnx: str | os.PathLike | None = None, device: str | torch.device = AUTO, dtype: str = "float32",
                  offload: str = "none", attention: str = "auto", compile: bool = False) -> LoadedPipeline:
    """Load the networks ``generate`` runs.

    Args:
        checkpoint: a model folder (None: the shipped weights of ``config``; a random model with a warning when
            none ship).
        config: shipped config name or YAML path (None: :data:`models.bundle.DEFAULT_CONFIG`).
        runtime: one of :data:`RUNTIMES`; "onnxruntime" runs the export in ``onnx`` (checkpoint, config, device,
            dtype, offload, attention and compile then do not apply: the export's manifest fixes the model).
            None: "onnxruntime" when ``onnx`` is given, else "torch".
        device: "auto" (CUDA when present, else the CPU), "cpu", "cuda", "cuda:1", …
        dtype: weight dtype name (:data:`diff4splat.runtime.DTYPES`).
        offload: "none", "model" or "model-prefetch" (:data:`diff4splat.runtime.OFFLOAD_MODES`).
        attention: the attention kernel tried first (:data:`diff4splat.runtime.ATTENTION_KERNELS`).
        compile: ``torch.compile`` the transformer's blocks (:class:`diff4splat.runtime.TorchRuntime`).

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
        import onnxruntime  # lazy: ~0.1 s at every command's start; only --runtime onnxruntime needs it

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
        result: the pipeline's :class:`~diff4splat.pipeline.GenerationResult` (scene, cameras, latents, timings).
        colors: (T, H, W, 3) in [0, 1], the scene rendered along ``result.cameras``.
        depths: (T, H, W) z-depth, metres (0 where nothing is seen).
        alphas: (T, H, W) in [0, 1].
        meta: meta.json (settings the run actually used, timings in seconds).
        inputs: the files the request read (an output folder may not be one of them or hold one).
        depth_fallback: depth written where nothing is seen, metres (the config's scene depth).
        seconds: wall time of :func:`generate`, seconds.
        kind: the output folder's marker kind: :data:`GENERATE_KIND`, or "reconstruct"
            (:mod:`diff4splat.reconstruct`).
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
    """What a request writes, checked before any work: ``out`` (when given) may be written as the folder of ``kind``
    (:func:`diff4splat.io.output_folders.check_output_dir`: its parent exists, it is not and holds none of
    ``inputs``, an existing one is replaced only as ``overwrite`` allows) and ``fps`` is a frame rate
    (:func:`diff4splat.io.video.check_fps`).

    Raises:
        OutputDirError: (a ValueError) ``out`` may not be written; FileExistsError as ``check_output_dir``.
        ValueError: a bad ``fps``, naming ``--fps``.
    """
    if out is not None:
        check_output_dir(out, inputs=inputs, overwrite=overwrite, kind=kind)
    check_fps(fps, "--fps")


def check_frame_count(pipe: Diff4SplatPipeline, frames: int) -> None:
    """Raise ValueError naming ``--frames`` unless ``frames`` is a length the pipeline's VAE takes (T = 1 + 4k)."""
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
    """``--cameras`` file → camera path at ``width`` × ``height``. RealEstate10K intrinsics are normalised by the
    photograph as displayed (``photo_shape`` (H, W) after EXIF orientation), the image that is centre-cropped.

    Raises:
        ValueError: a malformed file, or ``frames`` given and not the file's camera count.
    """
    if path.suffix.lower() == ".json":
        cams = load_cameras_json(path)
    else:
        cams = load_realestate10k(path, photo_shape[1], photo_shape[0])
    if frames is not None and frames != len(cams):
        raise ValueError(f"--frames {frames} differs from the {len(cams)} cameras in {path}")
    return cams.fitted(width, height)


def generate(
    image: str | os.PathLike | Tensor,  # a photo file, or (H, W, 3) in [0, 1] at the output resolution
    cameras: str | os.PathLike | CameraPath | None = None,
    *,
    pipeline: LoadedPipeline | Diff4SplatPipeline | Callable[[], LoadedPipeline] | None = None,
    trajectory: str = DEFAULT_TRAJECTORY,
    amplitude: float | None = None,
    frames: int | None = None,
    resolution: int | None = None,
    prompt: str = "",
    steps: int | None = None,
    sampler: str | None = None,
    guidance: float | None = None,
    seed: int = 0,
    depth: str | os.PathLike | Tensor | None = None,
    depth_kind: str = "metric",
    progress: bool = False,
    notes: Callable[[str], None] | None = None,
    out: str | os.PathLike | None = None,
    overwrite: bool = False,
    inputs: Iterable[str | os.PathLike | None] = (),
    fps: float = DEFAULT_FPS,
    frame_plys: bool = True,
) -> Generation:
    """A 4D scene from one photograph, rendered along its camera path (the ``diff4splat generate`` command).

    Args:
        image: the photograph: a file (any format OpenCV reads; EXIF orientation applied, centre-cropped to the
            model's aspect ratio and resized to the output resolution) or an (H, W, 3) tensor in [0, 1] already at
            the output resolution and the model's aspect ratio.
        cameras: a camera file (``cameras.json``, or RealEstate10K ``.txt``), a :class:`CameraPath` at the output
            resolution, or None for the ``trajectory`` preset.
        pipeline: the networks: a :class:`LoadedPipeline` (:func:`load_pipeline`), a bare pipeline, a zero-argument
            loader called after the request's checks, or None for the shipped model on the ``auto`` device.
        trajectory, amplitude: the camera path preset and its size (:func:`diff4splat.cameras.make_trajectory`).
        frames: T = 1 + 4k frames (default: the config's); with a camera file, its count must match.
        resolution: output height, pixels (default: 256, or the model's height if larger); with a tensor image,
            None or the tensor's height.
        prompt: text describing the motion; "" runs no text encoder.
        steps, sampler, seed: the flow-matching sampler's (defaults: the config's; seed 0).
        guidance: classifier-free guidance scale (default: the config's; :meth:`Diff4SplatPipeline.__call__`).
        depth: a depth map of the photograph for the photo layer: a file (EXR channel Z, .npy, 16-bit PNG/TIFF in
            millimetres) or an (H, W) tensor at the output resolution; ``depth_kind``: "metric", "relative" or
            "inverse" (:data:`diff4splat.assembly.assemble.DEPTH_KINDS`).
        progress: tqdm progress bars.
        notes: called with one-line notes for the user (e.g. a depth map resized); default: ignored.
        out: the folder :func:`write` will fill, if known: checked first, before the request's files
            (:func:`check_destination`: its parent must exist, it may not be or hold an input, an existing folder
            is replaced only if it is empty or an earlier ``generate`` output, or with ``overwrite``), and the
            output's size estimate is checked against the free space of its disk
            (:func:`diff4splat.utils.limits.check_output_size`; None: against the fixed 4 GiB).
        overwrite: ``out`` may also replace a folder that is not an earlier ``generate`` output (pass the same
            to :func:`write`).
        inputs: further files and folders the request reads that are not arguments here, such as the folders a
            ``pipeline`` loader will read (``--checkpoint``, ``--onnx``): ``out`` may not be or hold one, nor may
            :func:`write`'s folder (:attr:`Generation.inputs`).
        fps: frame rate of video.mp4 and the viewer's playback, 1 … 1000 (meta.json ``fps``; :func:`write` uses
            it unless given another).
        frame_plys: whether :func:`write` writes frames/NNNN.ply, the scene at each frame's time (meta.json
            ``frame_plys``; False: scene.ply and deformation.npz hold the same, in frames × 40 bytes per Gaussian
            instead of frames × 108).

    Returns:
        :class:`Generation`; write it with :func:`write`.

    Raises:
        ValueError: any argument out of range or a limit exceeded (:class:`diff4splat.utils.limits.LimitError`, before
            the networks run), an ``out`` that may not be written
            (:class:`diff4splat.io.output_folders.OutputDirError`), a malformed photo, camera or depth file (the
            message names it), a camera path that sees none of the scene; everything
            :class:`~diff4splat.pipeline.Diff4SplatPipeline` raises.
        FileNotFoundError: a missing input file.
        FileExistsError: as :func:`diff4splat.io.output_folders.check_output_dir`.
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
    meta = generation_meta(loaded, result, prompt, None if cameras is not None else trajectory, files, depth_kind, seed,
                 timings, fps)
    meta["frame_plys"] = bool(frame_plys) and result.scene.changes_with_time
    return Generation(result, colors, depths, alphas, meta, read + list(loaded.files), cfg.scene_depth,
                      time.perf_counter() - t_start)


def generation_meta(loaded: LoadedPipeline, result: GenerationResult, prompt: str, trajectory: str | None, files: dict,
          depth_kind: str, seed: int, timings: dict, fps: float) -> dict:
    """meta.json of ``generate`` (``reconstruct`` starts from it): every setting comes from what the pipeline
    actually used; ``fps`` the frame rate of the folder's video and viewer."""
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
    """Write ``generate``'s output folder (README, "Output folders";
    :func:`diff4splat.io.scene_folder.write_scene_folder`: atomic, checked as it is written, missing parents
    created, an existing folder replaced only if it is an earlier output or with ``overwrite``).

    Args:
        generation: what :func:`generate` returned.
        out_dir: the folder; never one of the request's input files or a folder holding one.
        fps: frame rate of video.mp4 (and the viewer's playback), 1 … 1000; None: the one :func:`generate` was
            given (meta.json ``fps``).

    Returns:
        The meta dict written to meta.json (with the write and total timings).

    Raises:
        ValueError: a bad ``fps``; an ``out_dir`` that may not be written
            (:class:`diff4splat.io.output_folders.OutputDirError`).
        OSError: writing failed (``<path>: <reason>``); nothing half-written is left.
    """
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
