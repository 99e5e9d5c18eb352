"""Metric functions of ``diff4splat evaluate`` (:mod:`training.evaluate`): PSNR/SSIM, view angles and their bins,
no-model baselines, motion errors, bootstrap intervals. Pure functions of tensors on their inputs' device."""
from __future__ import annotations

import math

import kornia
import torch
import torch.nn.functional as F
from torch import Tensor

from diff4splat.cameras import unproject_depth

__all__ = ["PSNR_CAP", "ANGLE_BINS", "psnr_from_mse", "image_psnr", "image_ssim", "thumbnail", "pearson",
           "depth_errors", "frame_mse", "view_angles", "angle_bin", "binned_psnr", "repeat_baselines", "motion_errors",
           "kept_index_map", "ablation_noise", "BLUR_SIGMA", "BLUR_KERNEL", "covisible_mask", "masked_psnr",
           "blockiness", "BOOTSTRAP_DRAWS", "BOOTSTRAP_INTERVAL", "gap_intervals", "DELTA_THRESHOLDS_M"]

PSNR_CAP = 100.0
"""PSNR of identical images (MSE 0) is reported as this many dB instead of infinity."""

ANGLE_BINS: tuple[tuple[str, float, float], ...] = (("0_15", 0.0, 15.0), ("15_45", 15.0, 45.0),
                                                    ("45_90", 45.0, 90.0), ("90_180", 90.0, 180.0))
"""View-angle bins (name, low, high), degrees: low ≤ θ < high (the last includes 180°); keys ``psnr_<name>``."""

BLUR_SIGMA, BLUR_KERNEL = 1.5, 7
"""Gaussian blur of the ``repeat_blur`` baseline: σ in pixels, kernel size (``kornia.filters.gaussian_blur2d``)."""


def psnr_from_mse(mse: float) -> float:
    """PSNR in dB of images in [0, 1] from their MSE: −10·log10(mse), capped at :data:`PSNR_CAP`; NaN for NaN."""
    if math.isnan(mse):
        return float("nan")
    if mse <= 10 ** (-PSNR_CAP / 10):
        return PSNR_CAP
    return -10.0 * math.log10(mse)


def frame_mse(pred: Tensor, gt: Tensor) -> Tensor:
    """Per-frame MSE (F,) float64 of predictions (F, 3, H, W), clamped to [0, 1], against gt in [0, 1].
    Raises ValueError when the shapes differ."""
    if pred.shape != gt.shape:
        raise ValueError(f"pred has shape {tuple(pred.shape)}, gt {tuple(gt.shape)}: they must match")
    return ((pred.double().clamp(0, 1) - gt.double()) ** 2).flatten(1).mean(1)


def image_psnr(pred: Tensor, gt: Tensor) -> float:
    """PSNR in dB of predictions (F, 3, H, W) against gt in [0, 1], every pixel of every frame pooled."""
    return psnr_from_mse(float(frame_mse(pred, gt).mean()))


def thumbnail(x: Tensor, size: int = 8) -> Tensor:
    """Thumbnail baseline of images (F, 3, H, W): area-averaged to ``size``² and upsampled bilinearly to H×W."""
    small = F.adaptive_avg_pool2d(x, size)
    return F.interpolate(small, size=x.shape[-2:], mode="bilinear", align_corners=False)


def image_ssim(pred: Tensor, gt: Tensor) -> float:
    """Mean SSIM (kornia, 11×11 Gaussian window, σ 1.5) of predictions (F, 3, H, W), clamped to [0, 1], against gt;
    the border pixels are included (reflection padding), unlike skimage's ``structural_similarity``."""
    return float(kornia.metrics.ssim(pred.clamp(0, 1), gt, 11).mean())


def pearson(a: Tensor, b: Tensor) -> float:
    """Pearson correlation of two (N,) tensors; 0 when either is constant."""
    a, b = a - a.mean(), b - b.mean()
    den = math.sqrt(float((a * a).sum()) * float((b * b).sum()))
    return float((a * b).sum()) / den if den > 0 else 0.0


