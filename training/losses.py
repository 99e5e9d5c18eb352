"""Training losses of Diff4Splat (Pan et al. 2025), each a pure function; defaults are the paper's or, where it is
silent, those of the work each term comes from (:class:`LossWeights`)."""
from __future__ import annotations

import math
from dataclasses import dataclass

import kornia
import torch
import torch.nn.functional as F
from torch import Tensor

from diff4splat.cameras import project_points
from diff4splat.utils.checks import check_number, check_ranges, ranged
from diff4splat.utils.devices import autocast_off
from models.flow_matching import add_noise, sample_logit_normal, shift_sigmas, velocity_target

from .direction_test import moving_pixels

__all__ = ["LossWeights", "flow_matching_loss", "flow_matching_errors", "moving_cells", "sample_training_sigmas",
           "photometric_loss", "depth_correlation_loss", "depth_smoothness_loss", "log_depth_loss", "motion_loss",
           "displacement_loss", "scene_flow_loss", "warp_loss", "gather_track_predictions", "head_distillation_loss"]


def _weight(default: float) -> float:
    """A :class:`LossWeights` field defaulting to ``default``: a finite number ≥ 0 (checked on construction)."""
    return ranged(default, check_number, lo=0)


@dataclass
class LossWeights:
    """Weights of L = λ_rgb·L_photo + λ_depth·L_depth + λ_metric·L_log + λ_smooth·L_smooth + λ_motion·L_motion
    + λ_disp·L_disp + λ_flow·L_flow (+ λ_warp·L_warp for ``tracking``).

    ``ssim`` is the SSIM share inside the photometric loss (0.2, 3DGS Eq. 7); ``depth`` weighs the Pearson depth
    loss (FSGS/SparseGS), ``metric_depth`` the scale-invariant log loss (0: off, for a relative reference), ``smooth``
    the edge-aware smoothness (Godard et al.'s 1e-3); ``motion``/``displacement`` are stage-3 track losses,
    ``scene_flow`` the dense one over every pixel of frame 0 (:func:`scene_flow_loss`; 0: off); ``mover`` adds the
    ``diffusion`` objective's mean flow-matching error over the latent cells a moving object covers
    (:func:`moving_cells`; 0: off), so that the few cells where the objects' motion is seen are not drowned by the
    rest of the frame; ``motion_flow`` weighs the ``motion_generation`` objective's flow-matching loss.
    Raises ValueError for a negative or non-finite weight, or ``ssim`` above 1.
    """

    ssim: float = _weight(0.2)
    rgb: float = _weight(1.0)
    depth: float = _weight(0.1)
    metric_depth: float = _weight(0.0)
    smooth: float = _weight(1e-3)
    motion: float = _weight(1.0)
    displacement: float = _weight(0.0)
    scene_flow: float = _weight(0.0)
    warp: float = _weight(1.0)
    mover: float = _weight(0.0)
    motion_flow: float = _weight(1.0)

    def __post_init__(self) -> None:
        check_ranges("stage.weights", self)
        if self.ssim > 1:
            raise ValueError(f"stage.weights.ssim must lie in [0, 1] (the SSIM share of the photometric loss), "
                             f"got {self.ssim}")


def sample_training_sigmas(n: int, mean: float = 0.0, std: float = 1.0, shift: float = 1.0,
                           generator: torch.Generator | None = None, device=None) -> Tensor:
    """(n,) training σ in (0, 1): logit-normal (SD3 Eq. 19), then shifted σ' = sσ/(1 + (s−1)σ) (SD3 §5.3.2)."""
    return shift_sigmas(sample_logit_normal(n, mean, std, generator, device=device), shift)


def flow_matching_errors(velocity_fn, x0: Tensor, noise: Tensor, sigma: Tensor) -> Tensor:
    """Squared flow-matching errors (v_θ(x_σ, σ) − (ε − x0))², x_σ = (1−σ)x0 + σε (Lipman et al. 2023; rectified flow),
    of the shape of ``x0`` (B, ...). ``velocity_fn(x_sigma, sigma (B,))`` returns that shape; ``sigma`` (B,) in
    [0, 1]."""
    x_sigma = add_noise(x0, noise, sigma)
    return (velocity_fn(x_sigma, sigma) - velocity_target(x0, noise)) ** 2


def flow_matching_loss(velocity_fn, x0: Tensor, noise: Tensor, sigma: Tensor, from_frame: int = 0) -> Tensor:
    """Flow-matching loss: the mean of :func:`flow_matching_errors` from latent frame ``from_frame`` (dim 2) on, for
    networks that replace the first frames by a condition."""
    err = flow_matching_errors(velocity_fn, x0, noise, sigma)
    return torch.mean(err[:, :, from_frame:] if from_frame else err)


