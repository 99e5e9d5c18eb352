"""Evaluation on held-out scenes (``diff4splat evaluate``; command and tables: :mod:`training.evaluate_cli`, metric
functions: :mod:`training.eval_metrics`). Each clip's scene is generated as ``generate`` does, from its first
frame, camera path and caption, and rendered along its cameras at its times:

- ``psnr_input``/``ssim_input``: frame 0; ``psnr_novel``/``ssim_novel``: frames 1…T−1 (PSNR of their mean MSE);
- ``depth_corr``: Pearson correlation of rendered and true depth over valid covered pixels, with
  :data:`DEPTH_DIAGNOSTICS` on the same pixels; ``motion_epe`` (metres) of the tracks, split by :data:`DIAGNOSTICS`;
- ``loop_psnr`` (static clips, else NaN): a 360° ``orbit`` from frame 0 around its median true depth, rendered from
  the first camera at t = 1 against the true frame 0;
- ``vae_psnr``: the VAE round trip of the clip, the ceiling of every render (PyTorch models only, else NaN);
- :data:`DIRECTION` (issue 58's direction test, :mod:`training.direction_test`; NaN unless the clip is dynamic and
  its caption names one direction): the scene generated with the caption and one generated with its direction
  flipped, each moved the named way (1 / 0) and by how much along it (metres).

:data:`BASELINES` score frames 1…T−1 of variants: ``repeat``/``repeat_blur`` (frame 0 held), ``noise`` (sampled
latents replaced by noise), ``gt`` (the true video's latents; PyTorch only), ``video`` (the sampled latents decoded,
no 3D). PSNR by view angle pools the frames of all clips per :data:`training.eval_metrics.ANGLE_BINS`
(:func:`binned_keys`). See docs/DESIGN.md, "Training" (Evaluation). Generation and rendering run on
``pipe.device``; clips and metrics stay on the CPU.
"""
from __future__ import annotations

import math
import statistics
import time
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor
from tqdm.auto import tqdm

from data_prep.clips import ClipConfig, ClipDataset
from diff4splat.cameras import CameraPath, make_trajectory
from diff4splat.io import load_image
from diff4splat.pipeline import DEFAULT_RESOLUTION, Diff4SplatPipeline, GenerationResult
from diff4splat.render.sequence import render_path
from diff4splat.utils.devices import synchronize
from models.flow_matching import SAMPLERS, heun_sample, sigma_schedule

from .direction_test import direction_query, flip_direction, named_way_score
from .drag_eval import true_drags
from .eval_metrics import (
    ANGLE_BINS,
    ablation_noise,
    binned_psnr,
    depth_errors,
    frame_mse,
    image_psnr,
    image_ssim,
    kept_index_map,
    motion_errors,
    pearson,
    psnr_from_mse,
    repeat_baselines,
    thumbnail,
    view_angles,
)
from .objectives import track_query_index

__all__ = ["evaluate_clip", "evaluate_all", "aggregate", "ClipEvaluation", "sampling_tradeoffs",
           "photo_fidelity", "stiffness_profile", "METRICS", "DIAGNOSTICS", "DEPTH_DIAGNOSTICS", "BASELINES",
           "VARIANTS", "PHOTO_KEYS", "DIRECTION", "binned_keys", "scene_motion", "held_out_clips",
           "pixel_positions", "decoded_video", "clip_inputs"]

METRICS = ("psnr_input", "ssim_input", "psnr_novel", "ssim_novel", "depth_corr", "motion_epe", "loop_psnr", "vae_psnr")
"""Reported metrics; higher is better except ``motion_epe`` (metres)."""

DIAGNOSTICS = ("motion_epe_t0", "motion_epe_hold", "motion_disp_epe", "motion_disp_hold", "motion_disp_d5",
               "motion_disp_d10", "motion_disp_hold_d5", "motion_disp_hold_d10", "motion_epe_gt",
               "motion_disp_epe_gt", "flow_disp_epe", "flow_disp_hold", "flow_disp_d5", "flow_disp_d10",
               "flow_disp_hold_d5", "flow_disp_hold_d10", "flow_disp_epe_gt", "motion_disp_epe_drag",
               "motion_disp_drag_d5", "motion_disp_drag_d10")
