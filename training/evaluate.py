"""Evaluation on held-out scenes: image, depth and motion metrics of generated 4D scenes, and the
error against run time of the flow-matching samplers.

``diff4splat evaluate --checkpoint DIR --data DIR [--random] [--sampling] [--csv FILE]`` (registered
through the ``diff4splat.commands`` entry point, so the runtime package never imports ``training``).

Per held-out clip (reference camera, T frames, model resolution), the scene is *generated* exactly as
``generate`` does it — from the clip's first frame, its camera path and its caption — and rendered
along the clip's cameras at the clip's times:

- ``psnr_input``/``ssim_input``: frame 0 (the input view at t = 0) against the ground truth;
- ``psnr_novel``/``ssim_novel``: frames 1…T−1 (new views at new times);
- ``depth_corr``: Pearson correlation of rendered and true metric depth over valid covered pixels;
- ``motion_epe``: mean distance (metres) between tracked points predicted by the scene (the Gaussian
  at the track's frame-0 pixel, deformed to each time) and the true 3D tracks, visible points only;
- ``loop_psnr``: loop closure on static clips. The scene is generated along a 360° ``orbit`` from the
  clip's first frame with the clip's intrinsics, around the point at the median true depth of that frame
  (the orbit's frames advance 2π/T, so the loop closes at the first camera at t = 1),
  and rendered from the first camera at t = 1, the frame that closes the loop; it is compared with the
  ground-truth first frame, which in a static world is also the true view from that camera at t = 1.
  Drift of the generated scene around the loop (spurious motion, geometry that only holds near the
  input view) lowers it; an explicit scene that comes back to the photograph scores its input PSNR.
  Dynamic clips have no ground truth for that view and report NaN (skipped in the mean). Comparing the
  rendered first and last frames with each other instead would reward an identity deformation with a
  perfect score whatever the scene looks like, so it is not used.

- ``vae_psnr``: PSNR of the VAE's reconstruction of the whole clip (posterior mean, decoded) against
  the clip — the ceiling that the latents put on everything downstream (PyTorch models only; NaN for
  another runtime).

With ``--photo IMAGE`` it also reports ``photo_psnr``: the scene generated from a real photograph,
rendered from the input camera at t = 0, against that photograph.
"""
from __future__ import annotations

import csv
import math
import statistics
import time
from pathlib import Path

import kornia
import torch
from torch import Tensor

from diff4splat.cameras import CameraPath, make_trajectory
from diff4splat.pipeline import Diff4SplatPipeline, load_model
from diff4splat.render.sequence import render_path

from .objectives import track_query_index

__all__ = ["evaluate_clips", "sampling_tradeoffs", "register", "METRICS", "DIAGNOSTICS"]

METRICS = ("psnr_input", "ssim_input", "psnr_novel", "ssim_novel", "depth_corr", "motion_epe", "loop_psnr",
           "vae_psnr")
"""Reported metrics; higher is better except ``motion_epe`` (metres)."""

DIAGNOSTICS = ("motion_epe_t0", "motion_epe_hold")
"""Reported beside the metrics to split ``motion_epe`` (metres, lower is better): ``motion_epe_t0`` is the
error at frame 0 alone (geometry: where the scene puts the tracked points before anything moves), and
``motion_epe_hold`` the error of holding each point at its frame-0 position (no motion). The predicted motion
helps where ``motion_epe`` < ``motion_epe_hold``; an identity deformation makes them equal."""


PSNR_CAP = 100.0
"""PSNR of identical images (MSE 0) is reported as this many dB instead of infinity."""


def _psnr(a: Tensor, b: Tensor) -> float:
    """PSNR in dB of images in [0, 1] (kornia), (F, 3, H, W); capped at :data:`PSNR_CAP`."""
    if float(((a.clamp(0, 1) - b) ** 2).mean()) <= 10 ** (-PSNR_CAP / 10):
        return PSNR_CAP
    return float(kornia.metrics.psnr(a.clamp(0, 1), b, 1.0))


