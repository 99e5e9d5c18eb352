"""Drags on held-out synthetic clips (issue 78, ``generate --drag``): one drag per moving object taken from its true
track (:func:`training.drag_eval.true_drags`), against holding still, the networks' own motion (the caption as the
prompt, no drag) and a drag that slides the whole photograph; with the model's depth and with the clip's true depth
(``--depth``). Per set, over dynamic clips with a visible mover: the displacement error at the tracks
(:func:`training.evaluate.scene_motion`: ``motion_disp_epe`` over holding still, δ5cm/δ10cm), at every valid pixel
(``flow_disp``), at the moving pixels only, and the still pixels' mean motion (mm)::

    python benchmarks/drags.py --data data/a data/b [--checkpoint DIR] [--strip docs/img.png] [--write SECTION]

``--strip``: frames of the first two clips (truth, the scene with no drag, dragged with the model's depth) and, in
a second image, of the shipped photograph dragged along a still path. ``--write`` puts the table in
docs/benchmarks.md under ``drags_<SECTION>``.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from unittest import mock

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import markdown_table, publish, save_strip  # noqa: E402

from diff4splat.cameras import CameraPath  # noqa: E402
from diff4splat.generate import generate  # noqa: E402
from diff4splat.pipeline import Diff4SplatPipeline  # noqa: E402
from diff4splat.render.sequence import render_path  # noqa: E402
from diff4splat.request import LoadedPipeline  # noqa: E402
from training.drag_eval import moving_objects, true_drags  # noqa: E402
from training.evaluate import clip_inputs, held_out_clips, pixel_positions, scene_motion  # noqa: E402

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "chelsea.png"
VARIANTS = ("no drag (caption as prompt)", "drags, the model's depth", "drags, the true depth",
            "drags sliding the whole photograph", "oracle regions, the true depth",
            "oracle regions moved by the drag point's true 3D track")
"""The last two are ablations of the two links: the true moving objects as the regions (the drag still lifted at its
point's depth), and those regions moved by the drag point's true 3D displacement (no lift)."""


def _whole(image, depth, **kwargs):
    """One region: every pixel follows the nearest drag (the baseline)."""
    return np.zeros(image.shape[:2], np.int32)


def _oracle_motion(clip: dict):
    """A stand-in for :func:`drag_motion` that moves each true moving object by its drag point's true 3D track."""
    labels = moving_objects(clip["pixel_tracks"], clip["pixel_track_valid"])
    tracks = clip["pixel_tracks"].double()

    def motion(drags, image, depth, K, times, segments=None):
        start = drags.positions[:, 0].astype(int)  # (N, 2) x, y: the drag points' pixels
        out = torch.zeros(len(times), *labels.shape, 3, dtype=torch.float64)
        clip_times = torch.linspace(0, 1, tracks.shape[0], dtype=torch.float64)
        for x, y in start:
            region = torch.from_numpy(labels == labels[y, x])
            for k, t in enumerate(times.double().tolist()):
                at = [float(np.interp(t, clip_times.numpy(), (tracks[:, y, x, c] - tracks[0, y, x, c]).numpy()))
                      for c in range(3)]
                out[k][region] = torch.tensor(at, dtype=torch.float64)
        return out.float().to(image.device), torch.from_numpy(labels > 0).to(image.device)
    return motion


def clip_row(pipe: Diff4SplatPipeline, clip: dict, variant: str) -> tuple[dict, object]:
    """``scene_motion`` of one variant's scene of ``clip``, plus its moving-pixel and still-pixel errors."""
    cams, image = clip_inputs(pipe, clip)
    drags = true_drags(clip)
    kwargs = {} if variant.startswith("no drag") else {"drags": drags}
    if "true depth" in variant or variant.startswith("oracle"):
        kwargs.update(depth=clip["depth"][0], depth_kind="metric")
    patch = mock.patch.dict({})
    if "whole" in variant:
        patch = mock.patch("diff4splat.geometry.drags.drag_segments", _whole)
    elif variant == VARIANTS[4]:
        labels = moving_objects(clip["pixel_tracks"], clip["pixel_track_valid"])
        patch = mock.patch("diff4splat.geometry.drags.drag_segments", lambda image, depth, **kw: labels)
    elif variant == VARIANTS[5]:
        patch = mock.patch("diff4splat.assembly.drag_scene.drag_motion", _oracle_motion(clip))
    t0 = time.perf_counter()
    with patch:
        res = pipe(image, cams, clip["caption"], **kwargs)
    m = scene_motion(pipe, res, clip)
    T, H, W = clip["pixel_tracks"].shape[:3]
    pixels, kept = pixel_positions(res)  # (H·W, T, 3)
    truth = clip["pixel_tracks"].reshape(T, H * W, 3).transpose(0, 1).double()
    true_disp, disp = truth - truth[:, :1], (pixels - pixels[:, :1]).double()
    valid = clip["pixel_track_valid"].reshape(-1) & kept
    moving = valid & (true_disp.norm(dim=-1).amax(1) > 0.01)
    err = (disp - true_disp).norm(dim=-1)
    m.update(moving_epe=float(err[moving].mean()), moving_hold=float(true_disp[moving].norm(dim=-1).mean()),
             still_mm=1000 * float(disp[valid & ~moving].norm(dim=-1).mean()), seconds=time.perf_counter() - t0)
    return m, res


def _ratio(rows: list[dict], a: str, b: str) -> float:
    ok = [r for r in rows if np.isfinite(r[a]) and np.isfinite(r[b])]
    return sum(r[a] for r in ok) / sum(r[b] for r in ok)


def _mean(rows: list[dict], key: str) -> float:
    vals = [r[key] for r in rows if np.isfinite(r[key])]
    return sum(vals) / len(vals)


def photo_strip(pipe: Diff4SplatPipeline, frames: int = 9) -> dict[str, torch.Tensor]:
    """The shipped photograph along a still path at 256², without and with two drags (the nose up, the left eye
    left; pixels of the 451×300 file, whose centre 300×300 the model sees)."""
    K = pipe.default_cameras("arc", frames, resolution=256).Ks
    still = CameraPath(torch.eye(4, dtype=K.dtype).expand(frames, 4, 4).clone(), K, 256, 256,
                       torch.linspace(0, 1, frames, dtype=K.dtype))
    loaded = LoadedPipeline(pipe, "shipped")
    rows = {}
    for label, drags in (("photo, no drag", []), ("--drag 262,240:0,-40 --drag 169,117:-30,0",
                                                    ["262,240:0,-40", "169,117:-30,0"])):
        out = generate(EXAMPLE, still, pipeline=loaded, drags=drags, frame_plys=False)
        rows[label] = out.colors.cpu()
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", nargs="+", required=True, help="dataset roots (one table row group each)")
    ap.add_argument("--checkpoint", default=None, help="model folder (default: the shipped weights)")
    ap.add_argument("--limit", type=int, default=None)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--strip", type=Path, default=None)
    ap.add_argument("--write", default=None, help="section suffix in docs/benchmarks.md")
    args = ap.parse_args()
    torch.manual_seed(0)
    pipe = Diff4SplatPipeline.from_pretrained(args.checkpoint, device=args.device)
    cfg = pipe.config
    table, looked, strip_keys = [], {}, set()
    for root in args.data:
        clips = [c for c in held_out_clips(root, cfg.height, cfg.width, cfg.num_frames, args.limit)
                 if bool(c["dynamic"]) and true_drags(c) is not None]
        if args.strip and not strip_keys:  # the first two clips of the first set
            strip_keys = {f"{Path(root).name}/{c['scene']}" for c in clips[:2]}
        for variant in VARIANTS:
            rows = []
            with torch.no_grad():
                for clip in clips:
                    m, res = clip_row(pipe, clip, variant)
                    rows.append(m)
                    key = f"{Path(root).name}/{clip['scene']}"
                    if key in strip_keys and variant in VARIANTS[:2]:
                        if variant == VARIANTS[0]:
                            looked[f"{key}: truth"] = clip["video"].permute(1, 2, 3, 0).float()
                        label = "no drag" if variant == VARIANTS[0] else "dragged (model depth)"
                        looked[f"{key}: {label}"] = render_path(res.scene, res.cameras)[0].cpu()
            table.append([Path(root).name, variant, len(rows),
                          f"{_ratio(rows, 'motion_disp_epe', 'motion_disp_hold'):.3f}",
                          f"{_mean(rows, 'motion_disp_d5'):.2f} / {_mean(rows, 'motion_disp_d10'):.2f}",
                          f"{_mean(rows, 'motion_disp_hold_d5'):.2f} / {_mean(rows, 'motion_disp_hold_d10'):.2f}",
                          f"{_ratio(rows, 'flow_disp_epe', 'flow_disp_hold'):.3f}",
                          f"{_ratio(rows, 'moving_epe', 'moving_hold'):.3f}", f"{_mean(rows, 'still_mm'):.1f}",
                          f"{_mean(rows, 'seconds'):.2f}"])
    head = ["set", "motion from", "clips", "tracks: error / holding still", "δ5cm / δ10cm", "δ holding still",
            "every pixel: ratio", "moving pixels: ratio", "still pixels' motion (mm)", "s per clip"]
    text = markdown_table(head, table)
    if args.strip:
        with torch.no_grad():
            looked.update(photo_strip(pipe))
        order = ("truth", "no drag", "dragged (model depth)")
        clips_rows = sorted((k for k in looked if k.split(": ")[-1] in order),
                            key=lambda k: (k.split(": ")[0], order.index(k.split(": ")[-1])))
        save_strip(args.strip, {k: looked[k] for k in clips_rows}, columns=9, scale=3)
        photo = {k: v for k, v in looked.items() if k not in clips_rows}
        save_strip(args.strip.with_name(args.strip.stem + "_photo" + args.strip.suffix), photo, columns=5)
    publish(f"drags_{args.write}", "Drags against holding still", f"Device: {args.device}.", text, bool(args.write))


if __name__ == "__main__":
    main()
