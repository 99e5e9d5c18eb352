"""How well `generate` reproduces real photographs at the input view, against a thumbnail baseline.

    python benchmarks/photo_fidelity.py [PHOTO ...] [--checkpoint DIR] [--config NAME] [--prompt TEXT]
                                        [--resolution PX] [--write]

For each photograph (default: the shipped examples/chelsea.png), ``diff4splat generate`` runs exactly as a user
runs it (default trajectory and frames, ``--resolution`` pixels of height, into a temporary folder), and frame 0
of the ``video.mp4`` it wrote is compared with the photograph as ``generate`` reads it (centre crop, resized to the
output resolution). Also (``training.evaluate.photo_fidelity``):

- ``render``: the scene rendered at the input camera, t = 0, before video encoding, at the output resolution and
  area-averaged to the model resolution (64² for ``base``);
- ``thumbnail``: the photograph reduced to 8×8 (area average) and upsampled bilinearly — what the VAE's spatial
  compression would keep at best without learning anything — at both resolutions.

PSNR in dB (kornia) of images in [0, 1]. ``--write`` puts the table into docs/benchmarks.md (``photo_fidelity``).
Photos must not be training images (docs/DESIGN.md, "Training"): chelsea.png is the demo; keep other unseen
photos outside the repo for development and pass them as arguments.
"""
from __future__ import annotations

import argparse
import functools
import sys
import tempfile
from pathlib import Path

import cv2
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import load_pipeline, markdown_table, publish, repo_relative  # noqa: E402

from diff4splat.generate import generate  # noqa: E402
from diff4splat.io import load_image  # noqa: E402
from diff4splat.pipeline import DEFAULT_RESOLUTION  # noqa: E402
from diff4splat.request import load_pipeline as load_generate_pipeline  # noqa: E402
from diff4splat.request import write  # noqa: E402
from models.bundle import DEFAULT_CONFIG  # noqa: E402
from training.eval_metrics import image_psnr  # noqa: E402
from training.evaluate import photo_fidelity  # noqa: E402

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "chelsea.png"


def video_frame0_psnr(photo: Path, target: torch.Tensor, args) -> float:
    """PSNR of frame 0 of the video.mp4 that ``diff4splat generate`` writes, against ``target`` (H, W, 3)."""
    with tempfile.TemporaryDirectory() as tmp:
        loader = functools.partial(load_generate_pipeline, args.checkpoint, None if args.checkpoint else args.config)
        write(generate(photo, pipeline=loader, prompt=args.prompt, resolution=args.resolution), f"{tmp}/out")
        ok, frame = cv2.VideoCapture(f"{tmp}/out/video.mp4").read()
        if not ok:
            raise RuntimeError(f"could not read frame 0 of the video of {photo}")
    rgb = torch.from_numpy(cv2.cvtColor(frame, cv2.COLOR_BGR2RGB)).float() / 255
    return image_psnr(rgb.permute(2, 0, 1)[None], target.permute(2, 0, 1)[None])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("photos", nargs="*", type=Path, default=[EXAMPLE])
    ap.add_argument("--checkpoint", type=Path, default=None)
    ap.add_argument("--config", default=DEFAULT_CONFIG)
    ap.add_argument("--prompt", default="")
    ap.add_argument("--resolution", type=int, default=DEFAULT_RESOLUTION)
    ap.add_argument("--write", action="store_true")
    args = ap.parse_args()
    pipe, source = load_pipeline(args.checkpoint, args.config)
    cfg = pipe.config
    width, height = pipe.output_size(args.resolution)
    rows = []
    for photo in args.photos:
        target = load_image(photo, size=(height, width))
        fid = photo_fidelity(pipe, photo, args.prompt, resolution=args.resolution)
        row = [photo.name, f"{video_frame0_psnr(photo, target, args):.2f}", f"{fid['photo_psnr']:.2f}",
               f"{fid['photo_thumbnail']:.2f}", f"{fid['photo_psnr_model']:.2f}", f"{fid['photo_thumbnail_model']:.2f}"]
        rows.append(row)
        print(" | ".join(row), flush=True)
    table = markdown_table(["photo", f"video.mp4 frame 0, {width}×{height}", f"render, {width}×{height}",
                            f"thumbnail 8×8, {width}×{height}", f"render, {cfg.width}×{cfg.height}",
                            f"thumbnail 8×8, {cfg.width}×{cfg.height}"], rows)
    publish("photo_fidelity", f"Input-view fidelity on real photographs ({repo_relative(source)}, output "
            f"{width}×{height}, model {cfg.width}×{cfg.height}, prompt {args.prompt!r})",
            "PSNR (dB) against the photograph as `generate` reads it.", table, args.write)

if __name__ == "__main__":
    main()
