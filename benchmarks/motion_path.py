"""The LDRM's motion path on held-out synthetic clips (issue 58): displacement error from frame 0 against holding
still, from the true video's latents and from generated ones, on dynamic clips; spurious motion on static clips.

For each clip the pipeline builds the scene twice, from the clip's own latents (VAE-encoded, no sampling) and from
latents it samples with the clip's caption as the prompt; the photo layer's points at the tracks' frame-0 pixels are
followed through the scene (:func:`training.evaluate.scene_motion`). Reported per set, means over clips: the
displacement error (m) and the same for holding still, its ratio, EPE3D (m, absolute positions), δ5cm / δ10cm of the
displacement (TAPVid-3D's thresholds), the ratio and δ over every valid frame-0 pixel (the clips' ``pixel_tracks``:
dense scene flow, ``flow_disp_*``), and on static clips the mean predicted displacement (mm), at the tracks and at
every pixel:

    python benchmarks/motion_path.py --data data/synth_heldout --checkpoint runs/x/model [--direction] [--write SECTION]

``--direction`` adds the direction test (:mod:`training.direction_test`): on each dynamic clip whose caption names
one direction, the scene from the true latents, and from sampled ones with the caption and with its direction flipped;
then, link by link, what the chain holds before the LDRM: the two decoded sampled videos and the true latents'
decoding, each read by ``reconstruct`` (:meth:`Diff4SplatPipeline.reconstruct`, the classical route of
docs/DESIGN.md, no prompt): the DiT's motion and the VAE's; and, as the test's control (motion that is certainly
there), ``reconstruct`` of the clip's own frames; and, without sampling, whether the DiT's flow-matching error over
the moving object's cells is lower with the caption than with its direction flipped (:func:`text_use`). A set for
it: ``data_prep synth --static-ratio 0 --motions translate --max-movers 1`` (every caption names one direction).
``--latents ''`` leaves out the motion table.

``--write`` puts the table in docs/benchmarks.md under ``motion_path_<SECTION>``.
"""
from __future__ import annotations

import argparse
import math
import shlex
import sys
from functools import partial
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import markdown_table, save_strip, write_section  # noqa: E402

from diff4splat.pipeline import Diff4SplatPipeline, GenerationResult  # noqa: E402
from training.direction_test import direction_query, flip_direction, named_way_score  # noqa: E402
from training.evaluate import (  # noqa: E402
    clip_inputs,
    decoded_video,
    held_out_clips,
    pixel_positions,
    scene_motion,
)
from training.losses import flow_matching_errors, moving_cells  # noqa: E402


def clip_scene(pipe: Diff4SplatPipeline, clip: dict, latents: str, steps: int | None, prompt: str | None = None):
    """``clip``'s generation from its ``latents`` ("true": VAE-encoded; "generated": sampled with ``prompt``, default
    the clip's caption; "frames": ``reconstruct`` of the clip's frames, no prompt)."""
    if latents == "frames":
        return read_video(pipe, clip, None)
    cams, image = clip_inputs(pipe, clip)
    video_latents = None
    if latents == "true":
        video_latents = pipe.runtime.encode_image(clip["video"][None].to(pipe.device) * 2 - 1)
    prompt = clip["caption"] if prompt is None else prompt
    return pipe(image, cams, prompt, steps=steps, video_latents=video_latents)


def read_video(pipe: Diff4SplatPipeline, clip: dict, video: torch.Tensor | None) -> GenerationResult:
    """``reconstruct``'s scene (the classical route, no prompt) of ``video`` (3, T, H, W) colours in [0, 1] along
    ``clip``'s cameras; None: the clip's own frames."""
    frames = (clip["video"] if video is None else video).permute(1, 2, 3, 0)
    return pipe.reconstruct(frames, clip_inputs(pipe, clip)[0])


def clip_motion(pipe: Diff4SplatPipeline, clip: dict, latents: str, steps: int | None) -> dict[str, float]:
    """:func:`scene_motion` of ``clip``'s scene from its ``latents`` (:func:`clip_scene`)."""
    res = clip_scene(pipe, clip, latents, steps)
    out = scene_motion(pipe, res, clip)
    out["deformed"] = float(res.scene.d_means is not None)
    return out