"""Reported beside ``motion_epe`` (metres; :func:`training.eval_metrics.motion_errors`): frame-0 error, holding
still, the displacement from frame 0 and its δ fractions (higher is better), and ``*_gt`` for the true latents;
``flow_*`` the same displacement terms over every valid frame-0 pixel (the clip's ``pixel_tracks``: dense scene flow;
on a static clip ``flow_disp_epe`` is the mean spurious motion); ``*_drag`` the displacement terms of the scene
generated with ``drags`` points per moving object taken from its true track (:func:`training.drag_eval.true_drags`;
NaN without ``drags`` or moving objects)."""

DIRECTION = ("direction_caption", "direction_flipped", "direction_along_caption", "direction_along_flipped")
"""The direction test (module docstring): the fraction of taking-part clips whose scene moved the captioned object
the named way, with the caption and with its direction flipped, and the mean displacement along the named way
(metres; holding still scores 0 and 0). :func:`aggregate` adds ``direction_clips``, how many took part."""

DEPTH_DIAGNOSTICS = ("depth_abs_rel", "depth_scale")
"""Beside ``depth_corr`` (:func:`training.eval_metrics.depth_errors`): AbsRel and the median rendered/true ratio."""

VARIANTS = ("noise", "gt", "video", "repeat", "repeat_blur")
"""Baselines and ablations scored on the model's novel frames (module docstring)."""

BASELINES = tuple(f"psnr_novel_{v}" for v in VARIANTS)
"""PSNR (dB) of each variant on frames 1…T−1 (mean over clips, like ``psnr_novel``)."""


def binned_keys() -> tuple[str, ...]:
    """``psnr_pooled[_<variant>]`` and per view-angle bin ``psnr_<bin>[_<variant>]``, ``frames_<bin>``."""
    return ("psnr_pooled", *(f"psnr_pooled_{v}" for v in VARIANTS)) + tuple(
        k for name, _, _ in ANGLE_BINS for k in (f"psnr_{name}", *(f"psnr_{name}_{v}" for v in VARIANTS),
                                                 f"frames_{name}"))


def held_out_clips(data: str | Path, height: int, width: int, num_frames: int, limit: int | None):
    """The first ``limit`` clips (CPU tensors) of a dataset, reference camera first, all scenes."""
    ds = ClipDataset(data, ClipConfig(num_frames=num_frames, height=height, width=width, scenes="all",
                                      reference_camera="first", target_cameras="same", plucker="raw", seed=0))
    n = len(ds) if limit is None else min(limit, len(ds))
    return [ds[i] for i in range(n)]


@dataclass
class ClipEvaluation:
    """What :func:`evaluate_clip` measures on one clip: ``max_angle`` the largest view angle (degrees); ``metrics``
    for :data:`METRICS`, :data:`DIAGNOSTICS`, :data:`DEPTH_DIAGNOSTICS`, :data:`BASELINES`, :data:`DIRECTION`;
    ``angles`` (T−1,) degrees and ``frame_mse`` {"model" or variant: (T−1,) float64, NaN where unavailable} of
    frames 1…T−1."""

    name: str
    dynamic: bool
    max_angle: float
    metrics: dict[str, float]
    angles: Tensor
    frame_mse: dict[str, Tensor] = field(default_factory=dict)


def pixel_positions(res: GenerationResult) -> tuple[Tensor, Tensor]:
    """CPU positions (H·W, T, 3), metres, of the photo layer's front disk at each frame-0 pixel (the first H·W slots,
    ``res.gaussian_index``) at the scene's camera times, and (H·W,) bool: the pixel's disk was kept (not pruned)."""
    H, W = res.cameras.height, res.cameras.width
    kept = kept_index_map(res.gaussian_index.cpu(), res.num_slots)[: H * W]  # frame 0's pixel → its Gaussian
    # gate 0: every Gaussian at every time (a scene with temporal opacity leaves the faded ones out by default)
    means = torch.stack([res.scene.at(t, gate=0).means.cpu() for t in res.cameras.times.tolist()], 1)  # (M, T, 3)
    return means[kept.clamp(min=0)], kept >= 0


