"""Held-out PSNR of ``diff4splat fit`` against run time (4D Gaussian Splatting on this CPU).

For every scene of a held-out synthetic dataset (``data_prep synth``, a seed not used for development) and
``--holdout-camera 1`` (camera 1 never trained on), three ways to get a 4D scene:

(a) ``fit`` from the depth initialisation;
(b) ``fit`` initialised from ``generate`` (the default model run on camera 0's first frame along camera 0's
    path; Gaussians moved into the scene's world frame and scaled to its depth, ``training.fit_cli``);
(c) ``generate`` alone: the same placed Gaussians with generate's own deformation, rendered at the held-out
    frames (``PSNR at step 0`` of (b) is those Gaussians at t = 0 held still, the fit's starting point).

Each fit records the held-out PSNR (pooled MSE over all frames of camera 1; also over only its co-visible
pixels, those whose surface point a training view sees — DyCheck's mPSNR, ``holdout_masked_psnr``) every
``--eval-every`` steps
against the optimisation time (evaluation excluded), the Gaussian count, and ms per step; the wall time
includes loading, initialisation and writing the output folder.

    data_prep synth --scenes 6 --cameras 10 --seed 80808 --static-ratio 0.5 --out data/fit_eval
    pip install -e ".[bench]"   # matplotlib, for the plot
    python benchmarks/fit_tradeoffs.py --data data/fit_eval --iterations 1800 --write

writes a table and docs/fit_tradeoffs.png into docs/benchmarks.md (section ``fit_tradeoffs``). Use a fresh seed
for a new measurement: one looked at while changing the fit is development data.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine, markdown_table, write_section  # noqa: E402

from data_prep.format import list_scenes, load_scene  # noqa: E402
from diff4splat.generate import generate  # noqa: E402
from diff4splat.render import rasterize  # noqa: E402
from diff4splat.request import write  # noqa: E402
from training.eval_metrics import masked_psnr, psnr_from_mse  # noqa: E402
from training.fit import FitConfig  # noqa: E402
from training.fit_cli import place_generate_output, run_fit  # noqa: E402
from training.fit_data import covisible_masks, load_views, split_cameras  # noqa: E402

DOCS = Path(__file__).resolve().parent.parent / "docs"


def generate_for(scene_dir: Path, out: Path) -> float:
    """``diff4splat generate`` on camera 0's first frame along camera 0's path; returns seconds."""
    scene = load_scene(scene_dir)
    cam = scene.camera_names[0]
    t0 = time.perf_counter()
    write(generate(scene_dir / cam / "rgb" / "00000.png", scene_dir / cam / "cameras.json"), out)
    return time.perf_counter() - t0


def generate_alone_psnr(scene_dir: Path, gen_out: Path) -> tuple[float, float | None]:
    """(c): the generate output placed in the scene's world (``place_generate_output``, deformation included),
    rendered at every held-out frame at its time; PSNR of the pooled MSE, and over the co-visible pixels
    (``training.fit_data.covisible_masks``, as the fits' ``holdout_masked_psnr``; None without depth)."""

    scene = load_scene(scene_dir)
    placed = place_generate_output(gen_out, scene, scene.camera_names[0])
    train_names, held_names = split_cameras(scene, 1)
    held = load_views(scene, held_names)
    masks = covisible_masks(held, load_views(scene, train_names), static=not scene.meta.dynamic)
    preds = []
    with torch.no_grad():
        for v in held:
            g = placed.at(v.time)
            preds.append(rasterize(g.means, g.quats, g.scales, g.opacities, g.sh, v.viewmat[None], v.K[None],
                                   v.width, v.height, sh_degree=g.sh_degree, render_mode="RGB")[0][0].clamp(0, 1))
    pred, gt = torch.stack(preds), torch.stack([v.image for v in held])
    full = psnr_from_mse(float(((pred.double() - gt.double()) ** 2).mean()))
    return full, None if masks is None else masked_psnr(pred, gt, torch.stack(masks))


def run(data: Path, iterations: int, coarse: int, eval_every: int, names: list[str] | None, seed: int,
        with_generate: bool, json_path: Path | None = None) -> list[dict]:
    """Fit every scene (module docstring); rows are appended to ``json_path`` as they finish."""
    rows = []
    scenes = [s for s in list_scenes(data) if names is None or s.name in names]
    with tempfile.TemporaryDirectory() as tmp:
        for scene_dir in scenes:
            meta = load_scene(scene_dir).meta
            methods = [("depth init", None)]
            if with_generate and meta.dynamic:
                gen_out = Path(tmp) / f"{scene_dir.name}_gen"
                gen_s = generate_for(scene_dir, gen_out)
                gen_psnr, gen_masked = generate_alone_psnr(scene_dir, gen_out)
                methods.append(("generate init", gen_out))
            for name, init in methods:
                config = FitConfig(iterations=iterations, coarse_iterations=coarse if meta.dynamic else 0)
                m = run_fit(scene_dir, Path(tmp) / f"{scene_dir.name}_{len(rows)}", config, holdout_camera=1,
                            seed=seed, init=init, eval_every=eval_every, checkpoint_every=0)
                rows.append({"scene": scene_dir.name, "dynamic": meta.dynamic, "method": name, **m,
                             "generate_s": gen_s if init is not None else None,
                             "generate_psnr": gen_psnr if init is not None else None,
                             "generate_masked_psnr": gen_masked if init is not None else None})
                print(json.dumps({k: v for k, v in rows[-1].items() if k != "history"}), flush=True)
                if json_path is not None:
                    json_path.write_text(json.dumps(rows, indent=1))
    return rows


def _db(x) -> str:
    return "—" if x is None else f"{x:.2f}"


def tables(rows: list[dict], budgets=(30, 60, 120, 300, 600)) -> str:
    final = [[r["scene"], "dynamic" if r["dynamic"] else "static", r["method"], r["iterations"],
              f"{r['wall_time_s']:.0f}", f"{r['ms_per_iteration']:.0f}", f"{r['num_gaussians']:,}",
              f"{r['history'][0]['holdout_psnr']:.2f}" if r["history"] and r["history"][0]["step"] == 0 else "—",
              _db(r.get("generate_psnr")) + " / " + _db(r.get("generate_masked_psnr")),
              f"{r['holdout_psnr']:.2f}", _db(r.get("holdout_masked_psnr")),
              "—" if r.get("holdout_covisible") is None else f"{100 * r['holdout_covisible']:.1f} %",
              f"{r['holdout_ssim']:.3f}", f"{r['train_psnr']:.2f}"] for r in rows]
    out = markdown_table(["scene", "kind", "method", "steps", "wall s", "ms/step", "Gaussians",
                          "PSNR at step 0", "(c) generate alone: all / co-visible", "held-out PSNR",
                          "co-visible PSNR", "co-visible pixels", "SSIM", "train PSNR"], final)
    curve = []
    for r in rows:
        cells = []
        for b in budgets:
            done = [h for h in r["history"] if h["train_time_s"] <= b]
            cells.append(f"{done[-1]['holdout_psnr']:.2f} ({done[-1]['num_gaussians']:,})" if done else "—")
        curve.append([r["scene"], r["method"], *cells])
    out += "\n\nHeld-out PSNR dB (Gaussians) after a given optimisation time (evaluation excluded):\n\n"
    out += markdown_table(["scene", "method", *[f"≤ {b} s" for b in budgets]], curve)
    return out


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    for r in rows:
        h = [x for x in r["history"]]
        ax.plot([x["train_time_s"] for x in h], [x["holdout_psnr"] for x in h],
                "-" if r["method"] == "depth init" else "--", label=f"{r['scene']} {r['method']}")
    ax.set_xlabel("optimisation time, s (2-core CPU)")
    ax.set_ylabel("held-out camera PSNR, dB")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, required=True, help="held-out dataset root (data_prep synth, ≥ 2 cameras)")
    p.add_argument("--iterations", type=int, default=FitConfig().iterations)
    p.add_argument("--coarse", type=int, default=FitConfig().coarse_iterations, help="coarse steps of dynamic scenes")
    p.add_argument("--eval-every", type=int, default=250)
    p.add_argument("--scenes", nargs="*", default=None, help="scene names (default: all)")
    p.add_argument("--merge", type=Path, nargs="*", default=None,
                   help="do not fit: read the rows of earlier --json files (e.g. two runs in parallel) and write them")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-generate", action="store_true", help="skip (b) and (c)")
    p.add_argument("--generate-only", action="store_true",
                   help="only (c) for the dynamic scenes, merged into the --merge rows of the same scene")
    p.add_argument("--json", type=Path, default=None, help="also write the rows (with histories) here")
    p.add_argument("--write", action="store_true", help="write the table into docs/benchmarks.md")
    args = p.parse_args()
    if args.merge:
        rows = [r for f in args.merge for r in json.loads(f.read_text())]
        if args.generate_only:
            with tempfile.TemporaryDirectory() as tmp:
                for r in rows:
                    if r["method"] == "generate init" and r.get("generate_psnr") is None:
                        gen_out = Path(tmp) / r["scene"]
                        generate_for(args.data / r["scene"], gen_out)
                        r["generate_psnr"], r["generate_masked_psnr"] = generate_alone_psnr(args.data / r["scene"],
                                                                                             gen_out)
    else:
        rows = run(args.data, args.iterations, args.coarse, args.eval_every, args.scenes, args.seed,
                   not args.no_generate, args.json)
    body = tables(rows)
    print(body)
    if args.write:
        plot(rows, DOCS / "fit_tradeoffs.png")
        write_section("fit_tradeoffs", f"Machine: {machine()}. Command: `python benchmarks/fit_tradeoffs.py "
                      f"--data {args.data} --iterations {args.iterations} --write`.\n\n{body}\n\n"
                      "![held-out PSNR against time](fit_tradeoffs.png)")


if __name__ == "__main__":
    torch.manual_seed(0)
    torch.set_num_threads(int(__import__("os").environ.get("FIT_THREADS", torch.get_num_threads())))
    main()
