"""Evaluation on held-out scenes: image, depth and motion metrics of generated 4D scenes, baselines and
ablations that show whether the generator matters, and the error against run time of the samplers.

The command, its tables and its argument checks are :mod:`training.evaluate_cli`; the metric functions are
:mod:`training.eval_metrics`.

Per held-out clip (reference camera, T frames, model resolution), the scene is *generated* exactly as
``generate`` does it — from the clip's first frame, its camera path and its caption — and rendered
along the clip's cameras at the clip's times:

- ``psnr_input``/``ssim_input``: frame 0 (the input view at t = 0) against the ground truth;
- ``psnr_novel``/``ssim_novel``: frames 1…T−1 (new views at new times); PSNR of the MSE over those frames;
- ``depth_corr``: Pearson correlation of rendered and true metric depth over valid covered pixels; beside it
  (:data:`DEPTH_DIAGNOSTICS`) on the same pixels the scale it cannot see: ``depth_abs_rel`` and ``depth_scale``
  (:func:`training.eval_metrics.depth_errors`);
- ``motion_epe``: mean distance (metres) between tracked points predicted by the scene (the Gaussian
  at the track's frame-0 pixel, deformed to each time) and the true 3D tracks, visible points only.
  It is dominated by the frame-0 depth error (``motion_epe_t0``); the displacement error
  ``motion_disp_epe`` isolates motion (:func:`training.eval_metrics.motion_errors`);
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

Does the generator matter? On the same frames 1…T−1 (:data:`BASELINES`):

- ``psnr_novel_repeat``: the input frame repeated for every later frame (no model at all);
  ``psnr_novel_repeat_blur``: the same after a Gaussian blur (σ 1.5 px, kernel 7);
- ``psnr_novel_noise``: noise-latent ablation — the same clip generated with the sampled video latents
  replaced by pure noise (``video_latents``, :func:`training.eval_metrics.ablation_noise`; frame 0 is still
  the photograph's latent): what the generated video contributes;
- ``psnr_novel_gt``: the oracle — the latents of the true video (``vae.encode_latents``) instead of sampled
  ones (PyTorch models only, NaN for another runtime); with ``motion_epe_gt``/``motion_disp_epe_gt`` the
  LDRM's motion on ground-truth latents, to compare with its motion on generated latents;
- ``psnr_novel_video``: the generated video itself — the sampled latents decoded by the VAE
  (``runtime.decode_latents``, clamped to [0, 1]), frame i against true frame i, no 3D at all: what the
  generator alone shows at each camera, against which the scene's renders (which keep the photograph's pixels
  and must be one consistent 4D scene) and ``vae_psnr`` (the decoder's ceiling) are read.

PSNR by view angle (:func:`training.eval_metrics.view_angles`: rotation angle of R_i R_0ᵀ from the input
camera, which for an orbit is its sweep): the frames 1…T−1 of all clips are split into the bins of
:data:`training.eval_metrics.ANGLE_BINS` (0–15°, 15–45°, 45–90°, > 90°); each bin's PSNR is that of the
mean MSE over its frames (:func:`training.eval_metrics.binned_psnr`). Keys ``psnr_<bin>`` (the model),
``psnr_<bin>_<variant>`` for ``noise``, ``gt``, ``video``, ``repeat``, ``repeat_blur``, and ``frames_<bin>``
(frame count).

With ``--photo IMAGE`` it also reports :func:`photo_fidelity`: the scene generated from a real photograph at the
output resolution (``--resolution``, default 256), rendered from the input camera at t = 0, against that
photograph there and at the model resolution, beside the 8×8 thumbnail. The held-out clips are evaluated at
their own resolution (the model's: the data is 64²), which is then also the output resolution.

Devices: the pipeline (generation and rendering) runs on ``pipe.device`` (``--device``, default ``auto``: CUDA
when torch sees a GPU, else the CPU); the clips stay on the CPU and every metric is computed there, from CPU
copies of the renders and of the generated scene's points.
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

__all__ = ["evaluate_clip", "evaluate_clips", "evaluate_all", "aggregate", "ClipEvaluation", "sampling_tradeoffs",
           "photo_fidelity", "stiffness_profile", "METRICS", "DIAGNOSTICS", "DEPTH_DIAGNOSTICS", "BASELINES",
           "VARIANTS", "PHOTO_KEYS", "binned_keys", "scene_motion"]

METRICS = ("psnr_input", "ssim_input", "psnr_novel", "ssim_novel", "depth_corr", "motion_epe", "loop_psnr",
           "vae_psnr")
"""Reported metrics; higher is better except ``motion_epe`` (metres)."""

DIAGNOSTICS = ("motion_epe_t0", "motion_epe_hold", "motion_disp_epe", "motion_disp_hold", "motion_disp_d5",
               "motion_disp_d10", "motion_disp_hold_d5", "motion_disp_hold_d10", "motion_epe_gt",
               "motion_disp_epe_gt")
"""Reported beside the metrics to split ``motion_epe`` (metres, lower is better): ``motion_epe_t0`` is the
error at frame 0 alone (geometry: where the scene puts the tracked points before anything moves), and
``motion_epe_hold`` the error of holding each point at its frame-0 position (no motion). The predicted motion
helps where ``motion_epe`` < ``motion_epe_hold``; an identity deformation makes them equal. The absolute EPE
is dominated by the frame-0 depth error; ``motion_disp_epe`` (error of the displacement from frame 0) against
``motion_disp_hold`` (the true displacement, i.e. the error of no motion) isolates the motion, and
``motion_disp_d5``/``motion_disp_d10`` (higher is better) are the fractions of displacements within 5 / 10 cm, beside
``motion_disp_hold_d5``/``motion_disp_hold_d10`` of holding still. ``motion_epe_gt``/``motion_disp_epe_gt``: the
same for the scene generated from the true video's latents."""

