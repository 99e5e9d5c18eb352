"""Metric functions of ``diff4splat evaluate`` (:mod:`training.evaluate`): PSNR/SSIM/correlation, the
view angle of a camera and its bins, the no-model baselines, the motion errors and the map from pixels
to kept Gaussians. Pure functions of tensors, computed on the device of their inputs (which must share one);
the evaluation itself (generation, rendering) is in :mod:`training.evaluate`.
"""
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
"""View-angle bins (name, low, high) in degrees: a frame of view angle θ falls in the bin with
low ≤ θ < high (the last bin includes 180°). Names give the metric keys ``psnr_<name>``."""

BLUR_SIGMA, BLUR_KERNEL = 1.5, 7
"""Gaussian blur of the ``repeat_blur`` baseline: σ in pixels, kernel size (``kornia.filters.gaussian_blur2d``)."""


def psnr_from_mse(mse: float) -> float:
    """PSNR in dB of images in [0, 1] from their mean squared error: −10·log10(mse), capped at
    :data:`PSNR_CAP` (MSE ≤ 10^(−cap/10), e.g. identical images); NaN for a NaN MSE."""
    if math.isnan(mse):
        return float("nan")
    if mse <= 10 ** (-PSNR_CAP / 10):
        return PSNR_CAP
    return -10.0 * math.log10(mse)


def frame_mse(pred: Tensor, gt: Tensor) -> Tensor:
    """Per-frame mean squared error (F,) float64 of predictions (F, 3, H, W), clamped to [0, 1] first,
    against ground truth (F, 3, H, W) in [0, 1].

    Raises:
        ValueError: ``pred`` and ``gt`` shapes differ.
    """
    if pred.shape != gt.shape:
        raise ValueError(f"pred has shape {tuple(pred.shape)}, gt {tuple(gt.shape)}: they must match")
    return ((pred.double().clamp(0, 1) - gt.double()) ** 2).flatten(1).mean(1)


def image_psnr(pred: Tensor, gt: Tensor) -> float:
    """PSNR in dB of predictions (F, 3, H, W) (clamped to [0, 1]) against ground truth in [0, 1], over
    all frames together (the MSE of every pixel of every frame); capped at :data:`PSNR_CAP`."""
    return psnr_from_mse(float(frame_mse(pred, gt).mean()))


def thumbnail(x: Tensor, size: int = 8) -> Tensor:
    """The thumbnail baseline of images (F, 3, H, W): area-averaged to ``size``×``size`` and upsampled bilinearly
    back to H×W — what an 8×8-compressing decoder would keep of the photograph without learning anything."""
    small = F.adaptive_avg_pool2d(x, size)
    return F.interpolate(small, size=x.shape[-2:], mode="bilinear", align_corners=False)


def image_ssim(pred: Tensor, gt: Tensor) -> float:
    """Mean SSIM (kornia, 11×11 Gaussian window, σ 1.5) of predictions (F, 3, H, W), clamped to [0, 1], against gt.

    The mean runs over every pixel, the 5-pixel border included (kornia pads by reflection; 3DGS's ``ssim`` zero-pads
    and also averages every pixel); skimage's ``structural_similarity`` leaves the border out, which differs most on
    small images: 0.9459 here vs 0.9481 at 32², 0.9464 vs 0.9468 at 64² on the same pair.
    """
    return float(kornia.metrics.ssim(pred.clamp(0, 1), gt, 11).mean())


def pearson(a: Tensor, b: Tensor) -> float:
    """Pearson correlation of two (N,) tensors; 0 when either is constant."""
    a, b = a - a.mean(), b - b.mean()
    den = math.sqrt(float((a * a).sum()) * float((b * b).sum()))
    return float((a * b).sum()) / den if den > 0 else 0.0


def depth_errors(pred: Tensor, true: Tensor) -> dict[str, float]:
    """Metric depth errors that :func:`pearson` cannot see: its correlation ignores the depth's scale.

    ``depth_abs_rel``: mean |pred − true| / true, the AbsRel of monocular depth benchmarks (Eigen, Puhrsch & Fergus
    2014); ``depth_scale``: median of pred / true, 1 for the right scale (< 1: the scene placed too near, which
    exaggerates the parallax of every novel view).

    Args:
        pred, true: (N,) z-depths in metres, true > 0 (the valid pixels only).

    Returns:
        {"depth_abs_rel": ≥ 0, "depth_scale": > 0}; NaN for both when N = 0.
    """
    if pred.numel() == 0:
        return {"depth_abs_rel": float("nan"), "depth_scale": float("nan")}
    pred, true = pred.double(), true.double()
    return {"depth_abs_rel": float(((pred - true).abs() / true).mean()), "depth_scale": float((pred / true).median())}


