"""``diff4splat`` command line: ``diff4splat generate IMAGE ... --out DIR``, ``diff4splat export-onnx --out DIR`` and
``diff4splat render DIR (--cameras FILE | --trajectory NAME) --out OUT`` (:mod:`diff4splat.rerender`) and
``diff4splat view DIR [--port P]`` (:mod:`diff4splat.view`).

Bad input gets one line on stderr (``diff4splat: error: …``) and exit code 2, and no output folder.
"""
from __future__ import annotations

import argparse
import platform
import sys
import time
import warnings
from importlib.metadata import entry_points
from pathlib import Path

from .checks import check_positive_int
from .devices import AUTO, DEVICE_HELP, resolve_device
from .errors import run_cli

__all__ = ["main", "build_parser"]

OUT_HELP = ("output folder, written atomically; an existing one is replaced only if it is empty or an "
            "earlier output of this command (README, 'Output folders')")
OVERWRITE_HELP = ("also replace an existing --out that is not an earlier output of this command "
                  "(never a folder holding the inputs, the current or home directory)")
PLUGIN_GROUP = "diff4splat.commands"
"""Entry-point group of extra subcommands: ``register(subparsers)`` adds a parser whose defaults hold
``func(args) -> int``. ``training`` registers ``evaluate`` this way, so this package never imports it.
Building the parser only lists the names (nothing is loaded); an entry point is loaded when its
command is chosen (:func:`main`)."""


class CLIError(Exception):
    """A user error reported as one line with exit code 2."""


def _out_path(value: str) -> Path:
    """``--out`` as given: ``Path("")`` would silently mean the current directory."""
    if not value.strip():
        raise argparse.ArgumentTypeError(f"empty folder name {value!r}; give a new folder name")
    return Path(value)


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one line, exit 2 (argparse prints usage + message)
        raise CLIError(message)


