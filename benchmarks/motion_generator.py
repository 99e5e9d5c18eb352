"""The motion generator alone on held-out synthetic clips (``motion_dir_stage``;
:mod:`training.motion_generation`): the fraction of direction-test clips whose generated motion moves the captioned
object the named way with the caption and with its direction flipped, the median ratio of the generated to the true
displacement along the named way, and the static clips' motion (mm), for each guidance scale, against holding still
and the true motion tensor (the representation's ceiling: the grid's cells average a mover with what is around it)::

    python benchmarks/motion_generator.py --checkpoint DIR --data data/a data/b [--guidance 1 3] [--write SECTION]
        [--strip docs/img.jpg]

``--write`` puts the table in docs/benchmarks.md under ``motion_generator_<SECTION>``; ``--strip`` draws the first
six direction-test clips of the first set: the photograph with the true motion by the clip's end as arrows, then the
generated motion with the caption and with the flipped caption (the last guidance scale), each arrow a cell's
image-plane displacement f·Δx/z, f·Δy/z (f = the image's width: the synthetic cameras' ~53° field of view).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import markdown_table, publish  # noqa: E402

from diff4splat.io.video import save_image  # noqa: E402
from diff4splat.utils.devices import AUTO, DEVICE_HELP, resolve_device  # noqa: E402
from models.motion_generator import MotionGenerator, sample_motion  # noqa: E402
from training.direction_test import direction_query, flip_direction  # noqa: E402
from training.motion_generation import motion_examples, motion_stage_scores, static_motion_mm  # noqa: E402

ZOOM = 4
"""Enlargement of the strip's images."""


def arrows(image: torch.Tensor, motion: torch.Tensor, scale: float, label: str) -> np.ndarray:
    """(S·ZOOM, S·ZOOM, 3) uint8: ``image`` (3, S, S) in [−1, 1] with one arrow per cell of ``motion`` (3K, g, g)
    (units of ``scale``) whose last key time moves more than half a pixel."""
    S, g = image.shape[-1], motion.shape[-1]
    rgb = ((image.permute(1, 2, 0).cpu().numpy() + 1) * 127.5).clip(0, 255).astype(np.uint8)
    out = np.ascontiguousarray(cv2.resize(rgb, (S * ZOOM, S * ZOOM), interpolation=cv2.INTER_NEAREST))
    last = motion[-3:].cpu().numpy() * scale * S  # (3, g, g) image-plane pixels at S
    cell = S // g
    for y in range(g):
        for x in range(g):
            dx, dy = last[0, y, x], last[1, y, x]
            if np.hypot(dx, dy) > 0.5:
                a = ((x + 0.5) * cell * ZOOM, (y + 0.5) * cell * ZOOM)
                b = (a[0] + dx * ZOOM, a[1] + dy * ZOOM)
                cv2.arrowedLine(out, tuple(map(round, a)), tuple(map(round, b)), (255, 255, 0), 1, cv2.LINE_AA,
                                tipLength=0.25)
    cv2.putText(out, label, (3, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
    return out


def strip(model: MotionGenerator, ex, guidance: float, steps: int, seed: int, path: Path) -> None:
    """The ``--strip`` image (module docstring)."""
    rows = []
    for i in range(len(ex)):
        q = direction_query({"dynamic": ex.dynamic[i], "caption": ex.captions[i], "pixel_tracks": ex.pixel_tracks[i],
                             "pixel_track_valid": ex.valid[i]})
        if q is None:
            continue
        row = [arrows(ex.image[i], ex.motion[i], model.config.motion_scale, "truth")]
        for label, prompt in (("caption", ex.captions[i]), ("flipped", flip_direction(ex.captions[i]))):
            m = sample_motion(model, ex.image[i:i + 1], ex.depth[i:i + 1], [prompt], steps=steps, guidance=guidance,
                              generator=torch.Generator(device="cpu").manual_seed(seed))[0]
            row.append(arrows(ex.image[i], m, model.config.motion_scale, label))
        rows.append(np.concatenate(row, axis=1))
        if len(rows) == 6:
            break
    save_image(path, np.concatenate(rows, axis=0))


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("::")[0])
    ap.add_argument("--checkpoint", required=True, type=Path,
                    help="a model folder with a motion generator, or a MotionGenerator folder")
    ap.add_argument("--data", nargs="+", required=True, help="held-out dataset roots")
    ap.add_argument("--guidance", type=float, nargs="+", default=[1.0, 3.0])
    ap.add_argument("--steps", type=int, default=16, help="Euler steps (NFE per branch)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--device", default=AUTO, help=DEVICE_HELP)
    ap.add_argument("--write", default=None, help="section name suffix in docs/benchmarks.md")
    ap.add_argument("--strip", type=Path, default=None, help="image of the first set's first direction-test clips")
    args = ap.parse_args(argv)
    device = resolve_device(args.device)
    folder = args.checkpoint / "motion_generator"  # a model folder holds it there
    model = MotionGenerator.from_pretrained(folder if folder.is_dir() else args.checkpoint).to(device).eval()
    rows = []
    for n, root in enumerate(args.data):
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
        if args.strip and n == 0:
            strip(model, ex, args.guidance[-1], args.steps, args.seed, args.strip)
    head = ["set", "motion", "clips", "named way: caption", "named way: flipped", "magnitude / truth (median)",
            "static clips' motion (mm)", "s per sample"]
    publish(f"motion_generator_{args.write}", "The motion generator alone (direction test)",
            f"Device: {device}; {args.steps} Euler steps; checkpoint {Path(args.checkpoint).name}.",
            markdown_table(head, rows), bool(args.write))


if __name__ == "__main__":
    main()