def moving_cells(
    pixel_tracks: Tensor,  # (B, T, H, W, 3) clip-world metres: frame 0's pixels' true 3D tracks
    valid: Tensor,  # (B, H, W) bool
    viewmats: Tensor,  # (B, T, 4, 4) world-to-camera
    Ks: Tensor,  # (B, T, 3, 3) pixels
    grid: tuple[int, int, int],  # (n, h, w) latent frames, rows, columns
    temporal_factor: int,
) -> Tensor:
    """(B, n, h, w) bool: the latent cells that a moving object covers — every cell into which frame t's camera
    projects the point of a moving pixel (:func:`training.direction_test.moving_pixels`) at frame t, latent frame
    1 + (t − 1) // ``temporal_factor`` for t ≥ 1. Latent frame 0 (the photograph's, a condition) is all False.
    Raises ValueError when T is not 1 + (n − 1)·``temporal_factor`` or H, W are not multiples of h, w."""
    B, T, H, W, _ = pixel_tracks.shape
    n, h, w = grid
    if T != 1 + (n - 1) * temporal_factor or H % h or W % w:
        raise ValueError(f"pixel_tracks {tuple(pixel_tracks.shape)} do not fit the latent grid {grid} "
                         f"(temporal factor {temporal_factor})")
    moving = moving_pixels(pixel_tracks, valid).flatten(1)  # (B, H·W)
    with autocast_off():  # bfloat16 would move points near a cell's edge into the next cell
        uv, z = project_points(pixel_tracks.flatten(2, 3).float(), viewmats[:, :, None].float(),
                               Ks[:, :, None].float())  # (B, T, H·W, 2), (B, T, H·W)
    uv = torch.where(torch.isfinite(uv), uv, -1.0)
    col = torch.floor(uv[..., 0] / (W // w)).long()
    row = torch.floor(uv[..., 1] / (H // h)).long()
    frames = torch.arange(T, device=uv.device)
    latent_frame = 1 + (frames - 1) // temporal_factor  # (T,) floor division: frame 0 → 0
    hit = moving[:, None] & (z > 0) & (col >= 0) & (col < w) & (row >= 0) & (row < h) & (frames > 0)[None, :, None]
    clip = torch.arange(B, device=uv.device)[:, None, None]
    flat = ((clip * n + latent_frame[None, :, None]) * h + row) * w + col  # (B, T, H·W)
    cells = torch.zeros(B * n * h * w, dtype=torch.bool, device=uv.device)
    cells[flat[hit]] = True
    return cells.view(B, n, h, w)


def photometric_loss(pred: Tensor, target: Tensor, ssim_weight: float = 0.2, window_size: int = 11) -> Tensor:
    """(1 − λ)·L1 + λ·(1 − SSIM) of (B, 3, H, W) images in [0, 1] (3DGS Eq. 7; kornia SSIM, σ 1.5, odd window),
    in float32 at least. Raises ValueError unless both are (B, C, H, W) of one shape."""
    if pred.shape != target.shape or pred.dim() != 4:
        raise ValueError(
            f"pred and target must both be (B, C, H, W), got {tuple(pred.shape)} and {tuple(target.shape)}")
    with autocast_off():  # SSIM's variances E[x²] − μ² are ~1e-3: bfloat16 rounding would swamp them
        dt = torch.promote_types(pred.dtype, torch.float32)
        pred, target = pred.to(dt), target.to(dt)
        l1 = (pred - target).abs().mean()
        ssim = kornia.metrics.ssim(pred, target, window_size, max_val=1.0).mean()
    return (1 - ssim_weight) * l1 + ssim_weight * (1 - ssim)


def depth_correlation_loss(pred: Tensor, reference: Tensor, valid: Tensor | None = None, eps: float = 1e-6) -> Tensor:
    """Mean over images of 1 − ρ in [0, 2], ρ = cov(p, r) / sqrt((var p + eps)(var r + eps)) of (B, H, W) depths over
    ``valid`` finite pixels (FSGS, Zhu et al. 2024; SparseGS): scale- and shift-invariant; images with < 2 valid
    pixels give 0. Raises ValueError unless both are (B, H, W) of one shape."""
    if pred.shape != reference.shape or pred.dim() != 3:
        raise ValueError(
            f"pred and reference must both be (B, H, W), got {tuple(pred.shape)} and {tuple(reference.shape)}")
    if valid is None:
        valid = torch.ones_like(pred, dtype=torch.bool)
    valid = valid & torch.isfinite(reference) & torch.isfinite(pred)
    w = valid.to(pred.dtype).flatten(1)
    n = w.sum(1)
    p = torch.where(valid, pred, 0).flatten(1)
    r = torch.where(valid, reference, 0).flatten(1)
    safe_n = n.clamp(min=1)
    pc = (p - (p * w).sum(1, keepdim=True) / safe_n[:, None]) * w
    rc = (r - (r * w).sum(1, keepdim=True) / safe_n[:, None]) * w
    cov = (pc * rc).sum(1) / safe_n
    rho = cov / torch.sqrt(((pc ** 2).sum(1) / safe_n + eps) * ((rc ** 2).sum(1) / safe_n + eps))
    loss = torch.where(n >= 2, 1 - rho, torch.zeros_like(rho))
    return loss.mean()


def log_depth_loss(pred: Tensor, reference: Tensor, valid: Tensor | None = None, lam: float = 0.5) -> Tensor:
    """Scale-invariant log error mean(g²) − λ·mean(g)², g = log pred − log reference (Eigen et al. 2014, Eq. 4),
    averaged over images, of (B, H, W) depths in metres over ``valid`` pixels where both are finite and > 0 (an
    image with none gives 0). Raises ValueError unless both are (B, H, W), or for λ outside [0, 1]."""
    if pred.shape != reference.shape or pred.dim() != 3:
        raise ValueError(
            f"pred and reference must both be (B, H, W), got {tuple(pred.shape)} and {tuple(reference.shape)}")
    if not 0.0 <= lam <= 1.0:
        raise ValueError(f"lam must lie in [0, 1], got {lam}")
    if valid is None:
        valid = torch.ones_like(pred, dtype=torch.bool)
    valid = valid & torch.isfinite(pred) & torch.isfinite(reference) & (pred > 0) & (reference > 0)
    g = torch.where(valid, torch.log(torch.where(valid, pred, 1)) - torch.log(torch.where(valid, reference, 1)), 0)
    n = valid.flatten(1).sum(1)
    safe_n = n.clamp(min=1).to(g.dtype)
    mean_g = g.flatten(1).sum(1) / safe_n
    loss = (g ** 2).flatten(1).sum(1) / safe_n - lam * mean_g ** 2
    return torch.where(n > 0, loss, torch.zeros_like(loss)).mean()


def depth_smoothness_loss(depth: Tensor, image: Tensor, valid: Tensor | None = None) -> Tensor:
    """Edge-aware smoothness (Monodepth2, Godard et al. 2019, Eq. 3): mean |∂d*| e^{−|∂I|} over x and y of
    d* = (1/depth) / mean(1/depth) per image, over ``valid`` pixels (and pairs) with finite depth > 0.

    ``depth`` (B, H, W) metres, ``image`` (B, 3, H, W) in [0, 1]; returns a scalar ≥ 0 (0 with no valid pair)."""
    ok = torch.isfinite(depth) & (depth > 0)
    if valid is not None:
        ok = ok & valid
    disp = torch.where(ok, 1.0 / torch.where(ok, depth, torch.ones_like(depth)), torch.zeros_like(depth))
    n = ok.flatten(1).sum(1).clamp(min=1).to(disp.dtype)
    mean = disp.flatten(1).sum(1) / n
    disp = disp / torch.where(mean > 0, mean, torch.ones_like(mean))[:, None, None]
    ok_x, ok_y = ok[:, :, 1:] & ok[:, :, :-1], ok[:, 1:] & ok[:, :-1]
    dx = (disp[:, :, 1:] - disp[:, :, :-1]).abs()
    dy = (disp[:, 1:] - disp[:, :-1]).abs()
    ix = (image[..., 1:] - image[..., :-1]).abs().mean(1)
    iy = (image[..., 1:, :] - image[..., :-1, :]).abs().mean(1)
    lx = (dx * torch.exp(-ix) * ok_x).sum() / ok_x.sum().clamp(min=1)
    ly = (dy * torch.exp(-iy) * ok_y).sum() / ok_y.sum().clamp(min=1)
    return lx + ly


def gather_track_predictions(
    means: Tensor,  # (B, M, 3) canonical Gaussian means
    d_means: Tensor,  # (B, T, M, 3) mean offsets at the T track times
    index: Tensor,  # (B, P) long: the Gaussian (pixel of the reference frame) each track starts at
) -> Tensor:
    """(B, P, T, 3) positions μ + Δμ(t) in metres of tracked points; a track from frame-0 pixel (i, j) follows
    Gaussian i·W + j."""
    B, T, M, _ = d_means.shape
    idx = index[:, None, :, None].expand(B, T, index.shape[1], 3)
    pos = torch.gather(means[:, None].expand(B, T, M, 3), 2, idx) + torch.gather(d_means, 2, idx)
    return pos.permute(0, 2, 1, 3)


def motion_loss(pred: Tensor, target: Tensor, visibility: Tensor) -> Tensor:
    """End-point error Σ v‖x̂ − x‖₂ / max(1, Σ v) in metres of (B, P, T, 3) tracks under ``visibility`` (B, P, T);
    0 when nothing is visible. Raises ValueError on other shapes."""
    if pred.shape != target.shape or visibility.shape != pred.shape[:-1]:
        raise ValueError(f"pred {tuple(pred.shape)}, target {tuple(target.shape)} and visibility "
                         f"{tuple(visibility.shape)} must be (B, P, T, 3), (B, P, T, 3), (B, P, T)")
    v = visibility.to(pred.dtype)
    diff = torch.where(visibility[..., None], pred - target, 0)
    dist = torch.sqrt((diff ** 2).sum(-1) + 1e-12) * v  # eps keeps the gradient finite at 0
    return dist.sum() / v.sum().clamp(min=1)


def displacement_loss(pred: Tensor, target: Tensor, visibility: Tensor) -> Tensor:
    """:func:`motion_loss` of displacements from frame 0, over (p, t ≥ 1) visible at 0 and t: the motion without the
    frame-0 depth error (ours; the paper supervises absolute tracks)."""
    vis = visibility[:, :, 1:] & visibility[:, :, :1]
    return motion_loss(pred[:, :, 1:] - pred[:, :, :1], target[:, :, 1:] - target[:, :, :1], vis)


def scene_flow_loss(points: Tensor, target: Tensor, valid: Tensor) -> Tensor:
    """Dense :func:`displacement_loss`: mean end-point error in metres of the displacements from frame 0 of every
    pixel's point, ``points`` (T, H, W, 3) against ``target`` (T, H, W, 3) (``ClipDataset``'s ``pixel_tracks``), over
    the ``valid`` (H, W) pixels and t ≥ 1 (DGS-LRM's scene-flow supervision, Lin et al. 2025). Raises ValueError on
    other shapes."""
    T, H, W, _ = target.shape
    if points.shape != target.shape or valid.shape != (H, W):
        raise ValueError(f"points {tuple(points.shape)}, target {tuple(target.shape)} and valid {tuple(valid.shape)} "
                         "must be (T, H, W, 3), (T, H, W, 3), (H, W)")
    flat = lambda x: x.reshape(T, H * W, 3).transpose(0, 1)[None]  # noqa: E731  (1, H·W, T, 3) tracks
    return displacement_loss(flat(points), flat(target), valid.reshape(1, H * W, 1).expand(1, H * W, T))


def head_distillation_loss(student: Tensor, teacher: Tensor, sigma: float) -> Tensor:
    """MSE of a student head's raw maps (B, 12, S, H, W) (:meth:`models.ldrm.LDRM.head_maps`) against a teacher's,
    Gaussian-blurred by ``sigma`` ≥ 0 pixels (kornia, replicated borders) to drop its block seams (distillation,
    Hinton et al. 2015). Raises ValueError for shapes that differ, or a negative or non-finite ``sigma``."""
    if student.shape != teacher.shape or student.dim() != 5:
        raise ValueError(f"student {tuple(student.shape)} and teacher {tuple(teacher.shape)} must both be "
                         "(B, C, S, H, W) maps of one shape")
    if not (sigma >= 0 and math.isfinite(sigma)):
        raise ValueError(f"sigma must be a finite number ≥ 0 (pixels), got {sigma}")
    B, C, S, H, W = teacher.shape
    target = teacher.detach()
    if sigma > 0:
        radius = max(1, math.ceil(3 * sigma))
        flat = target.transpose(1, 2).reshape(B * S, C, H, W)
        flat = kornia.filters.gaussian_blur2d(flat, (2 * radius + 1, 2 * radius + 1), (sigma, sigma),
                                              border_type="replicate")
        target = flat.reshape(B, S, C, H, W).transpose(1, 2)
    return (student - target).square().mean()


def warp_loss(frames: Tensor, points: Tensor, viewmats: Tensor, Ks: Tensor) -> Tensor:
    """Brightness constancy (Jonschkowski et al. 2020): mean L1 between frame 0's colour and frame t's colour where
    each pixel's point is at t, over (t ≥ 1, pixel) pairs projecting inside frame t in front (occlusions unmasked).

    ``frames`` (T, 3, H, W) in [0, 1]; ``points`` (T, H, W, 3) metres; ``viewmats`` (T, 4, 4); ``Ks`` (T, 3, 3)."""

    T, _, H, W = frames.shape
    uv, z = project_points(points[1:], viewmats[1:, None, None], Ks[1:, None, None])  # (T−1, H, W, 2)
    size = uv.new_tensor([W, H])
    grid = uv / size * 2 - 1
    seen = F.grid_sample(frames[1:], grid.to(frames.dtype), mode="bilinear", padding_mode="zeros",
                         align_corners=False)  # (T−1, 3, H, W)
    inside = ((grid.abs() < 1).all(-1) & (z > 0)).to(frames.dtype)[:, None]
    return ((seen - frames[:1]).abs() * inside).sum() / (3 * inside.sum()).clamp_min(1)
