"""``diff4splat evaluate --checkpoint DIR --data DIR [--random] [--per-clip] [--drags K] [--sampling] [--csv FILE]
[--quiet]``: the command over :mod:`training.evaluate` (registered through the ``diff4splat.commands`` entry point).
Every argument, the ``--photo`` and every CSV output (:mod:`training.eval_csv`) are checked before any model loads.
It prints the per-clip table, the headline metrics, the depth and motion splits, the model beside its baselines per
view-angle bin, and its gap over each with a bootstrap interval over clips.
"""
from __future__ import annotations

import math
import warnings
from pathlib import Path

from diff4splat.generate import memory_estimate
from diff4splat.io.image import read_image
from diff4splat.io.inputs import check_input_file, check_input_folder
from diff4splat.pipeline import DEFAULT_RESOLUTION, Diff4SplatPipeline, load_model
from diff4splat.utils.checks import check_int, check_positive_int
from diff4splat.utils.devices import AUTO, DEVICE_HELP, resolve_device
from diff4splat.utils.limits import check_limit, check_memory
from models.bundle import DEFAULT_CONFIG

from .eval_csv import append_csv, check_csv_outputs, csv_outputs
from .eval_metrics import ANGLE_BINS, BOOTSTRAP_DRAWS, BOOTSTRAP_INTERVAL, gap_intervals
from .evaluate import (
    BASELINES,
    DEPTH_DIAGNOSTICS,
    DIAGNOSTICS,
    DIRECTION,
    METRICS,
    PHOTO_KEYS,
    VARIANTS,
    ClipEvaluation,
    aggregate,
    binned_keys,
    evaluate_all,
    held_out_clips,
    photo_fidelity,
    sampling_tradeoffs,
)

__all__ = ["register", "run", "CLIP_COLUMNS", "SAMPLING_COLUMNS"]


def _cell(value: object) -> str:
    """A table cell: floats to 4 significant digits, "—" for NaN."""
    if isinstance(value, float):
        return "—" if math.isnan(value) else f"{value:.4g}"
    return str(value)


def _print_table(rows: list[dict], header: list[str]) -> str:
    """A Markdown table of ``rows`` under ``header``."""
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    for r in rows:
        lines.append("| " + " | ".join(_cell(r[h]) for h in header) + " |")
    return "\n".join(lines)


_VARIANT_LABELS = {"model": "model (sampled latents)", "noise": "noise latents (ablation)",
                   "gt": "true-video latents (oracle)", "video": "generated video, decoded (no 3D)",
                   "repeat": "repeat frame 0", "repeat_blur": "repeat frame 0, blurred"}

_BIN_LABELS = {name: f"{lo:g}–{hi:g}°" for name, lo, hi in ANGLE_BINS}
"""Column label of each view-angle bin of :data:`training.eval_metrics.ANGLE_BINS`."""

CLIP_COLUMNS = ("clip", "dynamic", "max_angle", "psnr_novel", *VARIANTS, "disp_epe", "disp_hold")
"""Columns of a row of :func:`_per_clip_rows` (``--per-clip``)."""
SAMPLING_COLUMNS = ("sampler", "nfe", "steps", "ms", "latent_rms", "psnr")
"""Columns of a row of :func:`sampling_tradeoffs` (``--sampling``)."""


def _per_clip_rows(evals: list[ClipEvaluation]) -> list[dict]:
    """One row of :data:`CLIP_COLUMNS` per clip."""
    return [dict(zip(CLIP_COLUMNS, (e.name, "dynamic" if e.dynamic else "static", e.max_angle,
                                    e.metrics["psnr_novel"], *(e.metrics[f"psnr_novel_{v}"] for v in VARIANTS),
                                    e.metrics["motion_disp_epe"], e.metrics["motion_disp_hold"]), strict=True))
            for e in evals]


def _aggregate_tables(agg: dict) -> str:
    """The headline, depth, motion and per-bin baseline tables of the aggregate row."""
    metrics = _print_table([agg], ["model", "clips", *METRICS])
    if "photo_psnr" in agg:
        metrics += "\n\nThe photograph at the input view (output resolution, and area-averaged to the model's):\n"
        metrics += _print_table([agg], list(PHOTO_KEYS))
    depth = _print_table([agg], ["depth_corr", *DEPTH_DIAGNOSTICS])
    motion = _print_table([agg], ["motion_epe", *DIAGNOSTICS])
    direction = _print_table([agg], ["direction_clips", *DIRECTION])
    bins = {name: f"{_BIN_LABELS[name]} ({int(agg[f'frames_{name}'])} frames)" for name, _, _ in ANGLE_BINS}
    rows = []
    for v in ("model", *VARIANTS):
        suffix = "" if v == "model" else f"_{v}"
        rows.append({"novel views, PSNR dB": _VARIANT_LABELS[v], "mean of clips": agg[f"psnr_novel{suffix}"],
                     "all frames, pooled": agg[f"psnr_pooled{suffix}"],
                     **{bins[name]: agg[f"psnr_{name}{suffix}"] for name, _, _ in ANGLE_BINS}})
    versus = _print_table(rows, ["novel views, PSNR dB", "mean of clips", "all frames, pooled", *bins.values()])
    return (f"{metrics}\n\nDepth (rendered against true, covered valid pixels):\n{depth}\n\nMotion (metres):\n"
            f"{motion}\n\nDirection test (dynamic clips whose caption names one direction: the fraction moved the "
            f"named way and the mean displacement along it, metres, with the caption and with it flipped):\n"
            f"{direction}\n\nNovel views beside the baselines; by view angle from the input camera, the PSNR of the "
            f"mean MSE over the bin's frames of all clips:\n{versus}")