def depth_errors(pred: Tensor, true: Tensor) -> dict[str, float]:
    """Scale-aware depth errors of (N,) z-depths in metres (true > 0): ``depth_abs_rel`` = mean |pred − true| / true
    (AbsRel, Eigen et al. 2014), ``depth_scale`` = median pred / true (1: right scale); NaN for both when N = 0."""
    if pred.numel() == 0:
        return {"depth_abs_rel": float("nan"), "depth_scale": float("nan")}
    pred, true = pred.double(), true.double()
    return {"depth_abs_rel": float(((pred - true).abs() / true).mean()), "depth_scale": float((pred / true).median())}


def view_angles(viewmats: Tensor) -> Tensor:
    """View angle (T,) float64 degrees in [0, 180] of each camera of ``viewmats`` (T, 4, 4) world-to-camera from
    the first: the rotation angle of R_i R_0ᵀ, atan2(‖v‖, tr − 1) with v the skew part (‖v‖ = 2 sin θ). A pure
    translation has θ = 0; for an orbit it is the sweep angle up to 180°. Raises ValueError unless (T, 4, 4), T ≥ 1.
    """
    if viewmats.dim() != 3 or tuple(viewmats.shape[1:]) != (4, 4) or viewmats.shape[0] < 1:
        raise ValueError(f"viewmats must have shape (T, 4, 4) with T ≥ 1, got {tuple(viewmats.shape)}")
    R = viewmats[:, :3, :3].double()
    rel = R @ R[0].T  # (T, 3, 3)
    trace = rel.diagonal(dim1=-2, dim2=-1).sum(-1)
    v = torch.stack([rel[:, 2, 1] - rel[:, 1, 2], rel[:, 0, 2] - rel[:, 2, 0], rel[:, 1, 0] - rel[:, 0, 1]], -1)
    return torch.rad2deg(torch.atan2(v.norm(dim=-1), trace - 1.0))


def angle_bin(angles: Tensor) -> Tensor:
    """Index (…,) long into :data:`ANGLE_BINS` of each view angle (…,) in degrees [0, 180]."""
    highs = torch.tensor([hi for _, _, hi in ANGLE_BINS[:-1]], dtype=torch.float64, device=angles.device)
    return torch.bucketize(angles.double(), highs, right=True)


def binned_psnr(mse: Tensor, angles: Tensor) -> dict[str, tuple[float, int]]:
    """{bin name: (PSNR dB of the bin's mean MSE, NaN if empty; frames)} of per-frame ``mse`` (F,) and view
    ``angles`` (F,) degrees, for every bin of :data:`ANGLE_BINS`. Raises ValueError unless both are (F,)."""
    if mse.shape != angles.shape or mse.dim() != 1:
        raise ValueError(f"mse {tuple(mse.shape)} and angles {tuple(angles.shape)} must be matching (F,) tensors")
    idx = angle_bin(angles)
    out = {}
    for i, (name, _, _) in enumerate(ANGLE_BINS):
        sel = mse[idx == i]
        out[name] = (psnr_from_mse(float(sel.mean())) if sel.numel() else float("nan"), int(sel.numel()))
    return out


DELTA_THRESHOLDS_M = (0.05, 0.10)
"""Displacement-error thresholds of :func:`motion_errors`' δ fractions, metres."""
BOOTSTRAP_DRAWS = 2000
"""Resamplings of the clips in :func:`gap_intervals`."""
BOOTSTRAP_INTERVAL = (0.05, 0.95)
"""Quantiles of :func:`gap_intervals`' percentile interval (a 90 % interval)."""


