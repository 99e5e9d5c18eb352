"""Render quality vs time: depth-of-field samples, rolling-shutter chunks, tile size, SH degree (CPU).

    python benchmarks/render_tradeoffs.py [--size 128] [--gaussians 3000] [--threads 1] [--write]

One synthetic dynamic scene (Gaussians in front of the camera, a quarter of them moving sideways,
SH degree 3) and a camera moving along x. Each knob is swept against its most exact setting:

* DoF (thin lens, ray path): spp ∈ {1, …, 64} vs a 256-spp reference;
* rolling shutter (ray path): chunks ∈ {1, …, 32, H} vs chunks = H (exact per row);
* tile size of the rasterizer: {8, 16, 32} vs 16 (the image must not depend on it: error 0);
* SH degree 0–3 (rasterizer) vs degree 3: the truncation error of dropping the higher bands;
* the pinhole ray path vs the tile rasterizer (eps2d = 0): the cost and the EWA difference.

Prints a markdown table, writes docs/render_tradeoffs.csv and docs/render_tradeoffs.png, and with
``--write`` the table into docs/benchmarks.md (section ``render_tradeoffs``).
"""
from __future__ import annotations

import argparse
import csv
import math
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine, markdown_table, peak_rss_mb, write_section  # noqa: E402

from diff4splat.cameras import CameraPath, RollingShutter, ThinLens, intrinsics_from_fov  # noqa: E402
from diff4splat.render import rasterize, raytrace, render_rolling_shutter  # noqa: E402
from diff4splat.scene.dynamic import DynamicGaussians  # noqa: E402
from diff4splat.scene.gaussians import Gaussians  # noqa: E402

DOCS = Path(__file__).resolve().parent.parent / "docs"
T_FRAME = 0.5
RAY_TILE = 8
"""Pixel tile of the ray path's culling groups (8 is fastest at 128 px on this machine; 4: per-tile
overhead dominates, 16: ~2x more candidate Gaussians per ray)."""
APERTURE = 0.15