def build_parser(load_command: str | None = None) -> argparse.ArgumentParser:
    """The ``diff4splat`` argument parser.

    Commands of the :data:`PLUGIN_GROUP` entry points get a placeholder subparser that accepts any
    arguments, so listing them imports nothing (no ``training``); ``load_command`` names the one whose
    entry point is loaded to build its real subparser instead.

    Raises:
        ValueError: ``load_command`` is not a registered entry point.
    """
    from models.bundle import DEFAULT_CONFIG

    from .assemble import DEPTH_KINDS
    from .cameras import DEFAULT_AMPLITUDES, DEFAULT_TRAJECTORY, TRAJECTORIES
    from .cameras.trajectories import amplitude_help
    from .pipeline import DEFAULT_RESOLUTION

    config_help = f"shipped model config (tiny, small, paper) or a YAML path (default: {DEFAULT_CONFIG})"

    parser = _Parser(prog="diff4splat", description="One photograph + a camera path + a prompt → a 4D Gaussian scene.")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    g = sub.add_parser("generate", help="generate a 4D scene from an image",
                       description="Generate a 4D Gaussian scene from one image and write the output folder.")
    g.add_argument("image", help="input photograph (any format OpenCV reads: RGB, RGBA, grey, 8/16-bit)")
    cam = g.add_mutually_exclusive_group()
    cam.add_argument("--trajectory", choices=TRAJECTORIES, default=DEFAULT_TRAJECTORY,
                     help=f"camera path preset (default: {DEFAULT_TRAJECTORY}; arc sweeps "
                          f"{DEFAULT_AMPLITUDES['arc']:g} rad to the right around the scene, orbit a full 360°)")
    cam.add_argument("--cameras", type=Path, default=None,
                     help="camera path file: cameras.json (our format) or RealEstate10K .txt")
    g.add_argument("--amplitude", type=float, default=None,
                   help=f"size of the --trajectory preset's motion (its default if omitted). {amplitude_help()}; "
                        "a scene depth is the model config's scene_depth (2 m for the shipped ones)")
    g.add_argument("--frames", type=int, default=None, help="number of frames T = 1 + 4k (default: config)")
    g.add_argument("--resolution", type=int, default=None,
                   help=f"output height in pixels (the photo layer keeps the photograph at this resolution; default: "
                        f"{DEFAULT_RESOLUTION}, or the model's height if larger)")
    g.add_argument("--depth", type=Path, default=None, metavar="FILE",
                   help="a depth map of the photograph for its Gaussians instead of the network's: EXR (channel Z), "
                        ".npy, or a 16-bit PNG/TIFF (millimetres); NaN/inf/0 pixels are filled from the network")
    g.add_argument("--depth-kind", choices=DEPTH_KINDS, default="metric",
                   help="metric (z-depth in metres, used as given), relative (depth up to scale and shift) or inverse "
                        "(disparity up to scale and shift), both fitted to the network's depth (default: metric)")
    g.add_argument("--prompt", default="", help="text describing the motion; empty = no text encoder")
    g.add_argument("--steps", type=int, default=None, help="sampler steps (default: config)")
    g.add_argument("--sampler", choices=("euler", "heun"), default=None, help="ODE sampler (default: config)")
    g.add_argument("--seed", type=int, default=0, help="noise seed (default: 0)")
    g.add_argument("--checkpoint", type=Path, default=None,
                   help="model folder (default: the shipped weights of --config)")
    g.add_argument("--config", default=None, help=config_help)
    g.add_argument("--fps", type=int, default=8, help="video frame rate (default: 8)")
    g.add_argument("--device", default=AUTO, help=DEVICE_HELP)
    g.add_argument("--dtype", choices=("float32", "bfloat16", "float16"), default="float32",
                   help="weight dtype of the networks (bfloat16 halves a GPU's memory use; default: float32); "
                        "sampling, Gaussians and rendering stay float32")
    g.add_argument("--offload", choices=("none", "model"), default="none",
                   help="model: keep the networks in CPU memory and move one at a time to --device while it runs "
                        "(the paper-size model within 25 GB of GPU memory); default: none")
    g.add_argument("--runtime", choices=("torch", "onnxruntime"), default="torch",
                   help="run the networks with PyTorch or with onnxruntime on an --onnx export (default: torch)")
    g.add_argument("--onnx", type=Path, default=None, help="folder written by `diff4splat export-onnx` "
                   "(with --runtime onnxruntime)")
    g.add_argument("--quiet", action="store_true", help="no progress bars")
    g.add_argument("--out", type=_out_path, required=True, help=OUT_HELP)
    g.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)

    e = sub.add_parser("export-onnx", help="export the networks to ONNX for onnxruntime serving",
                       description="Export the VAE encoder/decoder, text encoder, DiT velocity and LDRM "
                                   "(+ deformation) as ONNX graphs with dynamic batch/frames/resolution, "
                                   "plus manifest.json. The export runs on the CPU in float32 (it has no "
                                   "--device); the graphs run on any onnxruntime provider, CUDA included.")
    e.add_argument("--checkpoint", type=Path, default=None,
                   help="model folder (default: the shipped weights of --config)")
    e.add_argument("--config", default=DEFAULT_CONFIG, help=config_help)
    e.add_argument("--out", type=_out_path, required=True, help=OUT_HELP)
    e.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    e.add_argument("--no-text", action="store_true", help="leave out the text encoder (empty prompt only)")
    e.add_argument("--static", action="store_true",
                   help="leave out the deformation network (static scenes only)")
    e.add_argument("--opset", type=int, default=18, help="ONNX opset, >= 18 (default: 18)")
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
    r.add_argument("--fps", type=int, default=8, help="video frame rate (default: 8)")
    r.add_argument("--device", default=AUTO, help=DEVICE_HELP + "; where the scene is rendered")
    r.add_argument("--quiet", action="store_true", help="no progress bar")
    r.add_argument("--out", type=_out_path, required=True, help=OUT_HELP)
    r.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    v = sub.add_parser("view", help="serve an output folder's interactive 4D viewer on 127.0.0.1",
                       description="Serve DIR's viewer (the full scene, never the size-reduced embedded copy) on "
                                   "127.0.0.1 only, and print the address; Ctrl-C stops. viewer.html in DIR "
                                   "also opens without a server (double click).")
    v.add_argument("folder", type=Path, metavar="DIR", help="output folder of `diff4splat generate`, `fit` or `render`")
    v.add_argument("--port", type=int, default=8000, help="TCP port on 127.0.0.1 (default: 8000; 0: any free port)")
    plugins = {ep.name: ep for ep in entry_points(group=PLUGIN_GROUP)}  # e.g. `evaluate`, from `training`
    if load_command is not None and load_command not in plugins:
        raise ValueError(f"load_command: {load_command!r} is not a {PLUGIN_GROUP} entry point "
                         f"(known: {sorted(plugins)})")
    for name, ep in plugins.items():
        if name == load_command:
            ep.load()(sub)
        else:  # placeholder: its arguments are left unparsed until the entry point is loaded
            placeholder = sub.add_parser(name, add_help=False, help=f"(from {ep.module}; `diff4splat {name} --help`)")
            placeholder.set_defaults(plugin=name)
    return parser