def gap_intervals(
    mse_model: list[Tensor],  # per clip: (F_c,) frame MSE of the model
    mse_other: list[Tensor],  # per clip: (F_c,) frame MSE of a baseline or ablation on the same frames
    angles: list[Tensor],  # per clip: (F_c,) view angles, degrees
    *,
    draws: int = BOOTSTRAP_DRAWS,
    seed: int = 0,
) -> dict[str, tuple[float, float, float, int]]:
    """PSNR gap 10·log10(Σ mse_other / Σ mse_model) of the model over another variant per view-angle bin, with a
    percentile bootstrap interval (Efron & Tibshirani 1993) resampling *clips* ``draws`` times (CPU generator seeded
    with ``seed``, float64 sums on the CPU).

    Returns {``"all"`` and each bin: (gap dB, low, high at :data:`BOOTSTRAP_INTERVAL`, clips with frames there)};
    NaN for a bin with no frame; a zero MSE gives ±inf, and the interval then takes the draws just outside its ends.
    Raises ValueError: no clips, lists of different lengths, a clip's tensors of different shapes, draws < 1.
    """
    if not mse_model or not len(mse_model) == len(mse_other) == len(angles):
        raise ValueError(f"need one tensor per clip in each list, got {len(mse_model)}, {len(mse_other)}, "
                         f"{len(angles)}")
    if any(not a.shape == b.shape == c.shape for a, b, c in zip(mse_model, mse_other, angles, strict=True)):
        raise ValueError("each clip's mse_model, mse_other and angles must have the same (F_c,) shape")
    if draws < 1:
        raise ValueError(f"draws must be ≥ 1, got {draws}")
    names = ["all"] + [name for name, _, _ in ANGLE_BINS]
    # (C, bins) sums of each variant's MSE and frame counts; column 0 pools every frame. Statistics on the CPU.
    cpu = torch.device("cpu")
    sums = torch.zeros(2, len(mse_model), len(names), dtype=torch.float64, device=cpu)
    counts = torch.zeros(len(mse_model), len(names), dtype=torch.float64, device=cpu)
    for c, (m, o, a) in enumerate(zip(mse_model, mse_other, angles, strict=True)):
        idx = angle_bin(a.detach().cpu()) + 1
        for k, x in enumerate((m, o)):
            x = x.detach().cpu().double()
            sums[k, c, 0] = x.sum()
            sums[k, c].index_add_(0, idx, x)
        counts[c, 0] = a.numel()
        counts[c].index_add_(0, idx, torch.ones(a.numel(), dtype=torch.float64, device=cpu))
    gen = torch.Generator(device=cpu).manual_seed(seed)
    picks = torch.randint(len(mse_model), (draws, len(mse_model)), generator=gen, device=cpu)
    weights = torch.zeros(draws, len(mse_model), dtype=torch.float64, device=cpu).scatter_add_(
        1, picks, torch.ones(picks.shape, dtype=torch.float64, device=cpu))  # (draws, C): how often each clip was drawn
    gaps = 10 * torch.log10((weights @ sums[1]) / (weights @ sums[0]))  # (draws, bins)
    gaps[(weights @ counts) == 0] = float("nan")
    levels = torch.tensor(BOOTSTRAP_INTERVAL, dtype=torch.float64, device=cpu)
    out = {}
    for b, name in enumerate(names):
        n = counts[:, b].sum()
        point = float(10 * torch.log10(sums[1, :, b].sum() / sums[0, :, b].sum())) if n else float("nan")
        g = gaps[:, b]
        g = g[~g.isnan()]
        if not g.numel():
            q = [math.nan] * 2
        elif bool(g.isinf().any()):  # a zero MSE: interpolating between ±inf draws gives NaN; take the draws
            q = [float(torch.quantile(g, levels[0], interpolation="lower")),  # outside the interval's ends instead
                 float(torch.quantile(g, levels[1], interpolation="higher"))]
        else:
            q = torch.quantile(g, levels).tolist()
        out[name] = (point, q[0], q[1], int((counts[:, b] > 0).sum()))
    return out


def repeat_baselines(video: Tensor) -> dict[str, Tensor]:
    """{"repeat", "repeat_blur": (T−1,) float64 MSE} of frames 1…T−1 of ``video`` (3, T, H, W) in [0, 1] against
    frame 0 repeated, unblurred or blurred (:data:`BLUR_SIGMA`, :data:`BLUR_KERNEL`). Raises ValueError unless T ≥ 2.
    """
    if video.dim() != 4 or video.shape[0] != 3 or video.shape[1] < 2:
        raise ValueError(f"video must have shape (3, T, H, W) with T ≥ 2, got {tuple(video.shape)}")
    frames = video.permute(1, 0, 2, 3).float()  # (T, 3, H, W)
    first, later = frames[:1], frames[1:]
    # σ as a tensor on the frames' device (kornia makes a tuple's check tensor on torch's default device)
    sigma = torch.tensor([[BLUR_SIGMA, BLUR_SIGMA]], dtype=first.dtype, device=first.device)
    blurred = kornia.filters.gaussian_blur2d(first, (BLUR_KERNEL, BLUR_KERNEL), sigma)
    return {"repeat": frame_mse(first.expand_as(later), later),
            "repeat_blur": frame_mse(blurred.expand_as(later), later)}


