"""Training losses of Diff4Splat (Pan et al. 2025, training objectives), each a pure function.

Weights default to the paper's where it states them; where it does not, the default is the
standard value of the work the term comes from, named in each docstring (:class:`LossWeights`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields

import kornia
import torch
import torch.nn.functional as F
from torch import Tensor

from diff4splat.cameras import project_points
from diff4splat.utils.devices import autocast_off
from models.flow_matching import add_noise, sample_logit_normal, shift_sigmas, velocity_target

__all__ = [
    "LossWeights",
    "flow_matching_loss",
    "sample_training_sigmas",
    "photometric_loss",
    "depth_correlation_loss",
    "depth_smoothness_loss",
    "log_depth_loss",
    "motion_loss",
    "displacement_loss",
    "warp_loss",
    "gather_track_predictions",
    "head_distillation_loss",
]


@dataclass
class LossWeights:
    """Weights of the reconstruction objective
    L = λ_rgb·L_photo + λ_depth·L_depth + λ_smooth·L_smooth + λ_motion·L_motion + λ_disp·L_disp.

    Attributes:
        ssim: λ of (1 − SSIM) inside the photometric loss; 0.2 as in 3DGS (Kerbl et al. 2023, Eq. 7).
        rgb: weight of the photometric loss.
        depth: weight of the depth-correlation loss (Pearson; as in SparseGS / FSGS depth priors).
        metric_depth: weight of the scale-invariant log loss (:func:`log_depth_loss`, λ = 0.5), which unlike the
            correlation keeps a share of the depth's scale: for metric reference depth. 0 (the default, and with a
            relative reference) leaves it out; the correlation alone lets the predicted scale drift.
        smooth: weight of the edge-aware depth smoothness (Godard et al. 2017 use 1e-3 on disparity).
        motion: weight of the track loss (stage 3 only).
        displacement: weight of the track-displacement loss (:func:`displacement_loss`, stage 3 only): the
            motion relative to frame 0, which the absolute track loss mixes with the frame-0 depth error.
        warp: weight of the dense warp loss of the ``tracking`` objective (:func:`warp_loss`).

    Raises:
        ValueError: a weight that is negative or not finite (a negative weight maximises its loss), or an
            ``ssim`` above 1 (the photometric loss mixes (1 − ssim)·L1 + ssim·(1 − SSIM)).
    """

    ssim: float = 0.2
    rgb: float = 1.0
    depth: float = 0.1
    metric_depth: float = 0.0
    smooth: float = 1e-3
    motion: float = 1.0
    displacement: float = 0.0
    warp: float = 1.0

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if not 0 <= value < math.inf:
                raise ValueError(f"stage.weights.{f.name} must be a finite number ≥ 0, got {value}")
        if self.ssim > 1:
            raise ValueError(f"stage.weights.ssim must lie in [0, 1] (the SSIM share of the photometric loss), "
                             f"got {self.ssim}")


def sample_training_sigmas(n: int, mean: float = 0.0, std: float = 1.0, shift: float = 1.0,
                           generator: torch.Generator | None = None, device=None) -> Tensor:
    """Training noise levels: logit-normal σ (SD3, Esser et al. 2024, §3.1 Eq. 19) then the timestep shift
    σ' = sσ/(1 + (s−1)σ) (SD3 §5.3.2). Returns (n,) in (0, 1)."""
    return shift_sigmas(sample_logit_normal(n, mean, std, generator, device=device), shift)


def flow_matching_loss(velocity_fn, x0: Tensor, noise: Tensor, sigma: Tensor, from_frame: int = 0) -> Tensor:
    """Conditional flow-matching loss (Lipman et al. 2023; rectified flow, Liu et al. 2023).

    x_σ = (1−σ)·x0 + σ·ε; the network predicts v = ε − x0; L = mean ‖v_θ(x_σ, σ) − (ε − x0)‖².

    Args:
        velocity_fn: ``f(x_sigma, sigma (B,)) -> v`` with the shape of ``x0``.
        x0: (B, ...) clean latents; (B, c, n, h, w) when ``from_frame`` > 0.
        noise: (B, ...) standard normal ε.
        sigma: (B,) noise levels in [0, 1].
        from_frame: first latent frame (dim 2) of the mean: a network that replaces the first frames of its input
            by a condition (Wan2.2-TI2V's image latent) has no velocity target there.

    Returns:
        Scalar mean squared error over every element (of frames ``from_frame`` … n − 1).
    """
    x_sigma = add_noise(x0, noise, sigma)
    err = velocity_fn(x_sigma, sigma) - velocity_target(x0, noise)
    return torch.mean((err[:, :, from_frame:] if from_frame else err) ** 2)


