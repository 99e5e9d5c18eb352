"""``diff4splat`` command line: ``generate`` (:mod:`diff4splat.generate_cli`), ``reconstruct``, ``export-onnx``,
``render`` (:mod:`diff4splat.render_command`), ``view`` (:mod:`diff4splat.viewer_server`) and plugin commands.
Bad input gets one line on stderr (``diff4splat: error: …``), exit code 2 and no output folder.
"""
from __future__ import annotations

import argparse
import sys
from functools import partial
from importlib.metadata import entry_points
from pathlib import Path

from diff4splat.cameras import TRAJECTORIES
from diff4splat.export import MAX_OPSET, MIN_OPSET, export_checkpoint
from diff4splat.generate import load_pipeline, write
from diff4splat.generate_cli import add_generate_parser, generate_command
from diff4splat.io.video import DEFAULT_FPS
from diff4splat.pipeline import load_model
from diff4splat.reconstruct import DEFAULT_LAYERS, LAYERS, reconstruct
from diff4splat.render_command import rerender
from diff4splat.utils.devices import AUTO, DEVICE_HELP, resolve_device
from diff4splat.utils.errors import print_warnings, run_cli
from diff4splat.viewer_server import serve
from models.bundle import DEFAULT_CONFIG, config_names

__all__ = ["main", "build_parser"]

OUT_HELP = ("output folder, written atomically; an existing one is replaced only if it is empty or an "
            "earlier output of this command (README, 'Output folders')")
OVERWRITE_HELP = ("also replace an existing --out that is not an earlier output of this command "
                  "(never a folder holding the inputs, the current or home directory)")
PLUGIN_GROUP = "diff4splat.commands"
"""Entry-point group of extra subcommands (``training``'s ``evaluate``): ``register(subparsers)`` adds a parser whose
defaults hold ``func(args) -> int``; it is loaded only when its command is chosen."""


class CLIError(Exception):
    """A user error reported as one line with exit code 2."""


def _out_path(value: str) -> Path:
    """``--out`` as a Path; an empty name (the current directory) is an error."""
    if not value.strip():
        raise argparse.ArgumentTypeError(f"empty folder name {value!r}; give a new folder name")
    return Path(value)


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one line, exit 2 (argparse prints usage + message)
        raise CLIError(message)


def build_parser(load_command: str | None = None) -> argparse.ArgumentParser:
    """The ``diff4splat`` argument parser; :data:`PLUGIN_GROUP` commands get a placeholder subparser except
    ``load_command``, whose entry point is loaded. ValueError: ``load_command`` is not a registered entry point."""
    config_help = f"shipped model config ({', '.join(config_names())}) or a YAML path (default: {DEFAULT_CONFIG})"

    parser = _Parser(prog="diff4splat", description="One photograph + a camera path + a prompt → a 4D Gaussian scene.")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    add_generate_parser(sub, out_type=_out_path, out_help=OUT_HELP, overwrite_help=OVERWRITE_HELP,
                        config_help=config_help)
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
    e.add_argument("--opset", type=int, default=MIN_OPSET,
                   help=f"ONNX opset, {MIN_OPSET} to {MAX_OPSET} (default: {MIN_OPSET})")
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
    r.add_argument("--out", type=_out_path, required=True, help=OUT_HELP)
    r.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    rc = sub.add_parser("reconstruct", help="turn a real video into a 4D scene (the LDRM on the video's latents)",
                        description="A monocular video (or a folder of frames) → the output folder of generate: the "
                                    "VAE encodes the clip, the LDRM places its pixels in 3D, the motion is measured "
                                    "from the frames (optical flow lifted with the LDRM's depth); frame 0 and the "
                                    "later source frames keep the video's own pixels.")
    rc.add_argument("video", type=Path, metavar="VIDEO",
                    help="video file (any format OpenCV reads) or folder of frames")
    rc.add_argument("--frames", type=int, default=None, help="clip length T = 1 + 4k (default: config)")
    rc.add_argument("--stride", type=int, default=1, help="take every S-th frame of the video (default: 1)")
    rc.add_argument("--start", type=int, default=0, help="first frame of the clip, 0-based (default: 0)")
    rc.add_argument("--cameras", type=Path, default=None, metavar="FILE",
                    help="cameras.json or RealEstate10K .txt for a moving camera: one camera per clip frame, or one "
                         "per video frame (the clip's are taken) (default: a still camera, the model's field of view)")
    rc.add_argument("--resolution", type=int, default=None,
                    help="output height in pixels (default: 256, or the model's if larger)")
    rc.add_argument("--layers", choices=LAYERS, default=DEFAULT_LAYERS,
                    help="frames kept as photo layers: every frame (T·1.25 Gaussians per output pixel), or the "
                         "LDRM's source frames 0, 4, 8, … (a quarter; coarser between frames) "
                         f"(default: {DEFAULT_LAYERS})")
    rc.add_argument("--checkpoint", type=Path, default=None,
                    help="model folder (default: the shipped weights of --config)")
    rc.add_argument("--config", default=None, help=config_help)
    rc.add_argument("--fps", type=float, default=DEFAULT_FPS, help=f"video frame rate (default: {DEFAULT_FPS:g})")
    rc.add_argument("--device", default=AUTO, help=DEVICE_HELP)
    rc.add_argument("--no-frame-plys", dest="frame_plys", action="store_false",
                    help="leave out frames/NNNN.ply (scene.ply + deformation.npz hold the same)")
    rc.add_argument("--quiet", action="store_true", help="no progress bar")
    rc.add_argument("--out", type=_out_path, required=True, help=OUT_HELP)
    rc.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
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


