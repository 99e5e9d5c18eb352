"""The request layer of ``generate`` and ``reconstruct``: what both share between the command line and the pipeline.

Loading the networks (:func:`load_pipeline`), the checks of the flags both share (:func:`check_request`), camera files
(:func:`cameras_from_file`), the scene rendered along its path with the request's meta.json (:func:`render_output`),
and writing the output folder (:func:`write`). Each user input is checked once, where it enters (docs/DESIGN.md,
"Inputs"): a file or flag here or in the command's library function, a tensor in the pipeline's ``check_inputs``.
"""
from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor

from diff4splat.cameras import CameraPath
from diff4splat.io import load_cameras_json, load_realestate10k
from diff4splat.io.inputs import check_input_file
from diff4splat.io.output_folders import check_output_dir
from diff4splat.io.scene_folder import scene_meta, write_scene_folder
from diff4splat.io.video import check_fps
from diff4splat.pipeline import DEFAULT_RESOLUTION, Diff4SplatPipeline, SceneResult
from diff4splat.render.sequence import render_path
from diff4splat.runtime import DTYPES, check_attention, check_offload
from diff4splat.utils.checks import check_positive_int
from diff4splat.utils.devices import AUTO, resolve_device
from diff4splat.utils.limits import check_limit, check_memory, check_output_size
from models.bundle import DEFAULT_CONFIG

__all__ = ["RUNTIMES", "LoadedPipeline", "SceneOutput", "load_pipeline", "resolve_pipeline", "check_request",
           "output_size", "check_budget", "cameras_from_file", "file_argument", "render_output",
           "write"]