def _ssim(a: Tensor, b: Tensor) -> float:
    return float(kornia.metrics.ssim(a.clamp(0, 1), b, 11).mean())


def _pearson(a: Tensor, b: Tensor) -> float:
    a, b = a - a.mean(), b - b.mean()
    den = math.sqrt(float((a * a).sum()) * float((b * b).sum()))
    return float((a * b).sum()) / den if den > 0 else 0.0


def _held_out_clips(data: str | Path, height: int, width: int, num_frames: int, limit: int | None):
    from data_prep.clips import ClipConfig, ClipDataset

    ds = ClipDataset(data, ClipConfig(num_frames=num_frames, height=height, width=width, scenes="all",
                                      reference_camera="first", target_cameras="same", plucker="raw", seed=0))
    n = len(ds) if limit is None else min(limit, len(ds))
    return [ds[i] for i in range(n)]


@torch.no_grad()
def evaluate_clip(pipe: Diff4SplatPipeline, clip: dict, *, steps: int | None = None, sampler: str | None = None,
                  seed: int = 0) -> dict[str, float]:
    """Metrics of one held-out clip (module docstring). Returns {metric: value}."""
    cfg = pipe.config
    T = clip["video"].shape[1]
    cams = CameraPath(clip["viewmats"].double(), clip["Ks"].double(), cfg.width, cfg.height, clip["times"].double())
    image = clip["video"][:, 0].permute(1, 2, 0)
    res = pipe(image, cams, clip["caption"], steps=steps, sampler=sampler, seed=seed)
    colors, depths, alphas = render_path(res.scene, res.cameras)
    pred = colors.permute(0, 3, 1, 2)
    gt = clip["video"].permute(1, 0, 2, 3)
    out = {"psnr_input": _psnr(pred[:1], gt[:1]), "ssim_input": _ssim(pred[:1], gt[:1]),
           "psnr_novel": _psnr(pred[1:], gt[1:]) if T > 1 else float("nan"),
           "ssim_novel": _ssim(pred[1:], gt[1:]) if T > 1 else float("nan")}
    valid = clip["depth_valid"] & (alphas > 0.5)
    out["depth_corr"] = (_pearson(depths[valid].double(), clip["depth"][valid].double())
                         if valid.sum() > 1 else float("nan"))
    # motion: every Gaussian survives pruning only if seen; map track pixels through the kept indices
    tracks, vis = clip["tracks"], clip["track_visibility"] & clip["track_mask"][:, None]
    idx, ok = track_query_index(tracks[:, 0], clip["Ks"][0], cfg.width, cfg.height, vis[:, 0])
    kept = _kept_pixel_map(pipe, res)
    g_idx = kept[idx]
    ok = ok & (g_idx >= 0)
    if bool(ok.any()):
        pred_pts = torch.stack([res.scene.at(float(t)).means[g_idx.clamp(min=0)] for t in res.cameras.times], 1)
        m = vis & ok[:, None]
        err = (pred_pts.float() - tracks).norm(dim=-1)
        hold = (pred_pts[:, :1].float() - tracks).norm(dim=-1)
        # a mean over no points is NaN, which evaluate_clips skips
        out["motion_epe"], out["motion_epe_hold"] = float(err[m].mean()), float(hold[m].mean())
        out["motion_epe_t0"] = float(err[:, 0][m[:, 0]].mean())
    else:
        out["motion_epe"] = out["motion_epe_hold"] = out["motion_epe_t0"] = float("nan")
    out["loop_psnr"] = _loop_psnr(pipe, image, clip, T, steps=steps, sampler=sampler, seed=seed)
    out["vae_psnr"] = float("nan")
    if pipe.model is not None:
        vae = pipe.model.vae
        video = clip["video"][None].to(pipe.device) * 2 - 1
        recon = (vae.decode_latents(vae.encode_latents(video))[0].cpu() + 1) / 2
        out["vae_psnr"] = _psnr(recon.permute(1, 0, 2, 3), gt)
    return out