def export_onnx_command(args) -> dict:
    """Run ``export-onnx`` (:func:`diff4splat.export.export_checkpoint`, warnings printed); returns the manifest."""
    return export_checkpoint(args.checkpoint, args.out, config=args.config, text=not args.no_text,
                             deformation=not args.static, opset=args.opset, overwrite=args.overwrite,
                             load=partial(print_warnings, load_model))


def reconstruct_command(args) -> dict:
    """Run ``reconstruct`` and :func:`diff4splat.generate.write`; returns the meta dict of meta.json."""
    generation = reconstruct(
        args.video, args.cameras, pipeline=lambda: print_warnings(load_pipeline, args.checkpoint, args.config,
                                                                  device=args.device),
        frames=args.frames, stride=args.stride, start=args.start, resolution=args.resolution, layers=args.layers,
        progress=not args.quiet, out=args.out, overwrite=args.overwrite, inputs=[args.checkpoint], fps=args.fps,
        frame_plys=args.frame_plys)
    return write(generation, args.out, overwrite=args.overwrite)


def main(argv: list[str] | None = None) -> int:
    """The ``diff4splat`` console script; returns the exit code: 0, 2 after an expected failure
    (:func:`diff4splat.utils.errors.run_cli`), 130 after Ctrl-C."""
    return run_cli("diff4splat", lambda: _main(argv), expected=(CLIError,))


def _main(argv: list[str] | None) -> int:
    parser = build_parser()
    args, unknown = parser.parse_known_args(argv)
    if getattr(args, "plugin", None) is not None:  # load that command's entry point, parse again
        args = build_parser(load_command=args.plugin).parse_args(argv)
    elif unknown:
        parser.error(f"unrecognized arguments: {' '.join(unknown)}")
    if args.command in ("generate", "reconstruct"):
        meta = (generate_command if args.command == "generate" else reconstruct_command)(args)
        print(f"wrote {args.out} ({meta['frames']} frames, {meta['num_gaussians']} Gaussians, "
              f"{'static' if meta['static'] else 'dynamic'}) in {meta['timings_s']['total']:.1f} s")
    elif args.command == "export-onnx":
        manifest = export_onnx_command(args)
        print(f"wrote {args.out} ({', '.join(f['file'] for f in manifest['files'].values())}, "
              f"opset {manifest['opset']})")
    elif args.command == "render":
        meta = rerender(args.folder, args.out, cameras=args.cameras, trajectory=args.trajectory,
                        amplitude=args.amplitude, frames=args.frames, width=args.width, height=args.height,
                        fps=args.fps, overwrite=args.overwrite, progress=not args.quiet,
                        device=resolve_device(args.device, "--device"))
        print(f"wrote {args.out} ({meta['frames']} frames, {meta['width']}x{meta['height']})")
    elif args.command == "view":
        return serve(args.folder, args.port)
    elif hasattr(args, "func"):
        return args.func(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
