"""The classical motion route: scene flow from optical flow and depth, scored on held-out tracks, knob by knob.

    python benchmarks/flow_motion.py --data DIR [DIR ...] [--checkpoint DIR] [--device cpu] [--write]

For every clip of the held-out sets (``data_prep synth``), frame 0's pixels are tracked through the clip
(:func:`diff4splat.geometry.scene_flow.track_pixels`: OpenCV DIS, chained, forward-backward check) and lifted to 3D with
the clip's **true** z-depth and cameras (:func:`~diff4splat.geometry.scene_flow.lift_tracks`); each 3D track's frame-0
pixel takes that pixel's trajectory, scored as ``diff4splat evaluate`` scores a scene's motion
(:func:`training.eval_metrics.motion_errors`: displacement error from frame 0 against holding still, δ 5 / 10 cm).
The frames are the clip's own, or its round trip through the model's VAE (what an LDRM reading the true video's
latents could see of it). With the true depth this is the route's upper bound: what the issue asks of a motion
path reading the true video's latents is ≤ 0.5× holding still. Static clips report the spurious motion (mean
displacement of their tracks, mm). Time: tracking and lifting one 17-frame 64² clip on one thread.
``--write`` puts the table into docs/benchmarks.md (section ``flow_motion_<label>``, ``--label`` default: the first
set's folder name). ``--strip IMAGE`` saves, for the ``--strip-clips`` dynamic clips whose tracks move most, nine
evenly spaced frames (columns) of the clip and of its VAE round trip (rows, labelled, enlarged 2×), to look at.
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
import warnings
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import markdown_table, publish, save_strip  # noqa: E402

from diff4splat.geometry.scene_flow import FB_TOLERANCE_PX, FLOW_UPSAMPLE, GATE_PX, lift_tracks, track_pixels  # noqa: E402
from diff4splat.pipeline import load_model  # noqa: E402
from diff4splat.utils.devices import resolve_device  # noqa: E402
from training.eval_metrics import motion_errors  # noqa: E402
from training.evaluate import held_out_clips  # noqa: E402
from training.objectives import track_query_index  # noqa: E402

VARIANTS = [  # (label, frames, upsample, preset, fb_tolerance, gate_px)
    ("defaults", "true", FLOW_UPSAMPLE, "medium", FB_TOLERANCE_PX, GATE_PX),
    ("upsample 1", "true", 1, "medium", FB_TOLERANCE_PX, GATE_PX),
    ("upsample 2", "true", 2, "medium", FB_TOLERANCE_PX, GATE_PX),
    ("preset fast", "true", FLOW_UPSAMPLE, "fast", FB_TOLERANCE_PX, GATE_PX),
    ("no forward-backward check", "true", FLOW_UPSAMPLE, "medium", float("inf"), GATE_PX),
    ("gate 1 px", "true", FLOW_UPSAMPLE, "medium", FB_TOLERANCE_PX, 1.0),
    ("no gate", "true", FLOW_UPSAMPLE, "medium", FB_TOLERANCE_PX, 0.0),
    ("defaults, VAE round trip", "vae", FLOW_UPSAMPLE, "medium", FB_TOLERANCE_PX, GATE_PX),
]


def filled_depth(depth: torch.Tensor) -> torch.Tensor:
    """(T, H, W) z-depth with invalid (+inf) pixels set to the clip's largest valid depth."""
    valid = torch.isfinite(depth)
    far = depth[valid].max() if bool(valid.any()) else depth.new_tensor(1.0)
    return torch.where(valid, depth, far)