def motion_errors(pred: Tensor, tracks: Tensor, mask: Tensor) -> dict[str, float]:
    """Errors in metres of predicted trajectories ``pred`` (N, T, 3) against true ``tracks`` (N, T, 3) over the
    (track, frame) pairs of ``mask`` (N, T) bool; a mean over no pairs is NaN.

    ``motion_epe`` mean ‖p̂_t − p_t‖; ``motion_epe_t0`` the same at frame 0; ``motion_epe_hold`` mean ‖p̂_0 − p_t‖;
    over pairs t ≥ 1 visible at 0 and t: ``motion_disp_epe`` mean ‖(p̂_t − p̂_0) − (p_t − p_0)‖ (free of the
    frame-0 depth error), ``motion_disp_hold`` mean ‖p_t − p_0‖, ``motion_disp_d5``/``_d10`` and
    ``motion_disp_hold_d5``/``_d10`` the fractions under :data:`DELTA_THRESHOLDS_M` (TAPVid-3D's δ, Koppula et al.
    2024). Raises ValueError unless pred and tracks are both (N, T, 3) and mask (N, T).
    """
    if pred.shape != tracks.shape or pred.dim() != 3 or pred.shape[-1] != 3 or mask.shape != pred.shape[:2]:
        raise ValueError(f"pred {tuple(pred.shape)} and tracks {tuple(tracks.shape)} must be (N, T, 3) and "
                         f"mask {tuple(mask.shape)} (N, T)")
    pred, tracks, mask = pred.double(), tracks.double(), mask.bool()

    def mean(x: Tensor, m: Tensor) -> float:
        return float(x[m].mean()) if bool(m.any()) else float("nan")

    err = (pred - tracks).norm(dim=-1)
    moved = mask[:, 1:] & mask[:, :1]
    true_disp = tracks[:, 1:] - tracks[:, :1]
    disp_err = (pred[:, 1:] - pred[:, :1] - true_disp).norm(dim=-1)
    return {"motion_epe": mean(err, mask), "motion_epe_t0": mean(err[:, 0], mask[:, 0]),
            "motion_epe_hold": mean((pred[:, :1] - tracks).norm(dim=-1), mask),
            "motion_disp_epe": mean(disp_err, moved),
            "motion_disp_hold": mean(true_disp.norm(dim=-1), moved),
            **{f"motion_disp_d{round(d * 100)}": mean((disp_err < d).double(), moved) for d in DELTA_THRESHOLDS_M},
            **{f"motion_disp_hold_d{round(d * 100)}": mean((true_disp.norm(dim=-1) < d).double(), moved)
               for d in DELTA_THRESHOLDS_M}}


def kept_index_map(gaussian_index: Tensor, total: int) -> Tensor:
    """Inverse of the pruning index ``gaussian_index`` (M,) (``GenerationResult.gaussian_index``): (total,) int64,
    the kept Gaussian of each unpruned slot, −1 if pruned. Raises ValueError on an index outside [0, total) or
    repeated."""
    idx = gaussian_index.long().reshape(-1)
    if idx.numel() and (int(idx.min()) < 0 or int(idx.max()) >= total):
        raise ValueError(f"gaussian_index must lie in [0, {total}), got [{int(idx.min())}, {int(idx.max())}]")
    if idx.unique().numel() != idx.numel():
        raise ValueError("gaussian_index has repeated entries")
    kept = torch.full((total,), -1, dtype=torch.long, device=idx.device)
    kept[idx] = torch.arange(idx.numel(), device=idx.device)
    return kept


def ablation_noise(shape: tuple[int, ...] | torch.Size, seed: int, device: str | torch.device = "cpu") -> Tensor:
    """Noise latents N(0, I) float32 of ``shape`` on ``device`` for the noise-latent ablation: the second draw of a
    CPU generator seeded with ``seed`` (the first is the sampler's own starting noise), the same on every device."""
    gen = torch.Generator(device="cpu").manual_seed(seed)
    torch.randn(tuple(shape), generator=gen, device=gen.device)  # the sampler's starting noise for this seed
    return torch.randn(tuple(shape), generator=gen, device=gen.device).to(device)


