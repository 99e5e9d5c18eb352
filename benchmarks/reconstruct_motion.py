"""``reconstruct``'s motion on synthetic clips with true 3D tracks: displacement error against holding still.

    python benchmarks/reconstruct_motion.py --data DIR [DIR ...] [--checkpoint DIR] [--device cpu] [--write]

Each held-out clip of a ``data_prep synth`` set (its first camera, 17 frames at the model's 64²) is given to
:meth:`Diff4SplatPipeline.reconstruct` as a video with its true cameras — the true frames, so the
LDRM reads the clip's own latents and the motion is measured on the frames themselves — and the scene's motion is
scored as ``diff4splat evaluate`` scores ``generate``'s (:func:`training.evaluate.scene_motion`: the photo layer's
point at each track's frame-0 pixel, deformed to each time; :func:`training.eval_metrics.motion_errors`): the
displacement error from frame 0 (EPE3D of the motion, metres) against holding still, the fractions within 5 / 10 cm,
and on static clips the spurious motion (mean displacement, mm), for each ``--layers`` choice. ``--write`` puts the
table into docs/benchmarks.md (``reconstruct_motion_<label>``).
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import markdown_table, parse_pipeline_run, publish  # noqa: E402

from diff4splat.assembly.layers import LAYERS  # noqa: E402
from diff4splat.cameras import CameraPath  # noqa: E402
from training.evaluate import held_out_clips, scene_motion  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, nargs="+", required=True, help="held-out sets (data_prep synth)")
    args, loaded = parse_pipeline_run(ap)
    pipe, cfg = loaded.pipeline, loaded.pipeline.config
    clips = [clip for root in args.data for clip in held_out_clips(root, cfg.height, cfg.width, cfg.num_frames, None)]
    dynamic = [c for c in clips if bool(c["dynamic"])]
    rows, hold = [], None
    for layers in LAYERS:
        found = {"dynamic": [], "static": [], "seconds": []}
        for clip in clips:
            cams = CameraPath(clip["viewmats"].double(), clip["Ks"].double(), cfg.width, cfg.height,
                              clip["times"].double())
            t0 = time.perf_counter()
            result = pipe.reconstruct(clip["video"].permute(1, 2, 3, 0), cams, layers=layers)
            found["seconds"].append(time.perf_counter() - t0)
            found["dynamic" if bool(clip["dynamic"]) else "static"].append(scene_motion(pipe, result, clip))

        def mean(key: str, which: str, found: dict = found) -> float:
            values = [m[key] for m in found[which] if m[key] == m[key]]  # NaN: no visible pair
            return statistics.fmean(values) if values else float("nan")

        epe, hold = mean("motion_disp_epe", "dynamic"), mean("motion_disp_hold", "dynamic")
        hold_d = (mean("motion_disp_hold_d5", "dynamic"), mean("motion_disp_hold_d10", "dynamic"))
        rows.append([f"`--layers {layers}`", f"{epe:.3f}", f"{epe / hold:.2f}",
                     f"{mean('motion_disp_d5', 'dynamic'):.2f} / {mean('motion_disp_d10', 'dynamic'):.2f}",
                     f"{1000 * mean('motion_disp_epe', 'static'):.1f}",
                     f"{statistics.fmean(found['seconds']):.1f}"])
        print(" | ".join(rows[-1]), flush=True)
    rows.append(["holding still", f"{hold:.3f}", "1.00", f"{hold_d[0]:.2f} / {hold_d[1]:.2f}", "0.0", "—"])
    table = markdown_table(["`reconstruct`", "displacement error (m)", "× holding still", "δ 5 / 10 cm",
                            "static clips (mm)", "s per clip"], rows)
    sets = ", ".join(str(d) for d in args.data)
    publish(f"reconstruct_motion_{args.label or args.data[0].name}", f"`reconstruct`'s motion on synthetic clips "
            f"({sets}: {len(dynamic)} dynamic, {len(clips) - len(dynamic)} static)", f"{args.note} True frames and "
            "cameras at 64², the LDRM's depth.".strip(), table, args.write)


if __name__ == "__main__":
    main()