def photometric_loss(pred: Tensor, target: Tensor, ssim_weight: float = 0.2, window_size: int = 11) -> Tensor:
    """L1 + λ·(1 − SSIM) between images (3DGS, Kerbl et al. 2023, Eq. 7); SSIM from kornia.

    Args:
        pred, target: (B, 3, H, W) in [0, 1].
        ssim_weight: λ ∈ [0, 1]; the L1 term has weight 1 − λ as in 3DGS.
        window_size: odd SSIM window (Gaussian σ = 1.5).

    Returns:
        Scalar; 0 iff pred == target.

    Raises:
        ValueError: shapes differ or are not (B, 3, H, W).
    """
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
    """1 − Pearson correlation between rendered and reference depth per image over valid pixels.

    Scale- and shift-invariant, so a relative (non-metric) reference depth supervises geometry
    (FSGS, Zhu et al. 2024; SparseGS, Xiong et al. 2023). With ρ = cov(p, r) / sqrt((var p + eps)(var r + eps)),
    a constant depth gives ρ = 0 (loss 1), never NaN.

    Args:
        pred, reference: (B, H, W) depths (any positive units).
        valid: (B, H, W) bool, or None for all pixels; images with < 2 valid pixels contribute 0.

    Returns:
        Scalar mean over images of 1 − ρ, in [0, 2].

    Raises:
        ValueError: ``pred`` and ``reference`` not both (B, H, W) of the same shape.
    """
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
    """Scale-invariant log error of metric depth (Eigen, Puhrsch & Fergus 2014, Eq. 4), per image.

    With g = log pred − log reference over the n valid pixels, L = mean(g²) − λ·mean(g)²: λ = 0 is the mean squared
    log error, λ = 1 is invariant to the depth's scale, and 0 < λ < 1 (the paper trains with 0.5) weighs the scale
    error by 1 − λ while the shape error keeps its full weight.

    Args:
        pred, reference: (B, H, W) depths in the same units (metres), > 0 where valid; pixels where either is not
            finite or ≤ 0 are left out.
        valid: (B, H, W) bool, or None for all pixels; images with no valid pixel contribute 0.
        lam: λ in [0, 1].

    Returns:
        Scalar mean over images, ≥ 0 (mean(g²) ≥ mean(g)² ≥ λ·mean(g)²).

    Raises:
        ValueError: shapes not both (B, H, W), or λ outside [0, 1].
    """
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
    """Edge-aware smoothness of mean-normalised inverse depth (Monodepth2, Godard et al. 2019, Eq. 3), over the
    pixels ``valid`` marks.

    L = mean |∂x d*| e^{−|∂x I|} + mean |∂y d*| e^{−|∂y I|}, d* = (1/depth) / mean(1/depth) per image,
    |∂I| averaged over colour channels; the means run over valid pixels (d*'s normaliser) and over neighbour
    pairs whose two pixels are valid (the differences). Zero for a constant depth on the valid pixels, whatever
    the others hold (an uncovered pixel renders depth 0: counted, its disparity swamped the normaliser and
    its edge pulled the covered neighbours towards the camera); small where depth edges align with image edges.

    Args:
        depth: (B, H, W) metres; only pixels with depth > 0 (finite) count.
        image: (B, 3, H, W) in [0, 1].
        valid: (B, H, W) bool, the pixels to regularise (e.g. rendered alpha > 0.5); None: every pixel.

    Returns:
        Scalar ≥ 0 (0 without a valid neighbour pair).
    """
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
    """Predicted 3D positions μ + Δμ(t) of tracked points (Diff4Splat motion supervision).

    Pixel-aligned Gaussians are indexed by their reference-frame pixel (row-major), so a track
    queried at pixel (i, j) of frame 0 follows Gaussian i·W + j.

    Returns:
        (B, P, T, 3) metres.
    """
    B, T, M, _ = d_means.shape
    idx = index[:, None, :, None].expand(B, T, index.shape[1], 3)
    pos = torch.gather(means[:, None].expand(B, T, M, 3), 2, idx) + torch.gather(d_means, 2, idx)
    return pos.permute(0, 2, 1, 3)