def _loop_psnr(pipe: Diff4SplatPipeline, image: Tensor, clip: dict, num_frames: int, **kw) -> float:
    """PSNR (dB) of the loop-closing frame of a 360° orbit against the ground-truth first frame
    (module docstring); NaN for a dynamic clip."""
    if bool(clip["dynamic"]):
        return float("nan")
    cfg = pipe.config
    valid = clip["depth_valid"][0]
    radius = float(clip["depth"][0][valid].median()) if bool(valid.any()) else cfg.scene_depth
    orbit = make_trajectory("orbit", num_frames, clip["Ks"][0].double(), cfg.width, cfg.height, scene_depth=radius)
    closing = CameraPath(orbit.viewmats[:1], orbit.Ks[:1], orbit.width, orbit.height,
                         torch.ones(1, dtype=orbit.viewmats.dtype))
    res = pipe(image, orbit, clip["caption"], **kw)
    colors, _, _ = render_path(res.scene, closing.to(torch.float32))
    return _psnr(colors.permute(0, 3, 1, 2), clip["video"][:, :1].permute(1, 0, 2, 3))


def _kept_pixel_map(pipe: Diff4SplatPipeline, res) -> Tensor:
    """(H·W,) index of each reference pixel's Gaussian after pruning, −1 where pruned.

    Pixel-aligned Gaussians keep their row-major order through pruning (``select`` with a mask), so
    the kept pixels are recovered by matching canonical means to the unpruned pixel grid order.
    """
    H, W = pipe.config.height, pipe.config.width
    stats = res.prune_stats
    kept = torch.full((H * W,), -1, dtype=torch.long)
    if stats["after"] == stats["before"]:
        kept[:] = torch.arange(H * W)
        return kept
    # pruned: recover kept pixels by projecting the canonical means into the reference camera
    g = res.scene.canonical
    K = res.cameras.Ks[0]
    uv = (K @ g.means.T.to(K)).T
    u = (uv[:, 0] / uv[:, 2]).floor().long().clamp(0, W - 1)
    v = (uv[:, 1] / uv[:, 2]).floor().long().clamp(0, H - 1)
    kept[v * W + u] = torch.arange(g.num_gaussians)
    return kept


@torch.no_grad()
def photo_psnr(pipe: Diff4SplatPipeline, image_path: str | Path, prompt: str = "", *, steps: int | None = None,
               seed: int = 0) -> float:
    """PSNR (dB) of the generated scene rendered from the input camera at t = 0 against the photograph
    itself (centre-cropped and resized to the model resolution, as ``generate`` reads it)."""
    from diff4splat.io import load_image

    cfg = pipe.config
    image = load_image(image_path, size=(cfg.height, cfg.width))
    res = pipe(image, pipe.default_cameras("orbit", cfg.num_frames), prompt, steps=steps, seed=seed)
    first = CameraPath(res.cameras.viewmats[:1], res.cameras.Ks[:1], cfg.width, cfg.height,
                       torch.zeros(1, dtype=res.cameras.viewmats.dtype))
    colors, _, _ = render_path(res.scene, first)
    return _psnr(colors.permute(0, 3, 1, 2), image.permute(2, 0, 1)[None])


def evaluate_clips(pipe: Diff4SplatPipeline, clips: list[dict], **kw) -> dict[str, float]:
    """Mean of every metric and diagnostic over clips (NaNs — e.g. no visible tracks — are skipped)."""
    rows = [evaluate_clip(pipe, c, **kw) for c in clips]
    return {k: statistics.fmean([r[k] for r in rows if not math.isnan(r[k])] or [float("nan")])
            for k in METRICS + DIAGNOSTICS}