@torch.no_grad()
def clip_motion(clip: dict, frames: torch.Tensor, upsample: int, preset: str, fb: float, gate: float
                ) -> tuple[dict[str, float], float]:
    """:func:`motion_errors` of the lifted tracks of one clip, and the seconds tracking and lifting took."""
    T, _, H, W = frames.shape
    start = time.perf_counter()
    positions, tracked = track_pixels(frames, upsample=upsample, preset=preset, fb_tolerance=fb)
    points, _ = lift_tracks(positions, tracked, filled_depth(clip["depth"].to(frames)), clip["Ks"].to(frames),
                            clip["viewmats"].to(frames), gate_px=gate)
    seconds = time.perf_counter() - start
    tracks, visible = clip["tracks"], clip["track_visibility"] & clip["track_mask"][:, None]
    index, ok = track_query_index(tracks[:, 0], clip["Ks"][0], W, H, visible[:, 0])
    pred = points.reshape(T, H * W, 3)[:, index.to(points.device)].transpose(0, 1).cpu()
    return motion_errors(pred.float(), tracks, visible & ok[:, None]), seconds


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, nargs="+", required=True, help="held-out sets (data_prep synth)")
    ap.add_argument("--checkpoint", type=Path, default=None, help="model whose VAE makes the round trip (default: "
                    "the shipped base model)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--label", default=None, help="section name suffix in docs/benchmarks.md")
    ap.add_argument("--note", default="", help="a sentence on the sets for the table's note")
    ap.add_argument("--write", action="store_true")
    ap.add_argument("--strip", type=Path, default=None, help="image of clips and their VAE round trips")
    ap.add_argument("--strip-clips", type=int, default=3, help="dynamic clips in --strip")
    args = ap.parse_args()
    device = resolve_device(args.device)
    torch.set_num_threads(1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model, _ = load_model(args.checkpoint)
    vae = model.vae.to(device).eval()
    cfg = model.config
    clips = [clip for root in args.data for clip in held_out_clips(root, cfg.height, cfg.width, cfg.num_frames, None)]
    frames = {}
    with torch.no_grad():
        for i, clip in enumerate(clips):
            video = clip["video"].to(device)
            frames[i, "true"] = video.transpose(0, 1)
            decoded = vae.decode_latents(vae.encode_latents(video[None] * 2 - 1))[0]
            frames[i, "vae"] = ((decoded + 1) / 2).clamp(0, 1).transpose(0, 1)
    dynamic = [i for i, c in enumerate(clips) if bool(c["dynamic"])]
    static = [i for i, c in enumerate(clips) if not bool(c["dynamic"])]
    if args.strip is not None:
        moving = sorted(dynamic, key=lambda i: -float(clips[i]["tracks"].diff(dim=1).norm(dim=-1).sum(1).mean()))
        save_strip(args.strip, {f"{kind} {i}": frames[i, source].permute(0, 2, 3, 1).cpu()
                                for i in moving[:args.strip_clips] for kind, source in (("clip", "true"),
                                                                                         ("VAE", "vae"))},
                   columns=9, scale=2)
    rows = []
    for label, source, up, preset, fb, gate in VARIANTS:
        results = {i: clip_motion(clips[i], frames[i, source], up, preset, fb, gate) for i in range(len(clips))}
        metrics = {i: r[0] for i, r in results.items()}

        def mean(key: str, which: list[int], metrics: dict = metrics) -> float:
            values = [metrics[i][key] for i in which if metrics[i][key] == metrics[i][key]]  # NaN: no visible pair
            return statistics.fmean(values) if values else float("nan")

        epe, hold = mean("motion_disp_epe", dynamic), mean("motion_disp_hold", dynamic)
        ms = 1000 * statistics.fmean(r[1] for r in results.values())
        rows.append([label, f"{up}", preset, f"{fb:g}", f"{gate:g}", f"{epe:.3f}", f"{epe / hold:.2f}",
                     f"{mean('motion_disp_d5', dynamic):.2f} / {mean('motion_disp_d10', dynamic):.2f}",
                     f"{1000 * mean('motion_disp_epe', static):.1f}", f"{ms:.0f}"])
        print(" | ".join(rows[-1]), flush=True)
    hold_row = (f"holding still: displacement error {hold:.3f} m, δ 5 / 10 cm "
                f"{mean('motion_disp_hold_d5', dynamic):.2f} / {mean('motion_disp_hold_d10', dynamic):.2f}")
    table = markdown_table(["variant", "upsample", "DIS preset", "fb tolerance (px)", "gate (px)",
                            "displacement error (m)", "× holding still", "δ 5 / 10 cm", "static clips (mm)",
                            "ms per clip"], rows)
    sets = ", ".join(str(d) for d in args.data)
    publish(f"flow_motion_{args.label or args.data[0].name}", f"Scene flow from optical flow and true depth "
            f"({sets}: {len(dynamic)} dynamic, {len(static)} static clips)", f"{args.note} Dynamic clips' {hold_row}. "
            "Frames 'true' unless the variant says VAE round trip; depth always the true depth (the route's upper "
            "bound).".strip(), table, args.write)


if __name__ == "__main__":
    main()