def _load_model(checkpoint: Path | None, config: str):
    """``load_model`` with its warnings (e.g. the random-model notice) printed as one line each on stderr.

    Returns:
        (model, source description, seconds taken).
    """
    from .pipeline import load_model

    if checkpoint is not None and not checkpoint.is_dir():
        raise FileNotFoundError(f"--checkpoint: {checkpoint} is not a folder")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        t0 = time.perf_counter()
        model, source = load_model(checkpoint, config, seed=0)
        t_load = time.perf_counter() - t0
    for w in caught:
        print(f"diff4splat: warning: {w.message}", file=sys.stderr)
    return model, source, t_load


def export_onnx_command(args) -> dict:
    """Run ``export-onnx``; returns the manifest written to ``--out/manifest.json``."""
    from .export import EXPORT_KIND, check_opset, export_onnx
    from .io.outdir import check_output_dir

    check_output_dir(args.out, inputs=[args.checkpoint], overwrite=args.overwrite, kind=EXPORT_KIND)
    check_opset(args.opset)
    model, source, _ = _load_model(args.checkpoint, args.config)
    checkpoint = None if source.startswith("random:") else Path(source)  # hash the weight files read
    return export_onnx(model, args.out, text=not args.no_text, deformation=not args.static, opset=args.opset,
                       checkpoint=checkpoint, source=source, inputs=[args.checkpoint], overwrite=args.overwrite)


def _check_generate_args(args) -> None:
    """CLI-level checks of ``generate``'s arguments, before any model is loaded (messages name the flags)."""
    from .cameras.trajectories import check_amplitude
    from .io.inputs import check_input_file
    from .io.outdir import check_output_dir
    from .io.video import check_fps
    from .limits import check_limit
    from .pipeline import check_prompt, check_seed

    check_input_file(args.image, "image")
    check_output_dir(args.out, inputs=_generate_inputs(args), overwrite=args.overwrite, kind="generate")
    for name in ("frames", "steps", "resolution"):
        if getattr(args, name) is not None:
            check_limit(name, check_positive_int(f"--{name}", getattr(args, name)), f"--{name}")
    if args.depth is not None:
        check_input_file(args.depth, "--depth")
    check_seed(args.seed, "--seed")
    check_prompt(args.prompt, "--prompt")
    if args.amplitude is not None and args.cameras is not None:
        raise ValueError("--amplitude scales a --trajectory preset; it does not apply to --cameras "
                         "(the camera file fixes the path)")
    if args.cameras is None:
        check_amplitude(args.trajectory, args.amplitude, "--amplitude")
    check_fps(check_positive_int("--fps", args.fps), "--fps")
    if args.runtime == "onnxruntime":
        if args.onnx is None:
            raise ValueError("--runtime onnxruntime needs --onnx DIR (a folder written by `diff4splat export-onnx`)")
        if (args.checkpoint is not None or args.config is not None or args.device != AUTO
                or args.dtype != "float32" or args.offload != "none"):
            raise ValueError("--checkpoint, --config, --device, --dtype and --offload do not apply to --runtime "
                             "onnxruntime "
                             "(the export's manifest fixes the model; onnxruntime picks CUDA or CPU)")
        if not args.onnx.is_dir():
            raise FileNotFoundError(f"--onnx: {args.onnx} is not a folder")
    elif args.onnx is not None:
        raise ValueError("--onnx needs --runtime onnxruntime")
    else:
        args.device = resolve_device(args.device, "--device")  # before any model is loaded


def _generate_inputs(args) -> list:
    """The paths ``generate`` reads; ``--out`` may not be one of them or hold one."""
    return [args.image, args.checkpoint, args.cameras, args.onnx, args.depth]