def view_angles(viewmats: Tensor) -> Tensor:
    """View angle of each camera from the first (the input camera), degrees in [0, 180].

    The view angle θ_i of camera i is the rotation angle of R_i R_0ᵀ, R_i = ``viewmats[i, :3, :3]`` the
    rotation of its world-to-camera matrix (R_i R_0ᵀ maps camera-0 coordinates to camera-i coordinates):
    θ = arccos((tr(R_i R_0ᵀ) − 1) / 2), computed as atan2(‖v‖, tr − 1) with
    v = (R₃₂ − R₂₃, R₁₃ − R₃₁, R₂₁ − R₁₂) (‖v‖ = 2 sin θ), accurate near 0° and 180°. It measures where the
    camera looks, not where it stands: a pure translation has θ = 0. For an orbit about the scene (the
    camera on a circle around a point, always looking at it: the ``orbit``/``arc`` presets, the synthetic
    clips' orbit cameras) it equals the orbit's sweep angle up to 180° (360° − sweep beyond).

    Args:
        viewmats: (T, 4, 4) world-to-camera matrices (OpenCV), T ≥ 1.

    Returns:
        (T,) float64 degrees; θ_0 = 0.

    Raises:
        ValueError: ``viewmats`` is not (T, 4, 4) with T ≥ 1.
    """
    if viewmats.dim() != 3 or tuple(viewmats.shape[1:]) != (4, 4) or viewmats.shape[0] < 1:
        raise ValueError(f"viewmats must have shape (T, 4, 4) with T ≥ 1, got {tuple(viewmats.shape)}")
    R = viewmats[:, :3, :3].double()
    rel = R @ R[0].T  # (T, 3, 3)
    trace = rel.diagonal(dim1=-2, dim2=-1).sum(-1)
    v = torch.stack([rel[:, 2, 1] - rel[:, 1, 2], rel[:, 0, 2] - rel[:, 2, 0], rel[:, 1, 0] - rel[:, 0, 1]], -1)
    return torch.rad2deg(torch.atan2(v.norm(dim=-1), trace - 1.0))


def angle_bin(angles: Tensor) -> Tensor:
    """Index (…,) long into :data:`ANGLE_BINS` of each view angle (…,) in degrees [0, 180]: the bin with
    low ≤ θ < high, 180° in the last bin. Every angle falls in exactly one bin."""
    highs = torch.tensor([hi for _, _, hi in ANGLE_BINS[:-1]], dtype=torch.float64, device=angles.device)
    return torch.bucketize(angles.double(), highs, right=True)


