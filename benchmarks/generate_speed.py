"""Wall time of `generate` per stage (default model config, CPU): median over repeats.

    python benchmarks/generate_speed.py [--frames 17] [--repeats 5] [--resolution PX] [--config NAME] [--write]

Stages of the pipeline at the output resolution (default 256, as ``generate``), and the wall time of the whole
command ``diff4splat generate examples/chelsea.png --out DIR`` as a user runs it (a fresh process: imports and
model loading included; median of 3).

``--write`` puts the table into docs/benchmarks.md (section ``generate_speed``).
"""
from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine, markdown_table, peak_rss_mb, repo_relative, write_section  # noqa: E402

from diff4splat.io import load_image  # noqa: E402
from diff4splat.io.scene_folder import write_scene_folder  # noqa: E402
from diff4splat.pipeline import DEFAULT_RESOLUTION, Diff4SplatPipeline, load_model  # noqa: E402
from diff4splat.render import rasterize  # noqa: E402
from diff4splat.render.sequence import render_path  # noqa: E402
from models.bundle import DEFAULT_CONFIG  # noqa: E402

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "chelsea.png"


def render_split(res, repeats: int) -> dict[str, float]:
    """Median ms of the render stage's parts: ``scene.at`` for every frame time, and the rasterize calls of
    :func:`render_path` on those precomputed Gaussians."""
    cams, scene = res.cameras, res.scene
    bg = torch.tensor([res.background])
    deform, raster = [], []
    for _ in range(repeats + 1):
        t0 = time.perf_counter()
        frames = [scene.at(float(t)) for t in cams.times]
        t1 = time.perf_counter()
        with torch.no_grad():
            for i, g in enumerate(frames):
                rasterize(g.means, g.quats, g.scales, g.opacities, g.sh, cams.viewmats[i:i + 1], cams.Ks[i:i + 1],
                          cams.width, cams.height, sh_degree=g.sh_degree, backgrounds=bg, render_mode="RGB+ED",
                          eps2d=res.eps2d)
        t2 = time.perf_counter()
        deform.append(t1 - t0)
        raster.append(t2 - t1)
    n = len(cams)
    return {f"deformation alone ({n} × scene.at)": 1000 * statistics.median(deform[1:]),
            f"rasterizer alone ({n} calls)": 1000 * statistics.median(raster[1:])}


FIRST_CALL = """
import time, torch
from diff4splat.render import rasterize
args = (torch.rand(500, 3) + torch.tensor([0, 0, 2.0]), torch.randn(500, 4), torch.full((500, 3), 0.02),
        torch.rand(500), torch.rand(500, 3), torch.eye(4)[None],
        torch.tensor([[[60.0, 0, 32], [0, 60.0, 32], [0, 0, 1]]]), 64, 64)
t0 = time.perf_counter(); rasterize(*args); t1 = time.perf_counter(); rasterize(*args); t2 = time.perf_counter()
print(1000 * ((t1 - t0) - (t2 - t1)))
"""


def first_call_ms() -> float:
    """Extra ms of the first render in a fresh process (median of 3 processes), numba's kernels cached."""
    runs = [float(subprocess.run([sys.executable, "-c", FIRST_CALL], capture_output=True, text=True,
                                 check=True).stdout.split()[-1]) for _ in range(3)]
    return statistics.median(runs)


def command_wall_s(resolution: int) -> list[float]:
    """Wall seconds of 3 runs of ``diff4splat generate`` on the example in fresh processes."""
    runs = []
    for _ in range(3):
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            subprocess.run(["diff4splat", "generate", str(EXAMPLE), "--out", f"{tmp}/o", "--quiet", "--resolution",
                            str(resolution)], check=True, capture_output=True)
            runs.append(time.perf_counter() - t0)
    return runs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=17)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--config", default=DEFAULT_CONFIG, help=f"model config (default: {DEFAULT_CONFIG})")
    ap.add_argument("--resolution", type=int, default=DEFAULT_RESOLUTION)
    ap.add_argument("--write", action="store_true")
    args = ap.parse_args()

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model, source = load_model(None, args.config)
    source = repo_relative(source)
    pipe = Diff4SplatPipeline(model)
    cfg = pipe.config
    width, height = pipe.output_size(args.resolution)
    image = load_image(EXAMPLE, size=(height, width))
    cams = pipe.default_cameras("orbit", args.frames, resolution=args.resolution)
    stages: dict[str, list[float]] = {}
    for r in range(args.repeats + 1):  # first run is warm-up
        res = pipe(image, cams, "a cat turns its head", seed=r)
        t0 = time.perf_counter()
        colors, depths, alphas = render_path(res.scene, res.cameras, eps2d=res.eps2d, background=res.background)
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
    split = render_split(res, args.repeats)
    render_ms = 1000 * statistics.median(stages["render"])
    split_rows = [[k, f"{v:.1f}"] for k, v in split.items()] + [
        ["render stage ÷ rasterizer alone", f"{render_ms / split['rasterizer alone (17 calls)']:.2f}×"]]
    first = first_call_ms()
    wall = command_wall_s(args.resolution)
    body = (f"### `generate` wall time per stage ({args.config}, output {width}×{height}, model "
            f"{cfg.width}×{cfg.height}, {args.frames} frames, "
            f"{cfg.sampling.steps} Euler steps, {res.scene.num_gaussians} Gaussians, weights: {source})\n\n"
            f"The whole command `diff4splat generate examples/chelsea.png --out DIR` (default resolution, a fresh "
            f"process: imports and model loading included): **{statistics.median(wall):.2f} s** wall, median of 3 "
            f"({min(wall):.2f}–{max(wall):.2f} s).\n\n"
            f"Stages: median of {args.repeats} runs after a warm-up; `python benchmarks/generate_speed.py --write`. "
            f"Machine: {machine()}. Peak RSS {peak_rss_mb():.0f} MiB.\n\n"
            + markdown_table(["stage", "ms"], rows)
            + f"\n\nThe render stage ({render_ms:.1f} ms, `render_path`) split: the deformation to each frame's "
            f"time alone, and the rasterizer alone on those precomputed Gaussians (the same calls), medians of "
            f"{args.repeats}:\n\n" + markdown_table(["part", "ms"], split_rows)
            + f"\n\nNot in the table (the warm-up run takes it): the first render in a new process costs "
            f"{first:.0f} ms more than the next one (importing numba and loading its cached kernels).")
    print(body)
    if args.write:
        write_section("generate_speed", body)


if __name__ == "__main__":
    torch.manual_seed(0)
    main()