def _load_pipeline(args):
    """The pipeline over the runtime ``--runtime`` asks for.

    Returns:
        (pipeline, model source description, seconds taken to load, extra version strings for meta.json).
    """
    from models.bundle import DEFAULT_CONFIG

    from .pipeline import DTYPES, Diff4SplatPipeline

    if args.runtime == "onnxruntime":
        import onnxruntime

        from .onnx_runtime import OnnxRuntime

        t0 = time.perf_counter()
        runtime = OnnxRuntime(args.onnx)
        t_load = time.perf_counter() - t0
        source = f"onnx:{args.onnx} ({runtime.manifest['source']})"
        return Diff4SplatPipeline(runtime), source, t_load, {"onnxruntime": onnxruntime.__version__}
    model, source, t_load = _load_model(args.checkpoint, args.config or DEFAULT_CONFIG)
    return (Diff4SplatPipeline(model, device=args.device, dtype=DTYPES[args.dtype], offload=args.offload), source,
            t_load, {})


def _load_cameras(path: Path, frames: int | None, photo_shape: tuple[int, int], width: int, height: int):
    """``--cameras`` file → camera path at the model's ``width`` × ``height``.

    RealEstate10K intrinsics are normalised by the video frame, i.e. by the photograph as displayed:
    ``photo_shape`` is its (H, W) after EXIF orientation (:func:`diff4splat.io.image.read_image`),
    the same image that is centre-cropped for the model.
    """
    from .io import load_cameras_json, load_realestate10k
    from .io.inputs import check_input_file

    check_input_file(path, "--cameras")
    if path.suffix.lower() == ".json":
        cams = load_cameras_json(path)
    else:
        cams = load_realestate10k(path, photo_shape[1], photo_shape[0])
    if frames is not None and frames != len(cams):
        raise ValueError(f"--frames {frames} differs from the {len(cams)} cameras in {path}")
    return cams.fitted(width, height)


def _load_inputs(args, pipe):
    """Decode the photograph once; its displayed shape serves the centre crop, the camera file and the depth map.

    Returns:
        (image (H, W, 3) in [0, 1] at the output resolution, camera path at the output resolution, the depth map
        (H, W) or None).
    """
    from .io.depth_maps import fit_depth_map, read_depth_map
    from .io.image import preprocess_image, read_image
    from .pipeline import DEFAULT_RESOLUTION

    cfg = pipe.config
    if args.frames is not None:
        cfg.vae.num_latent_frames(args.frames)  # T = 1 + 4k, checked before any work
    resolution = args.resolution if args.resolution is not None else max(DEFAULT_RESOLUTION, cfg.height)
    width, height = pipe.output_size(resolution)
    depth = None
    if args.depth is not None:  # read before the photo is decoded: a bad file costs nothing
        raw_depth = read_depth_map(args.depth, args.depth_kind)
    photo = read_image(args.image)
    image = preprocess_image(photo, (height, width))
    if args.depth is not None:
        depth, note = fit_depth_map(raw_depth, photo.shape[:2], (height, width))
        if note is not None and not args.quiet:
            print(f"diff4splat: note: --depth: {note}", file=sys.stderr)
    if args.cameras is not None:
        cameras = _load_cameras(args.cameras, args.frames, photo.shape[:2], width, height)
    else:
        cameras = pipe.default_cameras(args.trajectory, args.frames, args.amplitude, resolution=resolution)
    return image, cameras, depth


def _meta(args, pipe, result, source: str, versions: dict, timings: dict) -> dict:
    """meta.json of ``generate``: every setting comes from what the pipeline actually used."""
    import torch

    from . import __version__

    cfg = pipe.config
    return {
        "model": source,
        "config": cfg.name,
        "runtime": pipe.runtime.name,
        "device": str(pipe.device),
        "dtype": None if args.runtime != "torch" else args.dtype,
        "offload": None if args.runtime != "torch" else args.offload,
        "image": str(args.image),
        "prompt": args.prompt,
        "trajectory": None if args.cameras is not None else args.trajectory,
        "cameras_file": None if args.cameras is None else str(args.cameras),
        "frames": len(result.cameras),
        "width": result.cameras.width,
        "height": result.cameras.height,
        "model_width": cfg.width,
        "model_height": cfg.height,
        "eps2d": result.eps2d,
        "background": list(result.background),
        "photo_psnr_db": result.photo_psnr_db,
        "depth_file": None if args.depth is None else str(args.depth),
        "depth_kind": None if args.depth is None else args.depth_kind,
        "fps": args.fps,
        "seed": args.seed,
        "steps": result.steps,
        "sampler": result.sampler,
        "shift": result.shift,
        "static": result.scene.is_static,
        "num_gaussians": result.scene.num_gaussians,
        "prune": result.prune_stats,
        "timings_s": timings,
        "versions": {"diff4splat": __version__, "torch": torch.__version__, "python": platform.python_version(),
                     **versions},
    }