def binned_psnr(mse: Tensor, angles: Tensor) -> dict[str, tuple[float, int]]:
    """PSNR per view-angle bin of a set of frames (pooled over clips by the caller).

    The PSNR of a bin is that of the mean MSE over its frames (:func:`psnr_from_mse`), i.e. of all its
    pixels pooled, as ``psnr_novel`` is for the frames of one clip — not the mean of per-frame PSNRs,
    which a few near-perfect frames would dominate.

    Args:
        mse: (F,) per-frame MSE (:func:`frame_mse`).  angles: (F,) view angles, degrees.

    Returns:
        {bin name: (PSNR dB, NaN for an empty bin; number of frames)} for every bin of :data:`ANGLE_BINS`.

    Raises:
        ValueError: ``mse`` and ``angles`` not matching 1-D (F,) tensors.
    """
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
    """PSNR gap of the model over another variant per view-angle bin, with a bootstrap interval over clips.

    The gap of a set of frames is PSNR(model) − PSNR(other) of their pooled MSEs (:func:`binned_psnr`'s
    convention), 10·log10(Σ mse_other / Σ mse_model). A bin holding a few frames of one or two clips says little:
    the interval resamples the *clips* with replacement (the frames of a clip are not independent: they share its
    scene and its generation; Efron & Tibshirani 1993, the percentile bootstrap) ``draws`` times from a CPU
    generator seeded with ``seed``, and reports the :data:`BOOTSTRAP_INTERVAL` quantiles of the draws' gaps (draws
    whose clips have no frame in the bin are left out). Sums are float64 on the CPU.

    Args:
        mse_model, mse_other, angles: one (F_c,) tensor per clip, matching shapes, on any one device.
        draws: bootstrap resamplings, ≥ 1.  seed: the generator's seed.

    Returns:
        {``"all"`` and every bin name of :data:`ANGLE_BINS`: (gap dB, interval low, interval high, clips with
        frames there)}; NaN gap and interval for a bin with no frame. Gaps of capped PSNRs are not capped: a zero
        MSE gives ±inf, and where a draw's gap is infinite the interval's ends are the draws just outside it (no
        interpolation, which would give NaN).

    Raises:
        ValueError: no clips, lists of different lengths or a clip whose three tensors differ in shape, draws < 1.
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
    """Per-frame MSE of the no-model baselines on frames 1…T−1 of a clip.

    ``repeat``: the input frame 0 repeated for every later frame; ``repeat_blur``: the same after a
    Gaussian blur (σ = :data:`BLUR_SIGMA` px, kernel :data:`BLUR_KERNEL`, reflected border,
    ``kornia.filters.gaussian_blur2d``), which lowers the error where the true frames have moved.

    Args:
        video: (3, T, H, W) clip in [0, 1], T ≥ 2.

    Returns:
        {"repeat": (T−1,), "repeat_blur": (T−1,)} float64 MSE (:func:`frame_mse`).

    Raises:
        ValueError: ``video`` not (3, T, H, W) with T ≥ 2.
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
    """Errors (metres) of predicted point trajectories against true 3D tracks.

    - ``motion_epe``: mean ‖p̂_t − p_t‖ over the (track, frame) pairs of ``mask`` (all frames, frame 0 too);
    - ``motion_epe_t0``: the same at frame 0 alone (geometry: where the scene puts the points);
    - ``motion_epe_hold``: mean ‖p̂_0 − p_t‖ over ``mask``: holding each predicted point still;
    - ``motion_disp_epe``: mean ‖(p̂_t − p̂_0) − (p_t − p_0)‖ over tracks and frames t ≥ 1 visible at 0 and
      at t: the error of the predicted *displacement*, free of the frame-0 depth error that dominates the
      absolute ``motion_epe`` (a point placed 0.3 m too deep that moves exactly right has EPE 0.3 m and
      displacement error 0);
    - ``motion_disp_hold``: mean ‖p_t − p_0‖ over the same pairs: the displacement error of no motion;
    - ``motion_disp_d5``, ``motion_disp_d10``: the fraction of those pairs whose displacement error is below
      :data:`DELTA_THRESHOLDS_M` (5 cm, 10 cm; the 3D δ thresholds of TAPVid-3D's tracking accuracy, Koppula et al.
      2024, at fixed distances); ``motion_disp_hold_d5``, ``motion_disp_hold_d10`` the same of holding still.

    A mean over no pairs is NaN.

    Args:
        pred: (N, T, 3) predicted positions.  tracks: (N, T, 3) true positions.
        mask: (N, T) bool, the pairs to score (visible and with a predicted point).

    Returns:
        {key: value} for the nine keys above.

    Raises:
        ValueError: ``pred`` and ``tracks`` not the same (N, T, 3) shape, or ``mask`` not (N, T).
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
    """Inverse of the pruning index: (total,) long, the kept Gaussian of each unpruned slot, −1 if pruned.

    Args:
        gaussian_index: (M,) long, index of each kept Gaussian in the unpruned scene
            (``GenerationResult.gaussian_index``: the photo layer's 2·H·W slots first, front disks row-major, so
            slots 0…H·W−1 are the photograph's pixels; then the generated source frames).
        total: number of unpruned slots.

    Returns:
        (total,) int64 on ``gaussian_index``' device.

    Raises:
        ValueError: an index outside [0, total) or repeated.
    """
    idx = gaussian_index.long().reshape(-1)
    if idx.numel() and (int(idx.min()) < 0 or int(idx.max()) >= total):
        raise ValueError(f"gaussian_index must lie in [0, {total}), got [{int(idx.min())}, {int(idx.max())}]")
    if idx.unique().numel() != idx.numel():
        raise ValueError("gaussian_index has repeated entries")
    kept = torch.full((total,), -1, dtype=torch.long, device=idx.device)
    kept[idx] = torch.arange(idx.numel(), device=idx.device)
    return kept


def ablation_noise(shape: tuple[int, ...] | torch.Size, seed: int, device: str | torch.device = "cpu") -> Tensor:
    """Pure-noise latents N(0, I) of ``shape`` for the noise-latent ablation (float32, on ``device``).

    Drawn from a CPU generator seeded with ``seed`` *after* one draw of the same shape (that first draw
    is the pipeline's own starting noise for the seed), so the ablation's noise is independent of the
    sampler's starting point: a sampler that barely moves the noise is not credited with it. The draws are
    made on the CPU and moved, so they are the same numbers on every device.
    """
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
    """Pixels of an evaluation view whose surface point some training view sees (co-visibility).

    DyCheck (Gao et al. 2022, "Monocular Dynamic View Synthesis: A Reality Check", §4) scores novel views
    only where the test pixel is co-visible in the training views (mPSNR), because no method can know
    what no training camera saw. Here a pixel is co-visible when its back-projected point (the ground-truth
    depth) projects inside some training view (pixel centres at integer + 0.5) with z > 0 and is not
    occluded there: its z-depth in that view is at most ``(1 + rel_tol)`` times the training view's depth
    at the nearest pixel. Pixels with unknown depth (non-finite) count as co-visible, so they are never
    dropped from a masked metric.

    Returns:
        (H, W) bool on ``depth``'s device (all inputs on one device).

    Raises:
        ValueError: shapes that do not match the comments above.
    """
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
    """PSNR (:func:`psnr_from_mse`) of the squared error over the pixels where ``mask`` is true (DyCheck's
    mPSNR), every channel of every masked pixel of every frame pooled.

    Args:
        pred: (F, H, W, 3) clamped to [0, 1] first.  gt: (F, H, W, 3) in [0, 1].  mask: (F, H, W) bool.

    Returns:
        dB; NaN when the mask is empty.

    Raises:
        ValueError: shapes other than ``pred``, ``gt`` (F, H, W, 3) alike and ``mask`` (F, H, W).
    """
    if pred.shape != gt.shape or mask.shape != pred.shape[:-1]:
        raise ValueError(f"pred {tuple(pred.shape)}, gt {tuple(gt.shape)} and mask {tuple(mask.shape)} "
                         "must be (F, H, W, 3), (F, H, W, 3), (F, H, W)")
    if not bool(mask.any()):
        return float("nan")
    se = ((pred.double().clamp(0, 1) - gt.double()) ** 2)[mask]
    return psnr_from_mse(float(se.mean()))


def blockiness(x: Tensor, block: int) -> float:
    """How much a decoder paints its tokens into blocks: the mean squared difference of horizontally and vertically
    adjacent pixels across the borders of a ``block``-pixel grid (columns / rows j with (j + 1) mod block = 0),
    divided by the same mean inside the blocks. 1: the borders are like anywhere else (natural images: ≈ 1); a
    decoder that paints every token into its own block puts the steps on the borders (≫ 1).

    Args:
        x: (..., H, W) maps, channels (if any) before H and W.
        block: the grid's pitch in pixels (a decoder's token size, 8 for an 8×8-compressing VAE).

    Returns:
        The ratio (≥ 0; the inside mean is floored at 1e-20).
    """
    dx = (x[..., :, 1:] - x[..., :, :-1]) ** 2  # (..., H, W − 1): between columns j and j + 1
    dy = (x[..., 1:, :] - x[..., :-1, :]) ** 2
    bx = (torch.arange(dx.shape[-1], device=x.device) + 1) % block == 0
    by = (torch.arange(dy.shape[-2], device=x.device) + 1) % block == 0
    border = torch.cat([dx[..., bx].flatten(), dy[..., by, :].flatten()])
    inside = torch.cat([dx[..., ~bx].flatten(), dy[..., ~by, :].flatten()])
    return float(border.mean() / inside.mean().clamp_min(1e-20))
