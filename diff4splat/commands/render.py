"""``diff4splat render``: its flags and the call of :func:`diff4splat.render_command.rerender`."""
from __future__ import annotations

import argparse
from pathlib import Path

from diff4splat.cameras import TRAJECTORIES
from diff4splat.commands.options import add_out_flags
from diff4splat.io.video import DEFAULT_FPS
from diff4splat.render_command import rerender
from diff4splat.utils.devices import AUTO, DEVICE_HELP, resolve_device

__all__ = ["register", "run"]


def register(sub) -> argparse.ArgumentParser:
    """Add ``render`` and its flags to the ``diff4splat`` subparsers; returns its parser."""
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
    add_out_flags(r)
    r.set_defaults(func=run)
    return r


def run(args: argparse.Namespace) -> int:
    """Run ``render``; prints the folder's line, returns 0."""
    meta = rerender(args.folder, args.out, cameras=args.cameras, trajectory=args.trajectory,
                    amplitude=args.amplitude, frames=args.frames, width=args.width, height=args.height,
                    fps=args.fps, overwrite=args.overwrite, progress=not args.quiet,
                    device=resolve_device(args.device, "--device"))
    print(f"wrote {args.out} ({meta['frames']} frames, {meta['width']}x{meta['height']})")
    return 0
