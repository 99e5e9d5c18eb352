"""Duplicate pruning across source frames: Gaussian counts and render time with and without it.

For each camera preset and seed, ``generate`` runs on the example photograph and the table reports the
Gaussians of the unpruned S·H·W grid, those :func:`diff4splat.assembly.prune.duplicate_mask` drops, those left after
it, the later-frame Gaussians that covered the photograph and slid behind it (``slid``), and those left after the
occluder and opacity/visibility pruning (``GenerationResult.prune_stats``); then the same
opacity/visibility pruning without the duplicate pruning, for comparison. Render times are medians of
:func:`diff4splat.render.sequence.render_path` over the whole path (CPU), with and without the duplicate
pruning. With a random model (no trained weights for the config) the counts show the code path working,
not what a trained LDRM's overlap is.

The pipeline applies the duplicate pruning itself (:func:`diff4splat.assembly.prune.settle_generated`) and has no switch
to turn it off, so this script intercepts ``diff4splat.assembly.prune.duplicate_mask``: it records the unpruned scene
and the source cameras the pipeline passes, calls :func:`~diff4splat.assembly.prune.duplicate_mask` on them itself
(timed), and hands the mask back to the pipeline. The scene without duplicate pruning is the recorded unpruned scene
after the pipeline's own opacity/visibility pruning (:func:`diff4splat.assembly.prune.prune_scene`,
``config.prune_opacity``).

    python benchmarks/prune_duplicates.py [--config tiny] [--checkpoint DIR | --untrained] [--seeds 0 1 2]
        [--trajectories orbit arc forward pan-left] [--repeats 3] [--write]

``--write`` puts the table into docs/benchmarks.md (section ``prune_duplicates``).
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
import warnings
from pathlib import Path
from unittest import mock

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine, markdown_table, peak_rss_mb, repo_relative, write_section  # noqa: E402

import diff4splat.assembly.prune as prune_module  # noqa: E402
from diff4splat.assembly.prune import duplicate_mask, prune_scene  # noqa: E402
from diff4splat.io import load_image  # noqa: E402
from diff4splat.pipeline import Diff4SplatPipeline, load_model  # noqa: E402
from diff4splat.render.sequence import render_path  # noqa: E402
from models.bundle import DEFAULT_CONFIG  # noqa: E402

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "chelsea.png"
HEADER = ["path", "seed", "S", "before", "duplicates", "after dup.", "slid", "after occluders, vis.+opac.",
          "without dup.: after", "dup. mask ms", "render ms", "render ms without dup.", "speed-up"]


class _Recorder:
    """Stands in for ``duplicate_mask`` inside the pipeline: calls the real one, keeps its inputs and time."""

    def __init__(self) -> None:
        self.scene = None
        self.seconds = 0.0

    def __call__(self, scene, *args, **kwargs):
        t0 = time.perf_counter()
        dup = duplicate_mask(scene, *args, **kwargs)
        self.seconds = time.perf_counter() - t0
        self.scene = scene
        return dup


def _median_render_ms(scene, cameras, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        render_path(scene, cameras)
        times.append(time.perf_counter() - t0)
    return 1000 * statistics.median(times)


def run(pipe: Diff4SplatPipeline, image: torch.Tensor, trajectory: str, seed: int, prompt: str,
        repeats: int) -> list:
    """One table row: generate with the recorder in place, then render with and without duplicate pruning."""
    rec = _Recorder()
    with mock.patch.object(prune_module, "duplicate_mask", rec):
        res = pipe(image, pipe.default_cameras(trajectory), prompt, seed=seed)
    stats, S = res.prune_stats, len(res.source_frames)
    if rec.scene is None:  # one source frame: the pipeline has nothing to deduplicate
        without = res.scene
    else:
        without, _ = prune_scene(rec.scene, res.cameras, min_opacity=pipe.config.prune_opacity)
    render_path(res.scene, res.cameras, eps2d=res.eps2d)  # warm-up
    ms_with = _median_render_ms(res.scene, res.cameras, repeats)
    ms_without = _median_render_ms(without, res.cameras, repeats)
    dups = stats.get("duplicates", 0)
    return [trajectory, seed, S, stats["before"], dups, stats["before"] - dups, stats.get("slid", 0), stats["after"],
            without.num_gaussians, f"{1000 * rec.seconds:.1f}", f"{ms_with:.1f}", f"{ms_without:.1f}",
            f"{ms_without / ms_with:.2f}×"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=DEFAULT_CONFIG, help=f"model config (default: {DEFAULT_CONFIG})")
    ap.add_argument("--checkpoint", default=None, help="checkpoint folder (default: the config's shipped weights)")
    ap.add_argument("--untrained", action="store_true", help="the seeded random model of --config")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--trajectories", nargs="+", default=["orbit", "arc", "forward", "pan-left"])
    ap.add_argument("--prompt", default="")
    ap.add_argument("--repeats", type=int, default=3, help="render repeats per scene (median)")
    ap.add_argument("--write", action="store_true")
    args = ap.parse_args()

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model, source = load_model(args.checkpoint, args.config, untrained=args.untrained)
    source = repo_relative(source)
    pipe = Diff4SplatPipeline(model)
    cfg = pipe.config
    image = load_image(EXAMPLE, size=(cfg.height, cfg.width))
    rows = [run(pipe, image, trajectory, seed, args.prompt, args.repeats)
            for trajectory in args.trajectories for seed in args.seeds]
    body = (f"### Duplicate pruning across source frames ({args.config}, {cfg.width}×{cfg.height}, "
            f"{cfg.num_frames} frames, weights: {source})\n\n"
            f"Gaussian counts per stage of the pruning, and the median of {args.repeats} `render_path` runs "
            f"(after a warm-up) of the whole path with and without the duplicate pruning; "
            f"`python benchmarks/prune_duplicates.py --write`. Machine: {machine()}. "
            f"Peak RSS {peak_rss_mb():.0f} MiB.\n\n" + markdown_table(HEADER, rows))
    print(body)
    if args.write:
        write_section("prune_duplicates", body)


if __name__ == "__main__":
    torch.manual_seed(0)
    main()
