"""``diff4splat`` command line: ``diff4splat generate IMAGE ... --out DIR`` and ``diff4splat export-onnx --out DIR``.

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

__all__ = ["main", "build_parser"]

EXIT_USAGE = 2
PLUGIN_GROUP = "diff4splat.commands"
"""Entry-point group of extra subcommands: ``register(subparsers)`` adds a parser whose defaults hold
``func(args) -> int``. ``training`` registers ``evaluate`` this way, so this package never imports it."""


class CLIError(Exception):
    """A user error reported as one line with exit code 2."""


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one line, exit 2 (argparse prints usage + message)
        raise CLIError(message)


def build_parser() -> argparse.ArgumentParser:
    from .cameras import TRAJECTORIES

    parser = _Parser(prog="diff4splat", description="One photograph + a camera path + a prompt → a 4D Gaussian scene.")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    g = sub.add_parser("generate", help="generate a 4D scene from an image",
                       description="Generate a 4D Gaussian scene from one image and write the output folder.")
    g.add_argument("image", help="input photograph (any format OpenCV reads: RGB, RGBA, grey, 8/16-bit)")
    cam = g.add_mutually_exclusive_group()
    cam.add_argument("--trajectory", choices=TRAJECTORIES, default=None,
                     help="camera path preset (default: orbit)")
    cam.add_argument("--cameras", type=Path, default=None,
                     help="camera path file: cameras.json (our format) or RealEstate10K .txt")
    g.add_argument("--amplitude", type=float, default=None,
                   help="preset amplitude in units of the scene depth (preset default if omitted)")
    g.add_argument("--frames", type=int, default=None, help="number of frames T = 1 + 4k (default: config)")
    g.add_argument("--prompt", default="", help="text describing the motion; empty = no text encoder")
    g.add_argument("--steps", type=int, default=None, help="sampler steps (default: config)")
    g.add_argument("--sampler", choices=("euler", "heun"), default=None, help="ODE sampler (default: config)")
    g.add_argument("--seed", type=int, default=0, help="noise seed (default: 0)")
    g.add_argument("--checkpoint", type=Path, default=None,
                   help="model folder (default: the shipped weights of --config)")
    g.add_argument("--config", default=None, help="model config name in configs/ (default: tiny)")
    g.add_argument("--fps", type=int, default=8, help="video frame rate (default: 8)")
    g.add_argument("--device", default="cpu", help="torch device (default: cpu)")
    g.add_argument("--backend", choices=("torch", "onnxruntime"), default="torch",
                   help="run the networks with PyTorch or with onnxruntime on an --onnx export (default: torch)")
    g.add_argument("--onnx", type=Path, default=None, help="folder written by `diff4splat export-onnx` "
                   "(with --backend onnxruntime)")
    g.add_argument("--quiet", action="store_true", help="no progress bars")
    g.add_argument("--out", type=Path, required=True, help="output folder (replaced atomically)")

    e = sub.add_parser("export-onnx", help="export the networks to ONNX for onnxruntime serving",
                       description="Export the VAE encoder/decoder, text encoder, DiT velocity and LDRM (+ deformation) "
                                   "as ONNX graphs with dynamic batch/frames/resolution, plus manifest.json.")
    e.add_argument("--checkpoint", type=Path, default=None,
                   help="model folder (default: the shipped weights of --config)")
    e.add_argument("--config", default="tiny", help="model config name in configs/ (default: tiny)")
    e.add_argument("--out", type=Path, required=True, help="output folder (replaced atomically)")
    e.add_argument("--no-text", action="store_true", help="leave out the text encoder (empty prompt only)")
    e.add_argument("--static", action="store_true",
                   help="leave out the deformation network (static scenes only)")
    e.add_argument("--opset", type=int, default=18, help="ONNX opset, >= 18 (default: 18)")
    for ep in entry_points(group=PLUGIN_GROUP):  # e.g. `evaluate`, registered by the training package
        ep.load()(sub)
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
    from .export import check_opset, export_onnx

    if args.out.exists() and not args.out.is_dir():
        raise FileExistsError(f"--out: {args.out} is a file")
    check_opset(args.opset)
    model, source, _ = _load_model(args.checkpoint, args.config)
    checkpoint = None if source.startswith("random:") else Path(source)  # hash the weight files read
    return export_onnx(model, args.out, text=not args.no_text, deformation=not args.static, opset=args.opset,
                       checkpoint=checkpoint, source=source)


def _load_cameras(args, image_shape: tuple[int, int], width: int, height: int):
    from .cameras import CameraPath
    from .io import load_cameras_json, load_realestate10k

    path: Path = args.cameras
    if not path.is_file():
        raise FileNotFoundError(f"--cameras: {path} does not exist")
    if path.suffix.lower() == ".json":
        cams: CameraPath = load_cameras_json(path)
    else:  # RealEstate10K intrinsics are normalised by the video frame, i.e. by the photograph
        cams = load_realestate10k(path, image_shape[1], image_shape[0])
    if args.frames is not None and args.frames != len(cams):
        raise ValueError(f"--frames {args.frames} differs from the {len(cams)} cameras in {path}")
    return cams.fitted(width, height)


def generate(args) -> dict:
    """Run ``generate``; returns the meta dict written to meta.json."""
    import cv2
    import torch

    from . import __version__
    from .io import load_image
    from .io.output import write_scene_folder
    from .pipeline import Diff4SplatPipeline
    from .render.sequence import render_path

    t_start = time.perf_counter()
    image_path = Path(args.image)
    if not image_path.is_file():
        raise FileNotFoundError(f"image: {image_path} does not exist")
    if args.out.exists() and not args.out.is_dir():
        raise FileExistsError(f"--out: {args.out} is a file")
    for name in ("frames", "steps"):
        v = getattr(args, name)
        if v is not None and v < 1:
            raise ValueError(f"--{name} must be ≥ 1, got {v}")
    if args.fps < 1:
        raise ValueError(f"--fps must be ≥ 1, got {args.fps}")
    versions = {}
    if args.backend == "onnxruntime":
        if args.onnx is None:
            raise ValueError("--backend onnxruntime needs --onnx DIR (a folder written by `diff4splat export-onnx`)")
        if args.checkpoint is not None or args.config is not None or args.device != "cpu":
            raise ValueError("--checkpoint, --config and --device do not apply to --backend onnxruntime "
                             "(the export's manifest fixes the model; onnxruntime picks CUDA or CPU)")
        import onnxruntime

        from .onnx_runtime import OnnxBackend

        t0 = time.perf_counter()
        backend = OnnxBackend(args.onnx)
        t_load = time.perf_counter() - t0
        source = f"onnx:{args.onnx} ({backend.manifest['source']})"
        versions["onnxruntime"] = onnxruntime.__version__
        pipe = Diff4SplatPipeline(backend)
    else:
        if args.onnx is not None:
            raise ValueError("--onnx needs --backend onnxruntime")
        model, source, t_load = _load_model(args.checkpoint, args.config or "tiny")
        pipe = Diff4SplatPipeline(model, device=args.device)
    cfg = pipe.config
    if args.frames is not None:
        cfg.vae.num_latent_frames(args.frames)  # T = 1 + 4k, checked before any work

    raw = cv2.imread(str(image_path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise ValueError(f"image: OpenCV cannot decode {image_path}")
    image = load_image(image_path, size=(cfg.height, cfg.width))
    if args.cameras is not None:
        cameras = _load_cameras(args, raw.shape[:2], cfg.width, cfg.height)
    else:
        cameras = pipe.default_cameras(args.trajectory or "orbit", args.frames, args.amplitude)

    result = pipe(image, cameras, args.prompt, steps=args.steps, sampler=args.sampler, seed=args.seed,
                  progress=not args.quiet)
    t0 = time.perf_counter()
    colors, depths, alphas = render_path(result.scene, result.cameras, progress=not args.quiet)
    t_render = time.perf_counter() - t0

    meta = {
        "model": source,
        "config": cfg.name,
        "backend": pipe.backend.name,
        "image": str(image_path),
        "prompt": args.prompt,
        "trajectory": None if args.cameras is not None else (args.trajectory or "orbit"),
        "cameras_file": None if args.cameras is None else str(args.cameras),
        "frames": len(result.cameras),
        "width": cfg.width,
        "height": cfg.height,
        "fps": args.fps,
        "seed": args.seed,
        "steps": args.steps if args.steps is not None else cfg.sampling.steps,
        "sampler": args.sampler or cfg.sampling.sampler,
        "shift": cfg.sampling.shift,
        "static": result.scene.is_static,
        "num_gaussians": result.scene.num_gaussians,
        "prune": result.prune_stats,
        "timings_s": {"load_model": t_load, **result.timings, "render": t_render},
        "versions": {"diff4splat": __version__, "torch": torch.__version__, "python": platform.python_version(),
                     **versions},
    }
    t0 = time.perf_counter()
    write_scene_folder(args.out, result.scene, result.cameras, colors, depths, alphas, meta, fps=args.fps,
                       depth_fallback=cfg.scene_depth)
    meta["timings_s"]["write"] = time.perf_counter() - t0
    meta["timings_s"]["total"] = time.perf_counter() - t_start
    return meta


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``diff4splat`` console script. Returns the exit code."""
    try:
        args = build_parser().parse_args(argv)
        if args.command == "generate":
            meta = generate(args)
            t = meta["timings_s"]
            print(f"wrote {args.out} ({meta['frames']} frames, {meta['num_gaussians']} Gaussians, "
                  f"{'static' if meta['static'] else 'dynamic'}) in {t['total']:.1f} s")
        elif args.command == "export-onnx":
            manifest = export_onnx_command(args)
            print(f"wrote {args.out} ({', '.join(f['file'] for f in manifest['files'].values())}, "
                  f"opset {manifest['opset']})")
        elif hasattr(args, "func"):
            return args.func(args)
        return 0
    except (CLIError, ValueError, FileNotFoundError, FileExistsError) as e:
        msg = " ".join(str(e).split())
        print(f"diff4splat: error: {msg}", file=sys.stderr)
        return EXIT_USAGE


if __name__ == "__main__":
    sys.exit(main())
