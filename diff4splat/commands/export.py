"""``diff4splat export-onnx``: its flags and the call of :func:`diff4splat.export.export_checkpoint`."""
from __future__ import annotations

import argparse

from diff4splat.commands.options import add_model_flags, add_out_flags
from diff4splat.export import MAX_OPSET, MIN_OPSET, export_checkpoint
from diff4splat.utils.errors import printed_warnings
from models.bundle import DEFAULT_CONFIG

__all__ = ["register", "run"]


def register(sub) -> argparse.ArgumentParser:
    """Add ``export-onnx`` and its flags to the ``diff4splat`` subparsers; returns its parser."""
    e = sub.add_parser("export-onnx", help="export the networks to ONNX for onnxruntime serving",
                       description="Export the VAE encoder/decoder, text encoder, DiT velocity and LDRM "
                                   "(+ deformation) as ONNX graphs with dynamic batch/frames/resolution, "
                                   "plus manifest.json. The export runs on the CPU in float32 (it has no "
                                   "--device); the graphs run on any onnxruntime provider, CUDA included.")
    add_model_flags(e, DEFAULT_CONFIG)
    add_out_flags(e)
    e.add_argument("--no-text", action="store_true", help="leave out the text encoder (empty prompt only)")
    e.add_argument("--static", action="store_true",
                   help="leave out the deformation network (static scenes only)")
    e.add_argument("--opset", type=int, default=MIN_OPSET,
                   help=f"ONNX opset, {MIN_OPSET} to {MAX_OPSET} (default: {MIN_OPSET})")
    e.set_defaults(func=run)
    return e


def run(args: argparse.Namespace) -> int:
    """Run ``export-onnx`` (:func:`diff4splat.export.export_checkpoint`, warnings printed); prints the files written,
    returns 0."""
    with printed_warnings():
        manifest = export_checkpoint(args.checkpoint, args.out, config=args.config, text=not args.no_text,
                                     deformation=not args.static, opset=args.opset, overwrite=args.overwrite)
    print(f"wrote {args.out} ({', '.join(f['file'] for f in manifest['files'].values())}, "
          f"opset {manifest['opset']})")
    return 0