@torch.no_grad()
def sampling_tradeoffs(pipe: Diff4SplatPipeline, clips: list[dict], nfes=(1, 2, 4, 8, 16, 32, 64),
                       reference_steps: int = 256) -> list[dict]:
    """Error against run time of the Euler and Heun samplers.

    For each clip, the DiT's ODE is integrated with ``reference_steps`` Heun steps as the reference;
    each sampler at each NFE (Euler: steps = NFE; Heun: steps = ⌈(NFE+1)/2⌉, NFE = 2·steps − 1) is
    compared by the RMS latent distance to the reference, its wall time, and the PSNR of the
    generated scene's renders against the ground-truth clip.

    Returns:
        Rows {sampler, nfe, steps, ms, latent_rms, psnr}.
    """
    rows = []
    cfg = pipe.config
    refs = []
    for c in clips:
        cams = CameraPath(c["viewmats"].double(), c["Ks"].double(), cfg.width, cfg.height, c["times"].double())
        image = c["video"][:, 0].permute(1, 2, 0)
        refs.append((c, cams, image, pipe(image, cams, c["caption"], steps=reference_steps, sampler="heun").latents))
    for sampler in ("euler", "heun"):
        for nfe in nfes:
            steps = nfe if sampler == "euler" else max(1, math.ceil((nfe + 1) / 2))
            ms, rms, psnr = [], [], []
            for c, cams, image, ref in refs:
                t0 = time.perf_counter()
                res = pipe(image, cams, c["caption"], steps=steps, sampler=sampler)
                ms.append(1000 * (time.perf_counter() - t0))
                rms.append(float(((res.latents - ref) ** 2).mean().sqrt()))
                colors, _, _ = render_path(res.scene, res.cameras)
                psnr.append(_psnr(colors.permute(0, 3, 1, 2), c["video"].permute(1, 0, 2, 3)))
            rows.append({"sampler": sampler, "nfe": 2 * steps - 1 if sampler == "heun" else steps, "steps": steps,
                         "ms": statistics.median(ms), "latent_rms": statistics.fmean(rms),
                         "psnr": statistics.fmean(psnr)})
    return rows


@torch.no_grad()
def stiffness_profile(pipe: Diff4SplatPipeline, clip: dict, steps: int = 16, substeps: int = 32,
                      seed: int = 0) -> list[dict]:
    """How the sampler's error behaves along σ, especially near σ → 0.

    Along the ``steps``-step schedule (with the config's shift), from the state x(σ_i) of an accurate
    trajectory (each interval integrated with ``substeps`` Heun steps), reports for every step:
    ``local_error`` — RMS difference between one Euler step σ_i → σ_{i+1} and the accurate state
    x(σ_{i+1}) (the local truncation error, ≈ ½ h² ‖dv/dσ‖), and ``lipschitz`` — a finite-difference
    estimate ‖v(x+δ, σ_i) − v(x, σ_i)‖ / ‖δ‖ (‖δ‖ = 1e-3·‖x‖) of how stiff the velocity field is there.

    Returns:
        Rows {step, sigma, sigma_next, local_error, lipschitz}.
    """
    from models.flow_matching import heun_sample, sigma_schedule

    cfg = pipe.config
    runtime = pipe.runtime
    cams = CameraPath(clip["viewmats"].double(), clip["Ks"].double(), cfg.width, cfg.height, clip["times"].double())
    image = clip["video"][:, 0].permute(1, 2, 0)
    captured: dict = {}
    original = runtime.velocity

    def recorder(x, sigma, *cond):
        captured.setdefault("cond", cond)
        captured.setdefault("shape", x.shape)
        return original(x, sigma, *cond)

    runtime.velocity = recorder
    try:
        pipe(image, cams, clip["caption"], steps=1, sampler="euler", seed=seed)
    finally:
        del runtime.velocity  # restore the class method
    cond = captured["cond"]

    def v(x: Tensor, sigma: Tensor) -> Tensor:
        return original(x, sigma.reshape(1).to(x), *cond)

    gen = torch.Generator().manual_seed(seed)
    x = torch.randn(captured["shape"], generator=gen)
    sig = sigma_schedule(steps, cfg.sampling.shift, dtype=torch.float64)
    rows = []
    for i in range(steps):
        s0, s1 = sig[i], sig[i + 1]
        fine = heun_sample(v, x, torch.linspace(float(s0), float(s1), substeps + 1, dtype=torch.float64))
        v0 = v(x, s0)
        euler = x + (s1 - s0).to(x) * v0
        delta = torch.randn(x.shape, generator=gen)
        delta = delta * (1e-3 * x.norm() / delta.norm())
        lip = float((v(x + delta, s0) - v0).norm() / delta.norm())
        rows.append({"step": i, "sigma": float(s0), "sigma_next": float(s1),
                     "local_error": float(((euler - fine) ** 2).mean().sqrt()), "lipschitz": lip})
        x = fine
    return rows