def _gap_table(evals: list[ClipEvaluation]) -> str:
    """The model's PSNR gap over each variant with :func:`training.eval_metrics.gap_intervals` (variants with NaN
    frames, e.g. the true latents of an ONNX export, left out)."""
    model, angles = [e.frame_mse["model"] for e in evals], [e.angles for e in evals]
    others = {v: [e.frame_mse[v] for e in evals] for v in VARIANTS}
    gaps = {v: gap_intervals(model, other, angles) for v, other in others.items()
            if not any(bool(o.isnan().any()) for o in other)}
    clips = {name: n for name, (*_, n) in gaps["repeat"].items()}  # the same for every variant: the angles' bins
    header = {name: f"{_BIN_LABELS.get(name, 'all frames')} ({n} clip{'' if n == 1 else 's'})"
              for name, n in clips.items()}
    rows = [{"model minus": _VARIANT_LABELS[v],
             **{header[name]: "—" if math.isnan(g) else f"{g:+.2f} [{lo:+.2f}, {hi:+.2f}]"
                for name, (g, lo, hi, _) in by_bin.items()}} for v, by_bin in gaps.items()]
    lo, hi = BOOTSTRAP_INTERVAL
    return (f"The model's PSNR minus each variant's, dB, pooled over the frames (all, and by view angle), with the "
            f"{round(100 * lo)}–{round(100 * hi)} % interval of {BOOTSTRAP_DRAWS} bootstrap resamplings of the clips:\n"
            + _print_table(rows, ["model minus", *header.values()]))


def _check_args(args) -> dict:
    """Every check that needs no model; returns the CSV outputs (:func:`training.eval_csv.csv_outputs`), checked.
    Raises ValueError naming the flag (``--random`` with ``--checkpoint``, ``--prompt`` without ``--photo``, a bad
    count or ``--drags`` below 0, an undecodable photo, an unappendable CSV, a ``--data`` that is a file, FIFO or
    symlink loop), FileNotFoundError for a missing ``--photo`` or ``--data``."""
    check_input_folder(args.data, "--data")
    if args.random and args.checkpoint is not None:
        raise ValueError(f"--random evaluates the untrained model; --checkpoint {args.checkpoint} would be ignored "
                         "(give one of them)")
    if args.prompt and args.photo is None:
        raise ValueError("--prompt is used with --photo (the held-out clips have their own captions); give --photo")
    check_int("--drags", args.drags, 0)
    for name in ("limit", "frames", "steps", "resolution", "sampling_clips"):
        value = getattr(args, name)
        if value is not None:
            check_positive_int("--" + name.replace("_", "-"), value)
            if name in ("frames", "steps", "resolution"):
                check_limit(name, value, f"--{name}")
    if args.photo is not None:
        check_input_file(args.photo, "--photo")
        try:
            read_image(args.photo)  # decoded once now: an undecodable photo fails before the evaluation
        except ValueError as e:
            raise ValueError(f"--photo: {e}") from None
    if not args.csv:
        return {}
    columns = ["model", "clips", *METRICS, *DIAGNOSTICS, *DEPTH_DIAGNOSTICS, *BASELINES, "direction_clips", *DIRECTION,
               *binned_keys()]
    columns += list(PHOTO_KEYS) if args.photo is not None else []
    outputs = csv_outputs(Path(args.csv), columns, ["model", *CLIP_COLUMNS] if args.per_clip else None,
                          ["model", *SAMPLING_COLUMNS] if args.sampling else None)
    check_csv_outputs(outputs)
    return outputs