RUNTIMES = ("torch", "onnxruntime")
"""What runs the networks: PyTorch, or onnxruntime over an ``export-onnx`` folder."""


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
    """Load the networks a request runs on: ``checkpoint`` and ``config`` as
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
    check_attention(attention, "--attention")
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
class SceneOutput:
    """A request's scene rendered along its path, and the meta.json of the request (:func:`render_output`).

    Attributes:
        result: the pipeline's :class:`~diff4splat.pipeline.GenerationResult` or
            :class:`~diff4splat.pipeline.ReconstructionResult`.
        colors, depths, alphas: (T, H, W, 3) in [0, 1], (T, H, W) z-depth in metres (0 where nothing is seen) and
            (T, H, W) in [0, 1], the scene rendered along ``result.cameras``.
        meta, seconds: meta.json (the settings used, timings in seconds) and the wall time of the request.
        inputs: the files the request read (no output folder may be or hold one).
        depth_fallback: depth written where nothing is seen, metres (the config's scene depth).
        kind: the output folder's marker kind ("generate", "reconstruct").
    """

    result: SceneResult
    colors: Tensor
    depths: Tensor
    alphas: Tensor
    meta: dict
    inputs: list[Path]
    depth_fallback: float
    seconds: float
    kind: str


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


def check_request(out: str | os.PathLike | None, fps: float, frames: object, resolution: object, cameras: object, *,
                  inputs: Iterable[str | os.PathLike | None], overwrite: bool, kind: str) -> None:
    """The flags ``generate`` and ``reconstruct`` share, checked before any model loads, each error naming its flag:
    ``out`` (when given) may be written as a folder of ``kind`` (:func:`diff4splat.io.output_folders.check_output_dir`:
    OutputDirError, FileExistsError), ``--fps`` a frame rate, ``--frames`` and ``--resolution`` positive ints within
    their limits (None: the defaults; ValueError, LimitError), ``--cameras`` an existing file when it is a path
    (FileNotFoundError)."""
    if out is not None:
        check_output_dir(out, inputs=inputs, overwrite=overwrite, kind=kind)
    check_fps(fps, "--fps")
    for name, value in (("frames", frames), ("resolution", resolution)):
        if value is not None:
            check_limit(name, check_positive_int(f"--{name}", value), f"--{name}")
    if isinstance(cameras, (str, os.PathLike)):
        check_input_file(cameras, "--cameras")


def output_size(pipe: Diff4SplatPipeline, resolution: int | None) -> tuple[int, int]:
    """(width, height) of the output at ``resolution`` pixels of height (None: :data:`DEFAULT_RESOLUTION` or the
    model's height if larger); ValueError as :meth:`Diff4SplatPipeline.output_size`."""
    return pipe.output_size(resolution if resolution is not None else max(DEFAULT_RESOLUTION, pipe.config.height))


def check_budget(path: CameraPath, slots: int, memory: int, *, knobs: str, out: str | os.PathLike | None,
                 frame_plys: bool) -> None:
    """Before any network runs: the output folder of ``path`` with ``slots`` Gaussian slots fits its disk and the
    output-size limit (:func:`diff4splat.utils.limits.check_output_size`), and ``memory`` bytes, the command's
    estimate (:mod:`diff4splat.utils.costs`), fit the memory limit; a LimitError names the ``knobs`` that lower them."""
    check_output_size(len(path), path.width, path.height, slots, knobs=knobs, out=out, frame_plys=frame_plys)
    check_memory(memory, f"{len(path)} frames at {path.width}×{path.height}", knobs)


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


def file_argument(value: object) -> str | None:
    """A file argument as meta.json records it: its path, or None for a tensor, a camera path or nothing."""
    return str(value) if isinstance(value, (str, os.PathLike)) else None


def render_output(loaded: LoadedPipeline, result: SceneResult, request: dict, *, kind: str, fps: float,
                  frame_plys: bool, inputs: list[Path], started: float, progress: bool = False) -> SceneOutput:
    """``result``'s scene rendered along its cameras, and meta.json: where the networks came from and ran, the
    command's own ``request`` keys, the model size, the photo layer's PSNR, pruning, timings (seconds, with "load_model"
    and "render"), the CUDA peaks (GB) and :func:`diff4splat.io.scene_folder.scene_meta`. ``started`` is the request's
    ``time.perf_counter()`` at its start; ``inputs`` the files it read."""
    pipe, cfg = loaded.pipeline, loaded.pipeline.config
    t0 = time.perf_counter()
    colors, depths, alphas = render_path(result.scene, result.cameras, eps2d=result.eps2d,
                                         background=result.background, progress=progress)
    timings = {"load_model": loaded.load_seconds, **result.timings, "render": time.perf_counter() - t0}
    meta = {
        "model": loaded.source,
        "config": cfg.name,
        "runtime": pipe.runtime.name,
        "device": str(pipe.device),
        "dtype": loaded.dtype,
        "offload": loaded.offload,
        "attention": pipe.runtime.attention,
        "compile": pipe.runtime.compiled,
        **request,
        "model_width": cfg.width,
        "model_height": cfg.height,
        "photo_psnr_db": result.photo_psnr_db,
        "prune": result.prune_stats,
        "timings_s": timings,
        # the device's running peak at the end of each stage (SceneResult.high_water); CUDA only
        "peak_memory_gb": {k: round(v / 1e9, 3) for k, v in result.high_water.items()} or None,
        **scene_meta(result.scene, result.cameras, fps=fps, background=result.background, eps2d=result.eps2d,
                     versions=loaded.versions),
        "frame_plys": bool(frame_plys) and result.scene.changes_with_time,
    }
    return SceneOutput(result, colors, depths, alphas, meta, inputs + list(loaded.files), cfg.scene_depth,
                       time.perf_counter() - started, kind)


def write(output: SceneOutput, out_dir: str | os.PathLike, *, fps: float | None = None,
          overwrite: bool = False) -> dict:
    """Write a request's output folder atomically (:func:`diff4splat.io.scene_folder.write_scene_folder`;
    docs/DESIGN.md, "Output folder of generate"); ``fps`` None: meta.json's. Returns the meta
    dict written to meta.json, with the write and total timings. ValueError: a bad ``fps``; an ``out_dir`` that may not
    be written (``OutputDirError``). OSError: writing failed (``<path>: <reason>``); nothing half-written is left."""
    if fps is None:
        fps = output.meta["fps"]
    else:
        check_fps(fps, "--fps")
    meta = dict(output.meta, fps=fps, timings_s=dict(output.meta["timings_s"]))
    t0 = time.perf_counter()
    result = output.result
    write_scene_folder(out_dir, result.scene, result.cameras, output.colors, output.depths,
                       output.alphas, meta, fps=fps, depth_fallback=output.depth_fallback,
                       inputs=output.inputs, overwrite=overwrite, frame_plys=meta["frame_plys"],
                       kind=output.kind)
    meta["timings_s"]["write"] = time.perf_counter() - t0
    meta["timings_s"]["total"] = output.seconds + meta["timings_s"]["write"]
    return meta