def _print_table(rows: list[dict], header: list[str]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    for r in rows:
        lines.append("| " + " | ".join(f"{r[h]:.4g}" if isinstance(r[h], float) else str(r[h]) for h in header) + " |")
    return "\n".join(lines)


def run(args) -> int:
    """``diff4splat evaluate`` (see module docstring)."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model, source = load_model(args.checkpoint, args.config, seed=args.seed, untrained=args.random)
    pipe = Diff4SplatPipeline(model)
    cfg = pipe.config
    clips = _held_out_clips(args.data, cfg.height, cfg.width, args.frames or cfg.num_frames, args.limit)
    if not clips:
        raise ValueError(f"--data: no clips in {args.data}")
    metrics = evaluate_clips(pipe, clips, steps=args.steps)
    row = {"model": source, "clips": len(clips), **metrics}
    columns = ["model", "clips", *METRICS, *DIAGNOSTICS]
    if args.photo is not None:
        row["photo_psnr"] = photo_psnr(pipe, args.photo, args.prompt, steps=args.steps)
        columns.append("photo_psnr")
    print(_print_table([row], columns))
    if args.csv:
        _append_csv(Path(args.csv), row)
    if args.sampling:
        rows = sampling_tradeoffs(pipe, clips[: args.sampling_clips])
        print(_print_table(rows, ["sampler", "nfe", "steps", "ms", "latent_rms", "psnr"]))
        if args.csv:
            for r in rows:
                _append_csv(Path(args.csv).with_name(Path(args.csv).stem + "_sampling.csv"), {"model": source, **r})
    return 0


def _append_csv(path: Path, row: dict) -> None:
    new = not path.exists()
    with open(path, "a", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(row))
        if new:
            w.writeheader()
        w.writerow(row)


def register(subparsers) -> None:
    """Add the ``evaluate`` subcommand to ``diff4splat``'s CLI (entry point ``diff4splat.commands``)."""
    e = subparsers.add_parser("evaluate", help="evaluate a model on held-out scenes",
                              description="Image, depth and motion metrics on held-out scenes; sampler error vs NFE.")
    e.add_argument("--checkpoint", type=Path, default=None, help="model folder (default: shipped weights)")
    e.add_argument("--random", action="store_true", help="evaluate the seeded random (untrained) model")
    e.add_argument("--config", default="tiny", help="config of the shipped/random model (default: tiny)")
    e.add_argument("--seed", type=int, default=0, help="seed of the random model (default: 0)")
    e.add_argument("--data", type=Path, required=True, help="held-out dataset root (data_prep format)")
    e.add_argument("--frames", type=int, default=None, help="clip length T = 1 + 4k (default: config)")
    e.add_argument("--steps", type=int, default=None, help="sampler steps (default: config)")
    e.add_argument("--limit", type=int, default=None, help="evaluate at most this many clips")
    e.add_argument("--sampling", action="store_true", help="also measure sampler error vs NFE")
    e.add_argument("--sampling-clips", type=int, default=4, help="clips used for the sampling sweep")
    e.add_argument("--photo", type=Path, default=None,
                   help="also report photo_psnr: the render at the input camera, t = 0, against this photograph")
    e.add_argument("--prompt", default="", help="prompt used with --photo")
    e.add_argument("--csv", type=Path, default=None, help="append the table rows to this CSV")
    e.set_defaults(func=run)
