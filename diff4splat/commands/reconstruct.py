"""``diff4splat reconstruct``: its flags and the call of :func:`diff4splat.reconstruct.reconstruct` and
:func:`diff4splat.request.write` (the library does the work and every check; this module only maps flags)."""
from __future__ import annotations

import argparse
from functools import partial
from pathlib import Path

from diff4splat.assembly.layers import DEFAULT_LAYERS, LAYERS
from diff4splat.commands.options import add_model_flags, add_out_flags, report_scene
from diff4splat.io.video import DEFAULT_FPS
from diff4splat.reconstruct import reconstruct
from diff4splat.request import load_pipeline, write
from diff4splat.utils.devices import AUTO, DEVICE_HELP
from diff4splat.utils.errors import printed_warnings

__all__ = ["register", "run"]


def register(sub) -> argparse.ArgumentParser:
    """Add ``reconstruct`` and its flags to the ``diff4splat`` subparsers; returns its parser."""
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
    add_model_flags(rc)
    rc.add_argument("--fps", type=float, default=DEFAULT_FPS, help=f"video frame rate (default: {DEFAULT_FPS:g})")
    rc.add_argument("--device", default=AUTO, help=DEVICE_HELP)
    rc.add_argument("--no-frame-plys", dest="frame_plys", action="store_false",
                    help="leave out frames/NNNN.ply (scene.ply + deformation.npz hold the same)")
    rc.add_argument("--quiet", action="store_true", help="no progress bar")
    add_out_flags(rc)
    rc.set_defaults(func=run)
    return rc


def run(args: argparse.Namespace) -> int:
    """Run ``reconstruct`` and :func:`diff4splat.request.write`; prints the folder's line, returns 0."""
    with printed_warnings():  # the loader's and the run's, one line each
        output = reconstruct(
            args.video, args.cameras, pipeline=partial(load_pipeline, args.checkpoint, args.config, device=args.device),
            frames=args.frames, stride=args.stride, start=args.start, resolution=args.resolution, layers=args.layers,
            progress=not args.quiet, out=args.out, overwrite=args.overwrite, inputs=[args.checkpoint], fps=args.fps,
            frame_plys=args.frame_plys)
    return report_scene(args.out, write(output, args.out, overwrite=args.overwrite))