def motion_loss(pred: Tensor, target: Tensor, visibility: Tensor) -> Tensor:
    """Visibility-masked mean Euclidean distance between predicted and ground-truth 3D tracks.

    L = Σ_{p,t} v_pt ‖x̂_pt − x_pt‖₂ / max(1, Σ v_pt)   (end-point error in metres).

    Args:
        pred: (B, P, T, 3) predicted positions, metres.
        target: (B, P, T, 3) ground-truth positions, metres.
        visibility: (B, P, T) bool.

    Returns:
        Scalar metres; 0 when nothing is visible.

    Raises:
        ValueError: shapes other than ``pred``, ``target`` (B, P, T, 3) alike and ``visibility`` (B, P, T).
    """
    if pred.shape != target.shape or visibility.shape != pred.shape[:-1]:
        raise ValueError(f"pred {tuple(pred.shape)}, target {tuple(target.shape)} and visibility "
                         f"{tuple(visibility.shape)} must be (B, P, T, 3), (B, P, T, 3), (B, P, T)")
    v = visibility.to(pred.dtype)
    diff = torch.where(visibility[..., None], pred - target, 0)
    dist = torch.sqrt((diff ** 2).sum(-1) + 1e-12) * v  # eps keeps the gradient finite at 0
    return dist.sum() / v.sum().clamp(min=1)


def displacement_loss(pred: Tensor, target: Tensor, visibility: Tensor) -> Tensor:
    """:func:`motion_loss` of the displacements from frame 0: ‖(x̂_pt − x̂_p0) − (x_pt − x_p0)‖₂ over the
    (p, t ≥ 1) with the point visible at 0 and at t.

    The absolute track error is dominated by where the scene puts a point at frame 0 (its metric depth);
    this term sees only the motion, so its gradient reaches the deformation undiluted (ours; the paper
    supervises absolute tracks).

    Args:
        pred, target: (B, P, T, 3) metres.  visibility: (B, P, T) bool.

    Returns:
        Scalar metres; 0 when no pair is visible.
    """
    vis = visibility[:, :, 1:] & visibility[:, :, :1]
    return motion_loss(pred[:, :, 1:] - pred[:, :, :1], target[:, :, 1:] - target[:, :, :1], vis)


def head_distillation_loss(student: Tensor, teacher: Tensor, sigma: float) -> Tensor:
    """Mean squared error between a student head's raw Gaussian maps and a teacher's, low-passed
    (knowledge distillation, Hinton et al. 2015, on the regression outputs).

    The teacher (the paper's non-overlapping transposed convolution, :class:`models.ldrm.LDRM` ``head: deconv``)
    decodes each token into its own f×f block, so its maps step at every block border; blurring them with a
    Gaussian of ``sigma`` pixels (kornia, borders replicated) keeps what the teacher learned and drops the seams the
    student (the overlapping upsampler) should not copy. ``sigma`` = 0: the teacher's maps as they are.

    Args:
        student: (B, 12, S, H, W) raw maps (:meth:`models.ldrm.LDRM.head_maps`).
        teacher: (B, 12, S, H, W) the teacher's raw maps on the same inputs (no gradient needed).
        sigma: blur standard deviation, pixels, ≥ 0.

    Returns:
        scalar loss, mean over every channel, frame and pixel.

    Raises:
        ValueError: shapes differ, or ``sigma`` negative or not finite.
    """
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
    """Brightness constancy of moving points: mean L1 between frame 0's colour at each pixel and frame t's colour where
    that pixel's point is at t, over the (t ≥ 1, pixel) pairs whose point projects inside frame t in front of it
    (the photometric loss of unsupervised optical flow, e.g. Jonschkowski et al. 2020, dense where tracks are sparse;
    occlusions are not masked).

    Args:
        frames: (T, 3, H, W) in [0, 1].
        points: (T, H, W, 3) world positions at each frame's time of frame 0's pixels, metres.
        viewmats: (T, 4, 4) world-to-camera; Ks: (T, 3, 3) pixels at (H, W).

    Returns:
        Scalar ≥ 0; 0 where nothing projects inside a frame.
    """
    T, _, H, W = frames.shape
    uv, z = project_points(points[1:], viewmats[1:, None, None], Ks[1:, None, None])  # (T−1, H, W, 2)
    size = uv.new_tensor([W, H])
    grid = uv / size * 2 - 1
    seen = F.grid_sample(frames[1:], grid.to(frames.dtype), mode="bilinear", padding_mode="zeros",
                         align_corners=False)  # (T−1, 3, H, W)
    inside = ((grid.abs() < 1).all(-1) & (z > 0)).to(frames.dtype)[:, None]
    return ((seen - frames[:1]).abs() * inside).sum() / (3 * inside.sum()).clamp_min(1)