def direction_rows(pipe: Diff4SplatPipeline, clips: list[dict], steps: int | None, strip: Path | None = None,
                   strip_clips: int = 2) -> tuple[list[list], str]:
    """The direction test (:mod:`training.direction_test`) on the dynamic clips whose caption names one direction:
    per variant the clips moved the named way and the mean displacement along the named axis times its sign
    (metres); and a sentence on how far the flip reaches the generated video (the mean absolute colour difference
    of the two decoded videos, frames 1…, per clip). The variants follow the chain link by link: the scene
    ``generate`` builds from the true latents and from sampled ones (caption, flipped caption); the decoded sampled
    videos read by ``reconstruct`` (the DiT's motion without the LDRM's); the decoded true latents read by
    ``reconstruct`` (what the VAE keeps of the motion); and the control, ``reconstruct`` of the clip's frames.
    ``strip``: an image of the first ``strip_clips`` taking-part clips, nine frames each of the clip, its decoded
    generated videos with the caption and flipped, and its true latents' decoding (rows, enlarged 2×)."""
    names = ("true latents, caption", "generated, caption", "generated, flipped caption",
             "generated video read by `reconstruct`, caption", "generated video read by `reconstruct`, flipped",
             "true latents' decoding read by `reconstruct` (the VAE's bound)",
             "the clip's frames (`reconstruct`, control)")
    tally: dict[str, list] = {name: [] for name in names}
    changes, looked = [], {}
    for clip in clips:
        query = direction_query(clip)
        if query is None:
            continue
        axis, sign, moving = query
        true, gen, flip = (clip_scene(pipe, clip, latents, steps, prompt)
                           for latents, prompt in zip(("true", "generated", "generated"),
                                                      (None, None, flip_direction(clip["caption"])), strict=True))
        videos = [decoded_video(pipe, res) for res in (gen, flip, true)]
        scenes = [true, gen, flip, *(read_video(pipe, clip, v) for v in videos), read_video(pipe, clip, None)]
        for name, scene, s in zip(names, scenes, (sign, sign, -sign, sign, -sign, sign, sign), strict=True):
            tally[name].append(named_way_score(*pixel_positions(scene), moving, axis, s))
        changes.append(float((videos[0] - videos[1])[:, 1:].abs().mean()))
        if strip is not None and len(looked) < 4 * strip_clips:
            k = len(looked) // 4
            for label, v in zip(("frames", "caption", "flipped", "VAE"), (clip["video"], *videos), strict=True):
                looked[f"{k}: {label}"] = v.permute(1, 2, 3, 0).float().cpu()
    if looked:
        save_strip(strip, looked, columns=9, scale=2)
    rows = [[name, len(v), f"{sum(ok for ok, _ in v) / max(1, len(v)):.2f}",
             f"{sum(d for _, d in v) / max(1, len(v)):+.4f}"] for name, v in tally.items()]
    reach = (f"Flipping the caption's direction changes the decoded generated video (frames 1…) by a mean absolute "
             f"colour of {min(changes):.4f}–{max(changes):.4f} (mean {sum(changes) / len(changes):.4f}; identical "
             f"in {sum(c == 0 for c in changes)} of {len(changes)} clips)." if changes else "")
    return rows, reach


def text_use(pipe: Diff4SplatPipeline, clips: list[dict], draws: int = 16) -> str:
    """A sentence on whether the DiT reads the direction word, without sampling: on each taking-part clip, its
    flow-matching error (:func:`training.losses.flow_matching_errors`) over the latent cells the moving object covers
    (:func:`training.losses.moving_cells`) at the clip's true latents, with the caption, with its direction flipped
    and with no prompt, the same ``draws`` (σ ~ U(0.05, 0.95), ε) for the three. A DiT that reads the word predicts
    the object's motion better with the caption in most clips; one that does not, in about half."""
    runtime = pipe.runtime
    errors = []
    for clip in clips:
        if direction_query(clip) is None:
            continue
        cams, _ = clip_inputs(pipe, clip)
        latents = runtime.encode_image(clip["video"][None].to(pipe.device) * 2 - 1)  # (1, c, n, h, w)
        cells = moving_cells(clip["pixel_tracks"][None], clip["pixel_track_valid"][None], clip["viewmats"][None],
                             clip["Ks"][None], tuple(latents.shape[2:]), runtime.latent.temporal_factor)
        if not bool(cells.any()):
            continue
        cells = cells.to(latents.device)
        plucker = pipe.packed_plucker(cams)
        gen = torch.Generator().manual_seed(0)
        noise = [torch.randn(latents.shape, generator=gen).to(latents) for _ in range(draws)]
        sigmas = [(0.05 + 0.9 * torch.rand(1, generator=gen)).to(latents) for _ in range(draws)]
        row = []
        for prompt in (clip["caption"], flip_direction(clip["caption"]), ""):
            text, mask = runtime.encode_text(prompt) if prompt or runtime.encodes_empty_prompt else (None, None)
            velocity = partial(runtime.velocity, image_latent=latents[:, :, :1], plucker=plucker, text=text,
                               text_mask=mask)
            err = sum(float(flow_matching_errors(velocity, latents, e, sig).mean(1)[cells].mean())
                      for e, sig in zip(noise, sigmas, strict=True))
            row.append(err / draws)
        errors.append(row)
    if not errors:
        return ""
    mean = [sum(r[k] for r in errors) / len(errors) for k in range(3)]
    lower = sum(r[0] < r[1] for r in errors)
    return (f"The DiT's flow-matching error over the moving object's latent cells, at the true latents ({draws} "
            f"draws of σ and ε per clip): {mean[0]:.4f} with the caption, {mean[1]:.4f} with its direction flipped, "
            f"{mean[2]:.4f} with no prompt; the caption's is the lower in {lower} of {len(errors)} clips.")


