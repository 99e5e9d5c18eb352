"""Wall time of `generate` per stage (default model config, CPU): median over repeats.

    python benchmarks/generate_speed.py [--frames 17] [--repeats 5] [--config NAME] [--write]

``--write`` puts the table into docs/benchmarks.md (section ``generate_speed``).
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
from _common import machine, markdown_table, peak_rss_mb, repo_relative, write_section  # noqa: E402

from diff4splat.io import load_image  # noqa: E402
from diff4splat.io.output import write_scene_folder  # noqa: E402
from diff4splat.pipeline import Diff4SplatPipeline, load_model  # noqa: E402
from diff4splat.render.sequence import render_path  # noqa: E402
from models.bundle import DEFAULT_CONFIG  # noqa: E402

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "chelsea.png"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=17)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--config", default=DEFAULT_CONFIG, help=f"model config (default: {DEFAULT_CONFIG})")
    ap.add_argument("--write", action="store_true")
    args = ap.parse_args()

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model, source = load_model(None, args.config)
    source = repo_relative(source)
    pipe = Diff4SplatPipeline(model)
    cfg = pipe.config
    image = load_image(EXAMPLE, size=(cfg.height, cfg.width))
    cams = pipe.default_cameras("orbit", args.frames)
    stages: dict[str, list[float]] = {}
    import tempfile

    for r in range(args.repeats + 1):  # first run is warm-up
        res = pipe(image, cams, "a cat turns its head", seed=r)
        t0 = time.perf_counter()
        colors, depths, alphas = render_path(res.scene, res.cameras)
        t_render = time.perf_counter() - t0
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            write_scene_folder(Path(tmp) / "out", res.scene, res.cameras, colors, depths, alphas, {})
            t_write = time.perf_counter() - t0
        if r == 0:
            continue
        for k, v in {**res.timings, "render": t_render, "write": t_write}.items():
            stages.setdefault(k, []).append(v)
    totals = [sum(vals[i] for vals in stages.values()) for i in range(args.repeats)]
    rows = [[k, f"{1000 * statistics.median(v):.1f}"] for k, v in stages.items()]
    rows.append(["**total**", f"**{1000 * statistics.median(totals):.1f}**"])
    body = (f"### `generate` wall time per stage ({args.config}, {cfg.width}×{cfg.height}, {args.frames} frames, "
            f"{cfg.sampling.steps} Euler steps, {res.scene.num_gaussians} Gaussians, weights: {source})\n\n"
            f"Median of {args.repeats} runs after a warm-up; `python benchmarks/generate_speed.py --write`. "
            f"Machine: {machine()}. Peak RSS {peak_rss_mb():.0f} MiB.\n\n"
            + markdown_table(["stage", "ms"], rows))
    print(body)
    if args.write:
        write_section("generate_speed", body)


if __name__ == "__main__":
    torch.manual_seed(0)
    main()
