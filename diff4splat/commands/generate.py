"""``diff4splat generate``: its flags and the call of :func:`diff4splat.generate.generate` and
:func:`diff4splat.request.write` (the library does the work and every check; this module only maps flags)."""
from __future__ import annotations

import argparse
import sys
from functools import partial
from pathlib import Path

from diff4splat.assembly.assemble import DEPTH_KINDS
from diff4splat.cameras import DEFAULT_AMPLITUDES, DEFAULT_TRAJECTORY, TRAJECTORIES
from diff4splat.cameras.trajectories import amplitude_help
from diff4splat.commands.options import add_model_flags, add_out_flags, report_scene
from diff4splat.generate import generate
from diff4splat.io.video import DEFAULT_FPS
from diff4splat.pipeline import DEFAULT_RESOLUTION
from diff4splat.request import load_pipeline, write
from diff4splat.runtime import ATTENTION_KERNELS, OFFLOAD_MODES
from diff4splat.utils.devices import AUTO, DEVICE_HELP
from diff4splat.utils.errors import printed_warnings
from models.flow_matching import SAMPLERS

__all__ = ["register", "run"]


def register(sub) -> argparse.ArgumentParser:
    """Add ``generate`` and its flags to the ``diff4splat`` subparsers; returns its parser."""
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
                   help=f"output height in pixels, at least the model's height (the photo layer keeps the photograph "
                        f"at this resolution; default: {DEFAULT_RESOLUTION}, or the model's height if larger)")
    g.add_argument("--depth", type=Path, default=None, metavar="FILE",
                   help="a depth map of the photograph for its Gaussians instead of the network's: EXR (channel Z), "
                        ".npy, or a 16-bit PNG/TIFF (millimetres); NaN/inf/0 pixels are filled from the network")
    g.add_argument("--depth-kind", choices=DEPTH_KINDS, default="metric",
                   help="metric (z-depth in metres, used as given), relative (depth up to scale and shift) or inverse "
                        "(disparity up to scale and shift), both fitted to the network's depth (default: metric)")
    g.add_argument("--prompt", default="", help="text describing the motion; empty = no text encoder")
    g.add_argument("--drag", action="append", default=[], metavar="X,Y:DX,DY[@T]",
                   help="move the photograph's point (X, Y) (pixels of the file as given) by (DX, DY) pixels by "
                        "normalised clip time T in (0, 1] (default 1, the end); repeatable. The region of like colour "
                        "and depth around each point moves with it at its depth; the rest of the scene stays still")
    g.add_argument("--tracks", type=Path, default=None, metavar="FILE",
                   help="instead of --drag: an N × T × 2 .npy of point tracks (x, y pixels of the photograph over T "
                        "evenly spaced clip times, as TAPIR writes), each point moving its region as a drag does")
    g.add_argument("--steps", type=int, default=None, help="sampler steps (default: config)")
    g.add_argument("--sampler", choices=SAMPLERS, default=None, help="ODE sampler (default: config)")
    g.add_argument("--guidance", type=float, default=None,
                   help="classifier-free guidance scale with a prompt, in [0, 30]; 1 = off (default: config: 1 for "
                        "ours, 5 for Wan2.2, 6 for CogVideoX)")
    g.add_argument("--seed", type=int, default=0, help="noise seed (default: 0)")
    add_model_flags(g)
    g.add_argument("--fps", type=float, default=DEFAULT_FPS, help=f"video frame rate (default: {DEFAULT_FPS:g})")
    g.add_argument("--device", default=AUTO, help=DEVICE_HELP)
    g.add_argument("--dtype", choices=("float32", "bfloat16", "float16"), default="float32",
                   help="weight dtype of the networks (bfloat16 halves a GPU's memory use; default: float32); "
                        "sampling, Gaussians and rendering stay float32")
    g.add_argument("--offload", choices=OFFLOAD_MODES, default="none",
                   help="model: keep the networks in CPU memory and move one at a time to --device while it runs "
                        "(the paper-size model within 25 GB of GPU memory); model-prefetch: the same, and on CUDA "
                        "the DiT's copy overlaps its first sampling step (not with --compile); default: none")
    g.add_argument("--attention", choices=tuple(ATTENTION_KERNELS), default="auto",
                   help="fused attention kernel the networks try first (cudnn: cuDNN's, tuned for Hopper GPUs; the "
                        "others stay behind it); default: auto, torch's own order")
    g.add_argument("--compile", action="store_true",
                   help="torch.compile the transformer's blocks (regional compilation): the first sampling step "
                        "compiles, the later ones run fused kernels (for long runs on a GPU; needs a C++ compiler "
                        "on the CPU)")
    g.add_argument("--runtime", choices=("torch", "onnxruntime"), default=None,
                   help="run the networks with PyTorch or with onnxruntime on an --onnx export (default: onnxruntime "
                        "with --onnx, else torch)")
    g.add_argument("--onnx", type=Path, default=None, help="folder written by `diff4splat export-onnx`, run with "
                   "onnxruntime")
    g.add_argument("--no-frame-plys", dest="frame_plys", action="store_false",
                   help="leave out frames/NNNN.ply, the scene at each frame's time (scene.ply and deformation.npz "
                        "hold the same; frames/ is most of a long path's folder: 4.4 of 7.2 GB at the paper size)")
    g.add_argument("--quiet", action="store_true", help="no progress bars (notes and warnings still print)")
    add_out_flags(g)
    g.set_defaults(func=run)
    return g


def run(args: argparse.Namespace) -> int:
    """Run ``generate``: :func:`diff4splat.generate.generate` (the output folder, the frame rate and the request
    checked before the model loads; the loader's and the run's warnings printed as ``diff4splat: warning:`` lines)
    and :func:`diff4splat.request.write`; prints the folder's line, returns 0."""
    with printed_warnings():  # the loader's and the run's (a prompt cut to the tokenizer's length), one line each
        output = generate(
            args.image, args.cameras, pipeline=partial(
                load_pipeline, args.checkpoint, args.config, runtime=args.runtime, onnx=args.onnx, device=args.device,
                dtype=args.dtype, offload=args.offload, attention=args.attention, compile=args.compile),
            trajectory=args.trajectory, amplitude=args.amplitude, frames=args.frames, resolution=args.resolution,
            prompt=args.prompt, steps=args.steps, sampler=args.sampler, guidance=args.guidance, seed=args.seed,
            depth=args.depth, depth_kind=args.depth_kind, progress=not args.quiet,
            notes=lambda note: print(f"diff4splat: note: {note}", file=sys.stderr), out=args.out,
            overwrite=args.overwrite, inputs=[args.checkpoint, args.onnx], fps=args.fps, frame_plys=args.frame_plys,
            drags=args.drag, tracks=args.tracks)
    return report_scene(args.out, write(output, args.out, overwrite=args.overwrite))