def _mean(rows: list[dict[str, float]], key: str) -> float:
    vals = [r[key] for r in rows if not math.isnan(r[key])]
    return sum(vals) / len(vals) if vals else float("nan")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True)
    ap.add_argument("--checkpoint", default=None, help="model folder (default: the shipped weights)")
    ap.add_argument("--limit", type=int, default=None)
    ap.add_argument("--steps", type=int, default=None)
    ap.add_argument("--latents", default="true,generated", help="the motion table's rows ('': none)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--write", default=None, help="section suffix in docs/benchmarks.md")
    ap.add_argument("--direction", action="store_true", help="also the direction test (training.direction_test)")
    ap.add_argument("--strip", type=Path, default=None, help="with --direction: an image of clips and their videos")
    args = ap.parse_args()
    torch.manual_seed(0)
    pipe = Diff4SplatPipeline.from_pretrained(args.checkpoint, device=args.device)
    cfg = pipe.config
    clips = held_out_clips(args.data, cfg.height, cfg.width, cfg.num_frames, args.limit)
    rows = []
    for which in [w for w in args.latents.split(",") if w]:
        per = {True: [], False: []}
        with torch.no_grad():
            for clip in clips:
                per[bool(clip["dynamic"])].append(clip_motion(pipe, clip, which, args.steps))
        dyn, sta = per[True], per[False]
        disp, hold = _mean(dyn, "motion_disp_epe"), _mean(dyn, "motion_disp_hold")
        rows.append([which, len(dyn), f"{disp:.4f}", f"{hold:.4f}", f"{disp / hold:.3f}",
                     f"{_mean(dyn, 'motion_epe'):.4f}",
                     f"{_mean(dyn, 'motion_disp_d5'):.3f} / {_mean(dyn, 'motion_disp_d10'):.3f}",
                     f"{_mean(dyn, 'motion_disp_hold_d5'):.3f} / {_mean(dyn, 'motion_disp_hold_d10'):.3f}",
                     f"{_mean(dyn, 'flow_disp_epe') / _mean(dyn, 'flow_disp_hold'):.3f}",
                     f"{_mean(dyn, 'flow_disp_d5'):.3f} / {_mean(dyn, 'flow_disp_d10'):.3f}",
                     f"{_mean(dyn, 'flow_disp_hold_d5'):.3f} / {_mean(dyn, 'flow_disp_hold_d10'):.3f}",
                     len(sta), f"{1000 * _mean(sta, 'motion_disp_epe'):.2f}",
                     f"{1000 * _mean(sta, 'flow_disp_epe'):.2f}", f"{sum(r['deformed'] for r in sta):.0f}"])
    head = ["latents", "dynamic clips", "displacement error (m)", "holding still (m)", "ratio", "EPE3D (m)",
            "δ5cm / δ10cm", "δ holding still", "every pixel: ratio", "every pixel: δ5cm / δ10cm",
            "every pixel: δ holding still", "static clips", "static: mean displacement (mm)",
            "static, every pixel (mm)", "static scenes with deformation"]
    table = markdown_table(head, rows) if rows else ""
    if args.direction:
        with torch.no_grad():
            rows, reach = direction_rows(pipe, clips, args.steps, args.strip)
            table += "\n\n" * bool(table) + "Direction test (`training.direction_test`):\n\n" + markdown_table(
                ["scene from", "clips", "moved the named way", "mean displacement along it (m)"], rows)
            table += f"\n\n{reach}" if reach else ""
            use = text_use(pipe, clips)
            table += f"\n\n{use}" if use else ""
    print(table)
    if args.write:
        cmd = shlex.join(["python", "benchmarks/motion_path.py", *sys.argv[1:]])
        write_section(f"motion_path_{args.write}", f"`{cmd}` (device: {args.device})\n\n{table}")


if __name__ == "__main__":
    main()