DEPTH_DIAGNOSTICS = ("depth_abs_rel", "depth_scale")
"""Reported beside ``depth_corr`` on the same pixels (:func:`training.eval_metrics.depth_errors`): the mean
relative error (lower is better) and the median ratio of rendered to true depth (1 is right)."""

VARIANTS = ("noise", "gt", "video", "repeat", "repeat_blur")
"""Baselines and ablations scored on the model's novel frames (module docstring)."""

BASELINES = tuple(f"psnr_novel_{v}" for v in VARIANTS)
"""PSNR (dB) of each variant on frames 1…T−1 (mean over clips, like ``psnr_novel``)."""


def binned_keys() -> tuple[str, ...]:
    """Keys of the pooled novel frames, ``psnr_pooled``, ``psnr_pooled_<variant>``, and of the view-angle bins:
    ``psnr_<bin>``, ``psnr_<bin>_<variant>``, ``frames_<bin>`` per bin."""
    return ("psnr_pooled", *(f"psnr_pooled_{v}" for v in VARIANTS)) + tuple(
        k for name, _, _ in ANGLE_BINS for k in (f"psnr_{name}", *(f"psnr_{name}_{v}" for v in VARIANTS),
                                                 f"frames_{name}"))


def _held_out_clips(data: str | Path, height: int, width: int, num_frames: int, limit: int | None):
    ds = ClipDataset(data, ClipConfig(num_frames=num_frames, height=height, width=width, scenes="all",
                                      reference_camera="first", target_cameras="same", plucker="raw", seed=0))
    n = len(ds) if limit is None else min(limit, len(ds))
    return [ds[i] for i in range(n)]


@dataclass
class ClipEvaluation:
    """What :func:`evaluate_clip` measures on one clip.

    Attributes:
        name: the clip's scene name.  dynamic: whether the scene moves.
        max_angle: camera motion size, the largest view angle of the clip's cameras (degrees).
        metrics: {key: value} for :data:`METRICS`, :data:`DIAGNOSTICS`, :data:`DEPTH_DIAGNOSTICS` and
            :data:`BASELINES`.
        angles: (T−1,) view angles (degrees) of frames 1…T−1.
        frame_mse: {"model" or variant: (T−1,) float64 MSE of frames 1…T−1} (NaN where not available).
    """

    name: str
    dynamic: bool
    max_angle: float
    metrics: dict[str, float]
    angles: Tensor
    frame_mse: dict[str, Tensor] = field(default_factory=dict)


def scene_motion(pipe: Diff4SplatPipeline, res: GenerationResult, clip: dict) -> dict[str, float]:
    """:func:`motion_errors` of a generated scene: each track's frame-0 pixel → its front disk of the photo layer
    (``res.gaussian_index``; the photo layer's front disks are the first H·W slots of the unpruned scene, at the
    output resolution, which is the clip's) → its positions at the clip's times. Computed on the CPU (the clip's
    device) from CPU copies of the scene's points."""
    H, W = res.cameras.height, res.cameras.width
    tracks, vis = clip["tracks"], clip["track_visibility"] & clip["track_mask"][:, None]
    idx, ok = track_query_index(tracks[:, 0], clip["Ks"][0], W, H, vis[:, 0])
    kept = kept_index_map(res.gaussian_index.cpu(), res.num_slots)
    g_idx = kept[idx]
    ok = ok & (g_idx >= 0)
    # gate 0: every Gaussian at every time (a scene with temporal opacity leaves the faded ones out by default)
    pred = torch.stack([res.scene.at(t, gate=0).means.cpu()[g_idx.clamp(min=0)] for t in res.cameras.times.tolist()], 1)
    return motion_errors(pred, tracks, vis & ok[:, None])