def run(args) -> int:
    """``diff4splat evaluate``. Raises ValueError (a missing device, a bad argument or output, no clips) and
    LimitError (a clip or the ``--photo`` scene needing more memory than allowed) before any clip loads."""

    device = resolve_device(args.device, "--device")  # before any model is loaded
    outputs = _check_args(args)  # refuse before the evaluation runs, not after
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model, source = load_model(args.checkpoint, args.config, seed=args.seed, untrained=args.random)
    pipe = Diff4SplatPipeline(model, device=device)
    cfg = pipe.config
    frames = args.frames or cfg.num_frames
    check_memory(memory_estimate(pipe, cfg.width, cfg.height, frames), f"{frames} frames at {cfg.width}×{cfg.height}",
                 "--frames")
    if args.photo is not None:
        width, height = pipe.output_size(args.resolution)
        check_memory(memory_estimate(pipe, width, height, cfg.num_frames),
                     f"--photo at {width}×{height}, {cfg.num_frames} frames", "--resolution")
    clips = held_out_clips(args.data, cfg.height, cfg.width, frames, args.limit)
    if not clips:
        raise ValueError(f"--data: no clips in {args.data}")
    evals = evaluate_all(pipe, clips, steps=args.steps, drags=args.drags, progress=not args.quiet)
    row = {"model": source, "clips": len(clips), **aggregate(evals)}
    if args.photo is not None:
        row.update(photo_fidelity(pipe, args.photo, args.prompt, resolution=args.resolution, steps=args.steps))
    per_clip = _per_clip_rows(evals)
    if args.per_clip:
        print(_print_table(per_clip, list(CLIP_COLUMNS)) + "\n")
    n_dyn = sum(e.dynamic for e in evals)
    print(f"{len(evals)} clips ({n_dyn} dynamic, {len(evals) - n_dyn} static); largest view angle per clip "
          f"{min(e.max_angle for e in evals):.1f}–{max(e.max_angle for e in evals):.1f}°\n")
    print(_aggregate_tables(row))
    print("\n" + _gap_table(evals))
    if "aggregate" in outputs:
        path, columns = outputs["aggregate"]
        append_csv(path, {k: row[k] for k in columns})
    for r in per_clip if "clips" in outputs else []:
        append_csv(outputs["clips"][0], {"model": source, **r})
    if args.sampling:
        rows = sampling_tradeoffs(pipe, clips[: args.sampling_clips])
        print(_print_table(rows, list(SAMPLING_COLUMNS)))
        for r in rows if "sampling" in outputs else []:
            append_csv(outputs["sampling"][0], {"model": source, **r})
    return 0


def register(subparsers) -> None:
    """Add the ``evaluate`` subcommand to ``diff4splat``'s CLI (entry point ``diff4splat.commands``)."""
    e = subparsers.add_parser("evaluate", help="evaluate a model on held-out scenes",
                              description="Image, depth and motion metrics on held-out scenes beside no-model "
                                          "baselines and latent ablations; sampler error vs NFE.")
    e.add_argument("--checkpoint", type=Path, default=None, help="model folder (default: shipped weights)")
    e.add_argument("--random", action="store_true", help="evaluate the seeded random (untrained) model")
    e.add_argument("--config", default=DEFAULT_CONFIG,
                   help=f"config of the shipped/random model (default: {DEFAULT_CONFIG})")
    e.add_argument("--seed", type=int, default=0, help="seed of the random model (default: 0)")
    e.add_argument("--data", type=Path, required=True, help="held-out dataset root (data_prep format)")
    e.add_argument("--frames", type=int, default=None, help="clip length T = 1 + 4k (default: config)")
    e.add_argument("--steps", type=int, default=None, help="sampler steps (default: config)")
    e.add_argument("--limit", type=int, default=None, help="evaluate at most this many clips")
    e.add_argument("--per-clip", action="store_true",
                   help="also print a table per clip (dynamic, largest view angle, model vs baselines, motion)")
    e.add_argument("--drags", type=int, default=0, metavar="K",
                   help="also generate each clip with K drags per moving object taken from its true tracks "
                        "(motion_disp_epe_drag, δ5cm/δ10cm; default 0: not)")
    e.add_argument("--sampling", action="store_true", help="also measure sampler error vs NFE")
    e.add_argument("--sampling-clips", type=int, default=4, help="clips used for the sampling sweep")
    e.add_argument("--photo", type=Path, default=None,
                   help="also report photo_psnr: the render at the input camera, t = 0, against this photograph")
    e.add_argument("--prompt", default="", help="prompt used with --photo")
    e.add_argument("--resolution", type=int, default=DEFAULT_RESOLUTION,
                   help=f"output height in pixels of the --photo scene (default {DEFAULT_RESOLUTION})")
    e.add_argument("--device", default=AUTO, help=DEVICE_HELP + "; where the model generates and renders "
                   "(metrics are computed on the CPU)")
    e.add_argument("--quiet", action="store_true", help="no progress bar")
    e.add_argument("--csv", type=Path, default=None,
                   help="append the aggregate row to this CSV (--per-clip: clip rows to <stem>_clips.csv; --sampling: "
                        "sampler rows to <stem>_sampling.csv)")
    e.set_defaults(func=run)