def scene_motion(pipe: Diff4SplatPipeline, res: GenerationResult, clip: dict) -> dict[str, float]:
    """:func:`motion_errors` on the CPU of a generated scene: each track follows the photo layer's front disk at its
    frame-0 pixel (the first H·W unpruned slots, ``res.gaussian_index``) through the clip's times; the ``flow_disp_*``
    terms (:data:`DIAGNOSTICS`) follow every frame-0 pixel against the clip's ``pixel_tracks``."""
    H, W = res.cameras.height, res.cameras.width
    tracks, vis = clip["tracks"], clip["track_visibility"] & clip["track_mask"][:, None]
    idx, ok = track_query_index(tracks[:, 0], clip["Ks"][0], W, H, vis[:, 0])
    pixels, kept = pixel_positions(res)
    out = motion_errors(pixels[idx], tracks, vis & ok[:, None] & kept[idx][:, None])
    T = pixels.shape[1]
    flow = clip["pixel_tracks"].reshape(T, H * W, 3).transpose(0, 1)
    dense = clip["pixel_track_valid"].reshape(H * W) & kept
    errors = motion_errors(pixels, flow, dense[:, None].expand(H * W, T))
    return out | {"flow" + k[len("motion"):]: v for k, v in errors.items() if k.startswith("motion_disp")}


def clip_inputs(pipe: Diff4SplatPipeline, clip: dict) -> tuple[CameraPath, Tensor]:
    """A :func:`held_out_clips` clip's reference camera path (float64 viewmats, Ks in pixels and times in seconds, at
    the model's width × height) and its first frame (H, W, 3) colours in [0, 1], as ``pipe`` takes them."""
    cfg = pipe.config
    cams = CameraPath(clip["viewmats"].double(), clip["Ks"].double(), cfg.width, cfg.height, clip["times"].double())
    return cams, clip["video"][:, 0].permute(1, 2, 0)