def _render(res: GenerationResult, cameras: CameraPath | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`render_path` of a generated scene on its device (the cameras, default its own path, moved there) with
    the scene's dilation and background (``res.eps2d``, ``res.background``), returned as CPU tensors."""
    cameras = res.cameras if cameras is None else cameras
    out = render_path(res.scene, cameras.to(res.scene.canonical.means.device), eps2d=res.eps2d,
                      background=res.background)
    return out[0].cpu(), out[1].cpu(), out[2].cpu()


@torch.no_grad()
def evaluate_clip(pipe: Diff4SplatPipeline, clip: dict, *, steps: int | None = None, sampler: str | None = None,
                  seed: int = 0) -> ClipEvaluation:
    """Metrics, baselines and ablations of one held-out clip (module docstring).

    Generates the clip's scene three times (sampled latents, noise latents, and — PyTorch models only —
    the true video's latents) plus the loop-closure orbit of a static clip; the sampled latents' frames
    (``psnr_novel_video``) are the pipeline's own decode where it made one (``generated_colors: video``), else
    decoded here; on ``pipe.device``; ``clip``'s
    tensors are CPU tensors (:func:`_held_out_clips`) and the metrics are computed on the CPU.

    Raises:
        ValueError: a clip of fewer than 2 frames (nothing to score as novel views).
    """
    cfg = pipe.config
    T = clip["video"].shape[1]
    if T < 2:
        raise ValueError(f"clip must have at least 2 frames, got {T}")
    cams = CameraPath(clip["viewmats"].double(), clip["Ks"].double(), cfg.width, cfg.height, clip["times"].double())
    image = clip["video"][:, 0].permute(1, 2, 0)
    gt = clip["video"].permute(1, 0, 2, 3)
    gen = dict(steps=steps, sampler=sampler, seed=seed)

    res = pipe(image, cams, clip["caption"], **gen)
    colors, depths, alphas = _render(res)
    pred = colors.permute(0, 3, 1, 2)
    mse = {"model": frame_mse(pred[1:], gt[1:]), **repeat_baselines(clip["video"])}
    decoded = res.video if res.video is not None else pipe.runtime.decode_latents(res.latents)  # decoded once
    video = ((decoded[0].float().cpu() + 1) / 2).clamp(0, 1)  # (3, T, h, w)
    mse["video"] = frame_mse(video.permute(1, 0, 2, 3)[1:], gt[1:])
    out = {"psnr_input": image_psnr(pred[:1], gt[:1]), "ssim_input": image_ssim(pred[:1], gt[:1]),
           "ssim_novel": image_ssim(pred[1:], gt[1:])}
    valid = clip["depth_valid"] & (alphas > 0.5)
    out["depth_corr"] = (pearson(depths[valid].double(), clip["depth"][valid].double())
                         if valid.sum() > 1 else float("nan"))
    out.update(depth_errors(depths[valid], clip["depth"][valid]))
    out.update(scene_motion(pipe, res, clip))
    out["loop_psnr"] = _loop_psnr(pipe, image, clip, T, **gen)

    noisy = pipe(image, cams, clip["caption"], video_latents=ablation_noise(res.latents.shape, seed), **gen)
    mse["noise"] = frame_mse(_render(noisy)[0][1:].permute(0, 3, 1, 2), gt[1:])
    mse["gt"] = torch.full((T - 1,), float("nan"), dtype=torch.float64, device="cpu")
    out["vae_psnr"] = out["motion_epe_gt"] = out["motion_disp_epe_gt"] = float("nan")
    if pipe.model is not None:
        # through the runtime, as the pipeline does: in its dtype, and on the device with model offload
        latents = pipe.runtime.encode_image(clip["video"][None].to(pipe.device) * 2 - 1)
        recon = (pipe.runtime.decode_latents(latents)[0].cpu() + 1) / 2
        out["vae_psnr"] = image_psnr(recon.permute(1, 0, 2, 3), gt)
        oracle = pipe(image, cams, clip["caption"], video_latents=latents, **gen)
        mse["gt"] = frame_mse(_render(oracle)[0][1:].permute(0, 3, 1, 2), gt[1:])
        motion = scene_motion(pipe, oracle, clip)
        out["motion_epe_gt"], out["motion_disp_epe_gt"] = motion["motion_epe"], motion["motion_disp_epe"]
    out["psnr_novel"] = psnr_from_mse(float(mse["model"].mean()))
    out.update({f"psnr_novel_{v}": psnr_from_mse(float(mse[v].mean())) for v in VARIANTS})
    angles = view_angles(clip["viewmats"])
    return ClipEvaluation(name=str(clip.get("scene", "")), dynamic=bool(clip["dynamic"]),
                          max_angle=float(angles.max()), metrics=out, angles=angles[1:], frame_mse=mse)


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
    """How a real photograph comes back at the input view (dB, :func:`training.eval_metrics.image_psnr`).

    The scene is generated from the photograph (centre-cropped and resized to the output resolution,
    ``resolution`` pixels of height, as ``generate`` reads it; None: the model resolution) along the 360° orbit
    and rendered from the input camera at t = 0 (with the scene's dilation and background). Returns:
    ``photo_psnr`` against the photograph at the output resolution; ``photo_psnr_model``: the render and the
    photograph both area-averaged to the model resolution (64² for ``base``); ``photo_thumbnail`` /
    ``photo_thumbnail_model``: the 8×8 thumbnail baseline (:func:`training.eval_metrics.thumbnail`) at each.
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
    """Aggregate of clip evaluations: the mean over clips of every metric, diagnostic and baseline (NaNs —
    e.g. no visible tracks — skipped), and per view-angle bin (:func:`binned_keys`) the PSNR of the mean
    MSE over the frames 1…T−1 of all clips in the bin (NaN for an empty bin) and the bin's frame count; and
    ``psnr_pooled[_<variant>]``, the PSNR of the mean MSE over all those frames (every bin together: unlike the
    mean over clips, a baseline's exact 100 dB on a clip where nothing moves does not dominate it).

    Raises:
        ValueError: no clip evaluations.
    """
    if not evals:
        raise ValueError("evals: no clip evaluations to aggregate")
    out = {k: statistics.fmean([e.metrics[k] for e in evals if not math.isnan(e.metrics[k])] or [float("nan")])
           for k in METRICS + DIAGNOSTICS + DEPTH_DIAGNOSTICS + BASELINES}
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
    """:func:`evaluate_clip` of every clip (keyword arguments passed on); ``progress``: a tqdm bar over the clips
    on stderr."""
    return [evaluate_clip(pipe, c, **kw) for c in tqdm(clips, desc="evaluate", unit="clip", disable=not progress,
                                                        dynamic_ncols=True)]


def evaluate_clips(pipe: Diff4SplatPipeline, clips: list[dict], **kw) -> dict[str, float]:
    """:func:`aggregate` of :func:`evaluate_all`: {key: value} for :data:`METRICS`, :data:`DIAGNOSTICS`,
    :data:`DEPTH_DIAGNOSTICS`, :data:`BASELINES` and :func:`binned_keys`."""
    return aggregate(evaluate_all(pipe, clips, **kw))


@torch.no_grad()
def sampling_tradeoffs(pipe: Diff4SplatPipeline, clips: list[dict], nfes=(1, 2, 4, 8, 16, 32, 64),
                       reference_steps: int = 256) -> list[dict]:
    """Error against run time of the Euler and Heun samplers.

    For each clip, the DiT's ODE is integrated with ``reference_steps`` Heun steps as the reference;
    each sampler at each NFE (Euler: steps = NFE; Heun: steps = ⌈(NFE+1)/2⌉, NFE = 2·steps − 1) is
    compared by the RMS latent distance to the reference, its wall time, and the PSNR of the
    generated scene's renders against the ground-truth clip. The clock is read after
    :func:`diff4splat.utils.devices.synchronize` (the device's queued work counted).

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
    """How the sampler's error behaves along σ, especially near σ → 0.

    Along the ``steps``-step schedule (with the config's shift), from the state x(σ_i) of an accurate
    trajectory (each interval integrated with ``substeps`` Heun steps), reports for every step:
    ``local_error`` — RMS difference between one Euler step σ_i → σ_{i+1} and the accurate state
    x(σ_{i+1}) (the local truncation error, ≈ ½ h² ‖dv/dσ‖), and ``lipschitz`` — a finite-difference
    estimate ‖v(x+δ, σ_i) − v(x, σ_i)‖ / ‖δ‖ (‖δ‖ = 1e-3·‖x‖) of how stiff the velocity field is there.

    Returns:
        Rows {step, sigma, sigma_next, local_error, lipschitz}.
    """
    cfg = pipe.config
    runtime = pipe.runtime
    cams = CameraPath(clip["viewmats"].double(), clip["Ks"].double(), cfg.width, cfg.height, clip["times"].double())
    image = clip["video"][:, 0].permute(1, 2, 0)
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