def generate(args) -> dict:
    """Run ``generate``: check arguments → load the runtime → load image and cameras → run the pipeline
    → render the path → write the output folder. Returns the meta dict written to meta.json."""
    from .io.output import write_scene_folder
    from .limits import check_memory, check_output_size
    from .render.sequence import render_path

    t_start = time.perf_counter()
    _check_generate_args(args)
    pipe, source, t_load, versions = _load_pipeline(args)
    image, cameras, depth = _load_inputs(args, pipe)
    check_output_size(len(cameras), cameras.width, cameras.height,  # before any network runs
                      pipe.scene_slots(cameras.width, cameras.height, len(cameras)))
    check_memory(pipe.memory_estimate(cameras.width, cameras.height, len(cameras)),
                 f"{len(cameras)} frames at {cameras.width}×{cameras.height}", "--frames or --resolution")
    result = pipe(image, cameras, args.prompt, steps=args.steps, sampler=args.sampler, seed=args.seed,
                  progress=not args.quiet, depth=depth, depth_kind=args.depth_kind)
    t0 = time.perf_counter()
    colors, depths, alphas = render_path(result.scene, result.cameras, eps2d=result.eps2d,
                                         background=result.background, progress=not args.quiet)
    timings = {"load_model": t_load, **result.timings, "render": time.perf_counter() - t0}
    meta = _meta(args, pipe, result, source, versions, timings)
    t0 = time.perf_counter()
    write_scene_folder(args.out, result.scene, result.cameras, colors, depths, alphas, meta, fps=args.fps,
                       depth_fallback=pipe.config.scene_depth, inputs=_generate_inputs(args), overwrite=args.overwrite)
    timings["write"] = time.perf_counter() - t0
    timings["total"] = time.perf_counter() - t_start
    return meta


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``diff4splat`` console script. Returns the exit code: 0, 2 after an expected
    failure (one ``diff4splat: error: …`` line, :func:`diff4splat.errors.run_cli`), 130 after Ctrl-C."""
    return run_cli("diff4splat", lambda: _main(argv), expected=(CLIError,))


def _main(argv: list[str] | None) -> int:
    parser = build_parser()
    args, unknown = parser.parse_known_args(argv)
    if getattr(args, "plugin", None) is not None:  # load that command's entry point, parse again
        args = build_parser(load_command=args.plugin).parse_args(argv)
    elif unknown:
        parser.error(f"unrecognized arguments: {' '.join(unknown)}")
    if args.command == "generate":
        meta = generate(args)
        t = meta["timings_s"]
        print(f"wrote {args.out} ({meta['frames']} frames, {meta['num_gaussians']} Gaussians, "
              f"{'static' if meta['static'] else 'dynamic'}) in {t['total']:.1f} s")
    elif args.command == "export-onnx":
        manifest = export_onnx_command(args)
        print(f"wrote {args.out} ({', '.join(f['file'] for f in manifest['files'].values())}, "
              f"opset {manifest['opset']})")
    elif args.command == "render":
        from .rerender import rerender

        meta = rerender(args.folder, args.out, cameras=args.cameras, trajectory=args.trajectory,
                        amplitude=args.amplitude, frames=args.frames, width=args.width, height=args.height,
                        fps=args.fps, overwrite=args.overwrite, progress=not args.quiet,
                        device=resolve_device(args.device, "--device"))
        print(f"wrote {args.out} ({meta['frames']} frames, {meta['width']}x{meta['height']})")
    elif args.command == "view":
        from .view import serve

        return serve(args.folder, args.port)
    elif hasattr(args, "func"):
        return args.func(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