def _render(res: GenerationResult, cameras: CameraPath | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """CPU (colors, depths, alphas) of :func:`render_path` of a scene along ``cameras`` (default: its own path)."""
    cameras = res.cameras if cameras is None else cameras
    out = render_path(res.scene, cameras.to(res.scene.canonical.means.device), eps2d=res.eps2d,
                      background=res.background)
    return out[0].cpu(), out[1].cpu(), out[2].cpu()


@torch.no_grad()
def evaluate_clip(pipe: Diff4SplatPipeline, clip: dict, *, steps: int | None = None, sampler: str | None = None,
                  seed: int = 0, drags: int = 0) -> ClipEvaluation:
    """Metrics, baselines and ablations (module docstring) of one clip of CPU tensors: generated with sampled,
    noise and (PyTorch only) true latents, plus the loop orbit of a static clip; with ``drags`` > 0 once more with that
    many drags per moving object from the true tracks (``*_drag`` of :data:`DIAGNOSTICS`). Raises ValueError for
    T < 2."""
    T = clip["video"].shape[1]
    if T < 2:
        raise ValueError(f"clip must have at least 2 frames, got {T}")
    cams, image = clip_inputs(pipe, clip)
    gt = clip["video"].permute(1, 0, 2, 3)
    gen = dict(steps=steps, sampler=sampler, seed=seed)

    res = pipe(image, cams, clip["caption"], **gen)
    colors, depths, alphas = _render(res)
    pred = colors.permute(0, 3, 1, 2)
    mse = {"model": frame_mse(pred[1:], gt[1:]), **repeat_baselines(clip["video"])}
    video = decoded_video(pipe, res)  # (3, T, h, w)
    mse["video"] = frame_mse(video.permute(1, 0, 2, 3)[1:], gt[1:])
    out = {"psnr_input": image_psnr(pred[:1], gt[:1]), "ssim_input": image_ssim(pred[:1], gt[:1]),
           "ssim_novel": image_ssim(pred[1:], gt[1:])}
    valid = clip["depth_valid"] & (alphas > 0.5)
    out["depth_corr"] = (pearson(depths[valid].double(), clip["depth"][valid].double())
                         if valid.sum() > 1 else float("nan"))
    out.update(depth_errors(depths[valid], clip["depth"][valid]))
    out.update(scene_motion(pipe, res, clip))
    true = true_drags(clip, per_object=drags) if drags else None
    dragged = scene_motion(pipe, pipe(image, cams, clip["caption"], drags=true, **gen), clip) if true else {}
    out.update({key: dragged.get(of, float("nan")) for key, of in (("motion_disp_epe_drag", "motion_disp_epe"),
                                                                   ("motion_disp_drag_d5", "motion_disp_d5"),
                                                                   ("motion_disp_drag_d10", "motion_disp_d10"))})
    out["loop_psnr"] = _loop_psnr(pipe, image, clip, T, **gen)
    out.update(_direction(pipe, clip, res, cams, image, **gen))

    noisy = pipe(image, cams, clip["caption"], video_latents=ablation_noise(res.latents.shape, seed), **gen)
    mse["noise"] = frame_mse(_render(noisy)[0][1:].permute(0, 3, 1, 2), gt[1:])
    mse["gt"] = torch.full((T - 1,), float("nan"), dtype=torch.float64, device="cpu")
    out["vae_psnr"] = out["motion_epe_gt"] = out["motion_disp_epe_gt"] = out["flow_disp_epe_gt"] = float("nan")
    if pipe.model is not None:
        # through the runtime, as the pipeline does: in its dtype, and on the device with model offload
        latents = pipe.runtime.encode_image(clip["video"][None].to(pipe.device) * 2 - 1)
        recon = (pipe.runtime.decode_latents(latents)[0].cpu() + 1) / 2
        out["vae_psnr"] = image_psnr(recon.permute(1, 0, 2, 3), gt)
        oracle = pipe(image, cams, clip["caption"], video_latents=latents, **gen)
        mse["gt"] = frame_mse(_render(oracle)[0][1:].permute(0, 3, 1, 2), gt[1:])
        motion = scene_motion(pipe, oracle, clip)
        out["motion_epe_gt"], out["motion_disp_epe_gt"] = motion["motion_epe"], motion["motion_disp_epe"]
        out["flow_disp_epe_gt"] = motion["flow_disp_epe"]
    out["psnr_novel"] = psnr_from_mse(float(mse["model"].mean()))
    out.update({f"psnr_novel_{v}": psnr_from_mse(float(mse[v].mean())) for v in VARIANTS})
    angles = view_angles(clip["viewmats"])
    return ClipEvaluation(name=str(clip.get("scene", "")), dynamic=bool(clip["dynamic"]),
                          max_angle=float(angles.max()), metrics=out, angles=angles[1:], frame_mse=mse)


def decoded_video(pipe: Diff4SplatPipeline, res: GenerationResult) -> Tensor:
    """(3, T, h, w) CPU colours in [0, 1] of a generation's latents decoded by the VAE: ``res.video`` where the
    pipeline kept it (decoded once per generation), else ``res.latents`` decoded through ``pipe.runtime``."""
    decoded = res.video if res.video is not None else pipe.runtime.decode_latents(res.latents)
    return ((decoded[0].float().cpu() + 1) / 2).clamp(0, 1)


def _direction(pipe: Diff4SplatPipeline, clip: dict, res: GenerationResult, cams: CameraPath, image: Tensor,
               **kw) -> dict[str, float]:
    """:data:`DIRECTION` of one clip from its scene ``res`` (generated from ``image`` along ``cams`` with the caption)
    and one more generated with the caption's direction flipped; NaN when the clip does not take part (no extra
    generation then)."""
    query = direction_query(clip)
    if query is None:
        return dict.fromkeys(DIRECTION, float("nan"))
    axis, sign, moving = query
    flipped = pipe(image, cams, flip_direction(clip["caption"]), **kw)
    out = {}
    for name, scene, s in (("caption", res, sign), ("flipped", flipped, -sign)):
        named_way, along = named_way_score(*pixel_positions(scene), moving, axis, s)
        out[f"direction_{name}"], out[f"direction_along_{name}"] = float(named_way), along
    return out


def _loop_psnr(pipe: Diff4SplatPipeline, image: Tensor, clip: dict, num_frames: int, **kw) -> float:
    """``loop_psnr`` (module docstring), dB; NaN for a dynamic clip."""
    if bool(clip["dynamic"]):
        return float("nan")
    cfg = pipe.config
    valid = clip["depth_valid"][0]
    radius = float(clip["depth"][0][valid].median()) if bool(valid.any()) else cfg.scene_depth
    orbit = make_trajectory("orbit", num_frames, clip["Ks"][0].double(), cfg.width, cfg.height, scene_depth=radius)
    closing = CameraPath(orbit.viewmats[:1], orbit.Ks[:1], orbit.width, orbit.height,
                         torch.ones(1, dtype=orbit.viewmats.dtype, device=orbit.viewmats.device))
    res = pipe(image, orbit, clip["caption"], **kw)
    colors, _, _ = _render(res, closing.to(torch.float32))
    return image_psnr(colors.permute(0, 3, 1, 2), clip["video"][:, :1].permute(1, 0, 2, 3))


PHOTO_KEYS = ("photo_psnr", "photo_psnr_model", "photo_thumbnail", "photo_thumbnail_model")
"""Keys of :func:`photo_fidelity` (``evaluate --photo``)."""


@torch.no_grad()
def photo_fidelity(pipe: Diff4SplatPipeline, image_path: str | Path, prompt: str = "", *,
                   resolution: int | None = DEFAULT_RESOLUTION, steps: int | None = None, seed: int = 0
                   ) -> dict[str, float]:
    """PSNR (dB) of a photograph's scene (generated along the orbit at ``resolution`` pixels of height, None: the
    model's) rendered at the input camera at t = 0: ``photo_psnr`` at the output resolution, ``photo_psnr_model``
    both area-averaged to the model resolution, and ``photo_thumbnail[_model]`` the 8×8 thumbnail baseline at each.
    """
    cfg = pipe.config
    width, height = pipe.output_size(resolution)
    image = load_image(image_path, size=(height, width))
    res = pipe(image, pipe.default_cameras("orbit", cfg.num_frames, resolution=resolution), prompt, steps=steps,
               seed=seed)
    first = CameraPath(res.cameras.viewmats[:1], res.cameras.Ks[:1], width, height,
                       torch.zeros(1, dtype=res.cameras.viewmats.dtype, device=res.cameras.viewmats.device))
    colors, _, _ = _render(res, first)
    pred, target = colors.permute(0, 3, 1, 2), image.permute(2, 0, 1)[None].cpu()
    small = lambda x: F.interpolate(x, size=(cfg.height, cfg.width), mode="area")  # noqa: E731
    return {"photo_psnr": image_psnr(pred, target), "photo_psnr_model": image_psnr(small(pred), small(target)),
            "photo_thumbnail": image_psnr(thumbnail(target), target),
            "photo_thumbnail_model": image_psnr(thumbnail(small(target)), small(target))}


def aggregate(evals: list[ClipEvaluation]) -> dict[str, float]:
    """Mean over clips of every metric, diagnostic, baseline and :data:`DIRECTION` key (NaNs skipped), how many clips
    took part in the direction test (``direction_clips``), and :func:`binned_keys`: the PSNR
    of the frames' mean MSE pooled over all clips, per view-angle bin and in all. Raises ValueError when empty."""
    if not evals:
        raise ValueError("evals: no clip evaluations to aggregate")
    out = {k: statistics.fmean([e.metrics[k] for e in evals if not math.isnan(e.metrics[k])] or [float("nan")])
           for k in METRICS + DIAGNOSTICS + DEPTH_DIAGNOSTICS + BASELINES + DIRECTION}
    out["direction_clips"] = float(sum(not math.isnan(e.metrics["direction_caption"]) for e in evals))
    angles = torch.cat([e.angles for e in evals])
    for variant in ("model", *VARIANTS):
        mse = torch.cat([e.frame_mse[variant] for e in evals])
        out["psnr_pooled" if variant == "model" else f"psnr_pooled_{variant}"] = psnr_from_mse(float(mse.mean()))
        bins = binned_psnr(mse, angles)
        for name, (psnr, count) in bins.items():
            out[f"psnr_{name}" if variant == "model" else f"psnr_{name}_{variant}"] = psnr
            out[f"frames_{name}"] = float(count)
    return out


def evaluate_all(pipe: Diff4SplatPipeline, clips: list[dict], *, progress: bool = False, **kw
                 ) -> list[ClipEvaluation]:
    """:func:`evaluate_clip` of every clip (keywords passed on), with a tqdm bar when ``progress``."""
    return [evaluate_clip(pipe, c, **kw) for c in tqdm(clips, desc="evaluate", unit="clip", disable=not progress,
                                                        dynamic_ncols=True)]


@torch.no_grad()
def sampling_tradeoffs(pipe: Diff4SplatPipeline, clips: list[dict], nfes=(1, 2, 4, 8, 16, 32, 64),
                       reference_steps: int = 256) -> list[dict]:
    """Rows {sampler, nfe, steps, ms, latent_rms, psnr} of each sampler at each NFE (Euler: steps = NFE; Heun:
    NFE = 2·steps − 1): median wall time (device synchronised), RMS latent distance to a ``reference_steps`` Heun
    solve, and the renders' PSNR against the clip."""
    rows, refs = [], []
    for c in clips:
        cams, image = clip_inputs(pipe, c)
        refs.append((c, cams, image, pipe(image, cams, c["caption"], steps=reference_steps, sampler="heun").latents))
    for sampler in SAMPLERS:
        for nfe in nfes:
            steps = nfe if sampler == "euler" else max(1, math.ceil((nfe + 1) / 2))
            ms, rms, psnr = [], [], []
            for c, cams, image, ref in refs:
                synchronize(pipe.device)
                t0 = time.perf_counter()
                res = pipe(image, cams, c["caption"], steps=steps, sampler=sampler)
                synchronize(pipe.device)
                ms.append(1000 * (time.perf_counter() - t0))
                rms.append(float(((res.latents - ref) ** 2).mean().sqrt()))
                colors, _, _ = _render(res)
                psnr.append(image_psnr(colors.permute(0, 3, 1, 2), c["video"].permute(1, 0, 2, 3)))
            rows.append({"sampler": sampler, "nfe": 2 * steps - 1 if sampler == "heun" else steps, "steps": steps,
                         "ms": statistics.median(ms), "latent_rms": statistics.fmean(rms),
                         "psnr": statistics.fmean(psnr)})
    return rows


@torch.no_grad()
def stiffness_profile(pipe: Diff4SplatPipeline, clip: dict, steps: int = 16, substeps: int = 32,
                      seed: int = 0) -> list[dict]:
    """Rows {step, sigma, sigma_next, local_error, lipschitz} along the ``steps``-step schedule, from an accurate
    trajectory (``substeps`` Heun steps per interval): ``local_error`` the RMS of one Euler step against it,
    ``lipschitz`` ‖v(x+δ) − v(x)‖ / ‖δ‖ with ‖δ‖ = 1e-3·‖x‖."""
    cfg = pipe.config
    runtime = pipe.runtime
    cams, image = clip_inputs(pipe, clip)
    captured: dict = {}
    original = runtime.velocity

    def recorder(x, sigma, **cond):
        captured.setdefault("cond", cond)
        captured.setdefault("shape", x.shape)
        return original(x, sigma, **cond)

    runtime.velocity = recorder
    try:
        pipe(image, cams, clip["caption"], steps=1, sampler="euler", seed=seed)
    finally:
        del runtime.velocity  # restore the class method
    v = partial(original, **captured["cond"])  # σ as the sampler gives it (0-dim)

    dev = pipe.device
    gen = torch.Generator(device="cpu").manual_seed(seed)  # CPU draws, moved: the same numbers on every device
    x = torch.randn(captured["shape"], generator=gen, device=gen.device).to(dev)
    sig = sigma_schedule(steps, cfg.sampling.shift, dtype=torch.float64)
    rows = []
    for i in range(steps):
        s0, s1 = sig[i], sig[i + 1]
        sigmas = torch.linspace(float(s0), float(s1), substeps + 1, dtype=torch.float64, device=sig.device)
        fine = heun_sample(v, x, sigmas)
        v0 = v(x, s0)
        euler = x + (s1 - s0).to(x) * v0
        delta = torch.randn(x.shape, generator=gen, device=gen.device).to(dev)
        delta = delta * (1e-3 * x.norm() / delta.norm())
        lip = float((v(x + delta, s0) - v0).norm() / delta.norm())
        rows.append({"step": i, "sigma": float(s0), "sigma_next": float(s1),
                     "local_error": float(((euler - fine) ** 2).mean().sqrt()), "lipschitz": lip})
        x = fine
    return rows