def make_scene(n: int, seed: int = 0) -> DynamicGaussians:
    """n Gaussians at 3–9 m in a 60° view, SH degree 3 (bands decaying ×0.5); a quarter move 1.5 m in x."""
    g = torch.Generator().manual_seed(seed)
    r = lambda *s: torch.rand(*s, generator=g)  # noqa: E731
    z = 3.0 + 6.0 * r(n)
    means = torch.stack([(r(n) - 0.5) * 1.2 * z, (r(n) - 0.5) * 1.2 * z, z], -1)
    sh = torch.randn(n, 16, 3, generator=g) * torch.tensor([1.0] + [0.5] * 3 + [0.25] * 5 + [0.125] * 7)[None, :, None]
    canon = Gaussians(means, torch.randn(n, 4, generator=g), 0.02 + 0.1 * r(n, 3), 0.3 + 0.65 * r(n), sh)
    d_means = torch.zeros(2, n, 3)
    d_means[1, : n // 4, 0] = 1.5
    d_quats = torch.zeros(2, n, 4)
    d_quats[..., 0] = 1.0
    return DynamicGaussians(canon, torch.tensor([0.0, 1.0]), d_means, d_quats, torch.zeros(2, n, 3))


def make_path(size: int) -> CameraPath:
    vms = torch.eye(4).repeat(2, 1, 1)
    vms[1, 0, 3] = -0.3  # camera centre moves 0.3 m along +x over the clip
    K = intrinsics_from_fov(size, size, fov_y_deg=60.0).expand(2, 3, 3).clone()
    return CameraPath(vms, K, size, size)


def timed(fn, repeats: int):
    """(median seconds, last result): ``repeats`` > 1 timed runs after one warm-up run, else a single
    timed run (expensive settings, references)."""
    out = fn() if repeats > 1 else None
    times = []
    for _ in range(max(repeats, 1)):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


def errors(img: torch.Tensor, ref: torch.Tensor) -> tuple[float, float]:
    """(PSNR dB, max |Δ|) of RGB images in [0, 1]; PSNR = inf when identical."""
    d = (img.clamp(0, 1) - ref.clamp(0, 1)).double()
    mse = float((d * d).mean())
    return (math.inf if mse == 0 else -10.0 * math.log10(mse)), float(d.abs().max())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--gaussians", type=int, default=3000)
    ap.add_argument("--repeats", type=int, default=3, help="timed runs of the cheap settings (expensive: 1)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--write", action="store_true")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    S = args.size
    scene, path = make_scene(args.gaussians), make_path(S)
    g = scene.at(T_FRAME)
    vm, K = path.viewmat_at(T_FRAME)[None], path.Ks[:1]
    bg = torch.zeros(1, 3)
    gargs = (g.means, g.quats, g.scales, g.opacities, g.sh, vm, K, S, S)
    rows: list[dict] = []

    def add(effect, setting, seconds, img, ref, note=""):
        psnr, mx = errors(img, ref)
        rows.append({"effect": effect, "setting": setting, "ms_per_frame": 1000 * seconds, "psnr_db": psnr,
                     "max_abs": mx, "note": note})
        print(f"{effect:>16} {setting:>8}  {1000 * seconds:9.1f} ms  PSNR {psnr:6.2f} dB  max {mx:.4f}", flush=True)

    # depth of field: thin lens focused at 5 m, aperture radius 15 cm: circle of confusion
    # 2·f·A·|z − z_f|/(z·z_f) = 4.4 px at 3 m and 3.0 px at 9 m for f = 111 px (128 px, 60°)
    def dof(spp):
        return lambda: rasterize(*gargs, sh_degree=3, backgrounds=bg, render_mode="RGB", tile_size=RAY_TILE,
                                 camera_params=ThinLens(APERTURE, 5.0, spp=spp))[0][0]
    _, ref = timed(dof(256), 1)
    for spp in (1, 2, 4, 8, 16, 32, 64):
        sec, img = timed(dof(spp), args.repeats if spp <= 8 else 1)
        add("DoF spp", str(spp), sec, img, ref, "vs 256 spp")

    # rolling shutter: readout 0.5 of the clip centred on t = 0.5, scene and camera moving
    def rs(chunks):
        return lambda: render_rolling_shutter(scene, path, RollingShutter(0.5, chunks=chunks), frames=[0],
                                              tile_size=RAY_TILE)[0][0]
    _, ref = timed(rs(None), 1)
    for chunks in (1, 2, 4, 8, 16, 32, None):
        sec, img = timed(rs(chunks), args.repeats if chunks is not None and chunks <= 8 else 1)
        add("rolling chunks", str(chunks or S), sec, img, ref, "vs chunks = H")

    # tile size: results must not depend on it
    def tiles(ts):
        return lambda: rasterize(*gargs, sh_degree=3, backgrounds=bg, render_mode="RGB", tile_size=ts)[0][0]
    _, ref = timed(tiles(16), 1)
    for ts in (8, 16, 32):
        sec, img = timed(tiles(ts), args.repeats)
        add("tile size", str(ts), sec, img, ref, "vs 16 (exact)")

    # SH degree: truncation error of dropping bands of the degree-3 colours
    def sh(d):
        return lambda: rasterize(*gargs, sh_degree=d, backgrounds=bg, render_mode="RGB")[0][0]
    _, ref = timed(sh(3), 1)
    for d in (0, 1, 2, 3):
        sec, img = timed(sh(d), args.repeats)
        add("SH degree", str(d), sec, img, ref, "vs degree 3")

    # pinhole: ray path vs tile rasterizer (no dilation)
    sec_t, ref = timed(lambda: rasterize(*gargs, sh_degree=3, backgrounds=bg, render_mode="RGB", eps2d=0.0)[0][0],
                       args.repeats)
    add("pinhole path", "tiles", sec_t, ref, ref, "eps2d = 0")
    sec_r, img = timed(
        lambda: raytrace(*gargs, sh_degree=3, backgrounds=bg, render_mode="RGB", tile_size=RAY_TILE)[0][0],
        args.repeats)
    add("pinhole path", "rays", sec_r, img, ref, "vs tiles (EWA)")

    with (DOCS / "render_tradeoffs.csv").open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        for row in rows:
            w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in row.items()})
    plot(rows, DOCS / "render_tradeoffs.png", S)
    table = markdown_table(
        ["effect", "setting", "ms / frame", "PSNR dB", "max abs", "reference"],
        [[r["effect"], r["setting"], f"{r['ms_per_frame']:.0f}",
          "exact" if math.isinf(r["psnr_db"]) else f"{r['psnr_db']:.1f}", f"{r['max_abs']:.2g}", r["note"]]
         for r in rows])
    body = (f"### Render quality vs time ({S}×{S}, {args.gaussians} Gaussians, a quarter moving, SH degree 3)\n\n"
            f"`python benchmarks/render_tradeoffs.py --write`; median of {args.repeats} runs after a warm-up "
            f"(a single run for spp ≥ 16 and chunks ≥ 16). DoF: thin lens A = {100 * APERTURE:.0f} cm, focus 5 m "
            f"(ray path, tile {RAY_TILE}). Rolling shutter: readout 0.5 clip-time centred on t = 0.5, a quarter of "
            f"the Gaussians moving 1.5 m/clip, camera 0.3 m/clip (ray path per band). "
            f"Errors on RGB in [0, 1]. Machine: {machine()}, shared with other jobs while this ran (timings vary "
            f"by up to ~30% between runs). Peak RSS {peak_rss_mb():.0f} MiB. "
            f"Plot: docs/render_tradeoffs.png, data: docs/render_tradeoffs.csv.\n\n" + table)
    print(body)
    if args.write:
        write_section("render_tradeoffs", body)


def plot(rows: list[dict], out: Path, size: int) -> None:
    """PSNR (left axis) and time (right axis) per setting for each knob; PNG written atomically."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    effects = ["DoF spp", "rolling chunks", "tile size", "SH degree"]
    fig, axes = plt.subplots(1, 4, figsize=(16, 3.6))
    for ax, eff in zip(axes, effects, strict=True):
        rs = [r for r in rows if r["effect"] == eff]
        x = [r["setting"] for r in rs]
        psnr = [min(r["psnr_db"], 99.0) for r in rs]
        ax.plot(x, psnr, "o-", color="tab:blue")
        ax.set_ylabel("PSNR dB (99 = exact)", color="tab:blue")
        ax.set_xlabel(eff)
        ax2 = ax.twinx()
        ax2.plot(x, [r["ms_per_frame"] for r in rs], "s--", color="tab:red")
        ax2.set_ylabel("ms / frame", color="tab:red")
        ax.set_title(f"{eff} ({size}×{size})")
    fig.tight_layout()
    tmp = out.with_suffix(".tmp.png")
    fig.savefig(tmp, dpi=90)
    plt.close(fig)
    tmp.replace(out)


if __name__ == "__main__":
    main()
