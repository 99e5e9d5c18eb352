"""The motion generator alone on held-out synthetic clips (issue 78's ``motion_dir_stage``;
:mod:`training.motion_generation`): the fraction of direction-test clips whose generated motion moves the captioned
object the named way with the caption and with its direction flipped, the median ratio of the generated to the true
displacement along the named way, and the static clips' motion (mm), for each guidance scale, against holding still
and the true motion tensor (the representation's ceiling: the grid's cells average a mover with what is around it)::

    python benchmarks/motion_generator.py --checkpoint DIR --data data/a data/b [--guidance 1 3] [--write SECTION]

``--write`` puts the table in docs/benchmarks.md under ``motion_generator_<SECTION>``.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import markdown_table, publish  # noqa: E402

from diff4splat.utils.devices import AUTO, DEVICE_HELP, resolve_device  # noqa: E402
from models.motion_generator import MotionGenerator  # noqa: E402
from training.motion_generation import motion_examples, motion_stage_scores, static_motion_mm  # noqa: E402


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("::")[0])
    ap.add_argument("--checkpoint", required=True, help="a MotionGenerator folder (save_pretrained)")
    ap.add_argument("--data", nargs="+", required=True, help="held-out dataset roots")
    ap.add_argument("--guidance", type=float, nargs="+", default=[1.0, 3.0])
    ap.add_argument("--steps", type=int, default=16, help="Euler steps (NFE per branch)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--device", default=AUTO, help=DEVICE_HELP)
    ap.add_argument("--write", default=None, help="section name suffix in docs/benchmarks.md")
    args = ap.parse_args(argv)
    device = resolve_device(args.device)
    model = MotionGenerator.from_pretrained(args.checkpoint).to(device).eval()
    rows = []
    for root in args.data:
        ex = motion_examples([root], model)
        ex.image, ex.depth = ex.image.to(device), ex.depth.to(device)
        ex.pixel_tracks, ex.valid = ex.pixel_tracks.to(device), ex.valid.to(device)
        name = Path(root).name
        truth = ex.motion.to(device)
        for label, motion in (("holding still", torch.zeros_like(truth)), ("the true motion tensor", truth)):
            s = motion_stage_scores(model, ex, sampler=lambda idx, prompts, m=motion: m[idx])
            rows.append([name, label, s.clips, f"{s.caption:.2f}", f"{s.flipped:.2f}", f"{s.magnitude_ratio:.2f}",
                         "0.0" if label == "holding still" else "–", "–"])
        for w in args.guidance:
            t = time.perf_counter()
            s = motion_stage_scores(model, ex, steps=args.steps, guidance=w, seed=args.seed)
            per_clip = (time.perf_counter() - t) / max(1, 2 * s.clips)
            still = static_motion_mm(model, ex, steps=args.steps, guidance=w, seed=args.seed)
            rows.append([name, f"generated, guidance {w:g}", s.clips, f"{s.caption:.2f}", f"{s.flipped:.2f}",
                         f"{s.magnitude_ratio:.2f}", f"{still:.1f}", f"{per_clip:.3f}"])
    head = ["set", "motion", "clips", "named way: caption", "named way: flipped", "magnitude / truth (median)",
            "static clips' motion (mm)", "s per sample"]
    publish(f"motion_generator_{args.write}", "The motion generator alone (direction test)",
            f"Device: {device}; {args.steps} Euler steps; checkpoint {Path(args.checkpoint).name}.",
            markdown_table(head, rows), bool(args.write))


if __name__ == "__main__":
    main()