def covisible_mask(
    depth: Tensor,  # (H, W) z-depth of the evaluated view, metres (+inf where unknown)
    viewmat: Tensor,  # (4, 4) world-to-camera of the evaluated view (OpenCV)
    K: Tensor,  # (3, 3) pixels
    train_depths: Tensor,  # (N, H', W') z-depth of the training views at the same time, metres
    train_viewmats: Tensor,  # (N, 4, 4)
    train_Ks: Tensor,  # (N, 3, 3)
    rel_tol: float = 0.03,
) -> Tensor:
    """(H, W) bool: pixels of an evaluation view co-visible in some training view (DyCheck's mask, Gao et al. 2022
    §4): the back-projected point lands inside that view with z > 0 and z ≤ (1 + rel_tol) × its depth at the nearest
    pixel. Non-finite depth counts as co-visible. Raises ValueError on shapes other than the comments above."""
    if depth.dim() != 2 or train_depths.dim() != 3 or train_viewmats.shape[0] != train_depths.shape[0] \
            or train_Ks.shape[0] != train_depths.shape[0]:
        raise ValueError(f"depth must be (H, W) and train_depths (N, H', W') with N viewmats and Ks, got "
                         f"{tuple(depth.shape)}, {tuple(train_depths.shape)}, {tuple(train_viewmats.shape)}, "
                         f"{tuple(train_Ks.shape)}")
    finite = torch.isfinite(depth)
    pts = unproject_depth(viewmat[None].double(), K[None].double(), depth[None].double())[0].reshape(-1, 3)
    pts = torch.where(finite.reshape(-1, 1), pts, torch.zeros_like(pts))
    seen = ~finite.reshape(-1)
    h, w = train_depths.shape[1:]
    for d, vm, k in zip(train_depths, train_viewmats.double(), train_Ks.double(), strict=True):
        cam = pts @ vm[:3, :3].T + vm[:3, 3]
        z = cam[:, 2]
        uv = (cam @ k.T)[:, :2] / z.clamp_min(1e-12)[:, None]
        col, row = torch.floor(uv[:, 0]), torch.floor(uv[:, 1])
        inside = (z > 0) & (col >= 0) & (col < w) & (row >= 0) & (row < h)
        ref = d.double()[row.clamp(0, h - 1).long(), col.clamp(0, w - 1).long()]
        seen |= inside & (z <= ref * (1.0 + rel_tol))
    return seen.reshape(depth.shape)


def masked_psnr(pred: Tensor, gt: Tensor, mask: Tensor) -> float:
    """DyCheck's mPSNR in dB of ``pred`` (F, H, W, 3), clamped to [0, 1], against ``gt`` over the pixels of ``mask``
    (F, H, W); NaN when the mask is empty. Raises ValueError on other shapes."""
    if pred.shape != gt.shape or mask.shape != pred.shape[:-1]:
        raise ValueError(f"pred {tuple(pred.shape)}, gt {tuple(gt.shape)} and mask {tuple(mask.shape)} "
                         "must be (F, H, W, 3), (F, H, W, 3), (F, H, W)")
    if not bool(mask.any()):
        return float("nan")
    se = ((pred.double().clamp(0, 1) - gt.double()) ** 2)[mask]
    return psnr_from_mse(float(se.mean()))


def blockiness(x: Tensor, block: int) -> float:
    """Blockiness of maps ``x`` (..., H, W): mean squared neighbour difference across the borders of a
    ``block``-pixel grid over the same inside the blocks (≈ 1 for natural images, ≫ 1 for per-token blocks)."""

    dx = (x[..., :, 1:] - x[..., :, :-1]) ** 2  # (..., H, W − 1): between columns j and j + 1
    dy = (x[..., 1:, :] - x[..., :-1, :]) ** 2
    bx = (torch.arange(dx.shape[-1], device=x.device) + 1) % block == 0
    by = (torch.arange(dy.shape[-2], device=x.device) + 1) % block == 0
    border = torch.cat([dx[..., bx].flatten(), dy[..., by, :].flatten()])
    inside = torch.cat([dx[..., ~bx].flatten(), dy[..., ~by, :].flatten()])
    return float(border.mean() / inside.mean().clamp_min(1e-20))
