"""Motion network of the LDRM: where each source pixel is at time t, read from the frames at pixel resolution
(docs/DESIGN.md, "The motion path"). Each source pixel's residual motion around its static reprojection ``uv``
(pixels, pixel (x, y)'s centre at (x + 0.5, y + 0.5)) comes from a feature pyramid (:meth:`MotionNetwork.encode`),
coarse-to-fine soft-argmax matching of learned features (:meth:`MotionNetwork.match`; FlowNet, Dosovitskiy et al.
2015 §3; RAFT, Teed & Deng 2020 §3.2), a dilated-conv head with a zero-initialised output and
:func:`motion_activations`."""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from diff4splat.utils.checks import check_number, check_ranges, ranged

from .pretrained import PretrainedMixin

COS_EPS = 1e-6
"""Norm below which a feature vector counts as zero in the cosine similarity."""

__all__ = ["MotionConfig", "MotionNetwork", "correlation", "correlation_reference", "motion_activations"]


@dataclass
class MotionConfig:
    """Sizes of :class:`MotionNetwork`.

    Attributes:
        features: F, channels of the compared frame features.
        hidden: channels of the head's convolutions.
        levels: pyramid levels (level l pooled 2^l×).
        radius: r, offsets −r…r per axis: (2r+1)² correlations per level.
        max_flow: soft-clamp bound of the flow per axis, pixels at the model resolution.
        min_flow: soft threshold on the flow's length, pixels, in [0, max_flow).
        max_log_depth: soft-clamp bound of the log z-depth ratio.

    Raises:
        ValueError: a field out of range.
    """

    features: int = ranged(8)
    hidden: int = ranged(32)
    levels: int = ranged(3)
    radius: int = ranged(2)
    max_flow: float = ranged(8.0, check_number, lo=0, lo_open=True)
    min_flow: float = 0.5
    max_log_depth: float = ranged(0.1, check_number, lo=0, lo_open=True)

    def __post_init__(self) -> None:
        check_ranges("MotionConfig", self)
        if not 0 <= float(self.min_flow) < float(self.max_flow):
            raise ValueError(f"MotionConfig.min_flow must be in [0, max_flow), got {self.min_flow}")


def _offsets(radius: int, like: Tensor) -> Tensor:
    """(D, 2) integer offsets (dx, dy) of a (2r+1)² window, dx fastest."""
    d = torch.arange(-radius, radius + 1, dtype=like.dtype, device=like.device)
    return torch.stack(torch.meshgrid(d, d, indexing="xy"), dim=-1).reshape(-1, 2)


def level_correlation(query: Tensor, target: Tensor, uv: Tensor, level: int, radius: int) -> Tensor:
    """One level of :func:`correlation`: ``query`` (N, F, H, W), ``target`` (N, F, H/2^l, W/2^l), ``uv`` (N, H, W, 2)
    full-resolution pixels → (N, (2r+1)², H, W)."""
    N, Fc, H, W = query.shape
    h, w = target.shape[-2:]
    offsets = _offsets(radius, uv)
    at = uv[:, None] / (2 ** level) + offsets[None, :, None, None]  # (N, D, H, W, 2) level-l pixel coordinates
    # one look-up for every offset: the D offsets stacked along the sampled rows
    grid = at / torch.tensor([w, h], dtype=at.dtype, device=at.device) * 2 - 1  # pixels → grid_sample's [−1, 1]
    sampled = F.grid_sample(target, grid.flatten(1, 2), mode="bilinear", padding_mode="zeros",
                            align_corners=False)  # (N, F, D·H, W)
    # cosine similarity, each side normalised first: F.cosine_similarity on the broadcast query is slower
    # (docs/benchmarks.md, "Motion path and synth costs")
    unit = lambda x: x / x.norm(dim=1, keepdim=True).clamp_min(COS_EPS)  # noqa: E731
    return (unit(query)[:, :, None] * unit(sampled.unflatten(2, (len(offsets), H)))).sum(1)


def _query(source: list[Tensor], level: int) -> Tensor:
    """The source features of ``level`` bilinearly at full resolution."""
    src = source[level]
    return src if level == 0 else F.interpolate(src, size=source[0].shape[-2:], mode="bilinear", align_corners=False)


def correlation(source: list[Tensor], target: list[Tensor], uv: Tensor, radius: int) -> Tensor:
    """Multi-level local correlation volume around each source pixel's position in the target frame.

    Args:
        source, target: per level l, (N, F, H/2^l, W/2^l) features.
        uv: (N, H, W, 2) full-resolution pixel positions in the target frame (outside reads zeros).
        radius: r ≥ 0.

    Returns:
        (N, levels·(2r+1)², H, W) in [−1, 1]; channel l·(2r+1)² + (dy + r)·(2r+1) + (dx + r) is the cosine similarity
        (normalised cross-correlation) of the upsampled source level at p and the target at uv(p)/2^l + (dx, dy).
    """
    return torch.cat([level_correlation(_query(source, level), target[level], uv, level, radius)
                      for level in range(len(source))], dim=1)


def correlation_reference(source: list[Tensor], target: list[Tensor], uv: Tensor, radius: int) -> Tensor:
    """:func:`correlation` by explicit bilinear interpolation, pixel by pixel (slow; the tests' reference)."""
    N, Fc, H, W = source[0].shape
    out = torch.zeros(N, len(source) * (2 * radius + 1) ** 2, H, W, dtype=source[0].dtype, device=source[0].device)
    for level, (src, tgt) in enumerate(zip(source, target, strict=True)):
        query = src if level == 0 else F.interpolate(src, size=(H, W), mode="bilinear", align_corners=False)
        h, w = tgt.shape[-2:]
        for n in range(N):
            for y in range(H):
                for x in range(W):
                    cx, cy = (uv[n, y, x] / 2 ** level).tolist()
                    for i, (dy, dx) in enumerate((a, b) for a in range(-radius, radius + 1)
                                                 for b in range(-radius, radius + 1)):
                        px, py = cx + dx - 0.5, cy + dy - 0.5  # index coordinates
                        x0, y0 = math.floor(px), math.floor(py)
                        value = torch.zeros(Fc, dtype=src.dtype, device=src.device)
                        for yy, wy in ((y0, 1 - (py - y0)), (y0 + 1, py - y0)):
                            for xx, wx in ((x0, 1 - (px - x0)), (x0 + 1, px - x0)):
                                if 0 <= yy < h and 0 <= xx < w:
                                    value = value + wy * wx * tgt[n, :, yy, xx]
                        c = level * (2 * radius + 1) ** 2 + i
                        q = query[n, :, y, x]
                        out[n, c, y, x] = (q * value).sum() / (q.norm().clamp_min(COS_EPS)
                                                               * value.norm().clamp_min(COS_EPS))
    return out


def motion_activations(raw: Tensor, match: Tensor, config: MotionConfig) -> tuple[Tensor, Tensor]:
    """Flow (N, H, W, 2) pixels and log z-depth ratio (N, H, W) from raw channels (N, 4, H, W) and ``match``
    (N, H, W, 2).

    flow₀ = max_flow·tanh((tanh(raw_0)·match + raw_xy)/max_flow); flow = flow₀·max(|flow₀| − τ, 0)/|flow₀|,
    τ = ``min_flow``; log ratio = max_log_depth·tanh(raw_z/max_log_depth) where flow ≠ 0, else 0. Zero ``raw`` gives
    zero. The threshold and mask pass gradients straight through (Bengio et al. 2013), so the zero-initialised output
    can leave its dead zone."""
    gate = torch.tanh(raw[:, :1]).permute(0, 2, 3, 1)  # (N, H, W, 1)
    flow = config.max_flow * torch.tanh((gate * match + raw[:, 1:3].permute(0, 2, 3, 1)) / config.max_flow)
    length = flow.norm(dim=-1, keepdim=True)
    shrunk = flow * (F.relu(length - config.min_flow) / length.clamp_min(1e-12))
    moving = (length[..., 0] > config.min_flow).to(raw.dtype)
    log_depth = config.max_log_depth * torch.tanh(raw[:, 3] / config.max_log_depth)
    flow = shrunk.detach() + (flow - flow.detach())
    log_depth = (log_depth * moving).detach() + (log_depth - log_depth.detach())
    return flow, log_depth


class MotionNetwork(nn.Module, PretrainedMixin):
    """Coarse-to-fine matching of two frames' features around a static point's reprojection → that pixel's motion."""

    config_class = MotionConfig

    def __init__(self, config: MotionConfig) -> None:
        super().__init__()
        self.config = config
        f, h = config.features, config.hidden
        self.encoder = nn.Sequential(nn.Conv2d(3, f, 3, padding=1), nn.GELU(), nn.Conv2d(f, f, 3, padding=1))
        # log of the soft-argmax's learned inverse temperature β per level; β = 40 lets a clear cosine peak win
        beta = torch.full((config.levels,), math.log(40.0))  # device: the construction context's (torch.device, meta)
        self.log_sharpness = nn.Parameter(beta)
        window = (2 * config.radius + 1) ** 2
        self.head = nn.Sequential(
            nn.Conv2d(window + f + 3, h, 3, padding=1), nn.GELU(),
            nn.Conv2d(h, h, 3, padding=2, dilation=2), nn.GELU(),
            nn.Conv2d(h, h, 3, padding=4, dilation=4), nn.GELU(),
        )
        self.out = nn.Conv2d(h, 4, 1)
        # Zero-init: the raw output is 0, the gate closed, so the network starts as the static scene.
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)

    def encode(self, frames: Tensor) -> list[Tensor]:  # frames: (N, 3, H, W) in [−1, 1]
        """Feature pyramid of ``frames`` (N, 3, H, W) in [−1, 1]: ``levels`` tensors (N, F, H/2^l, W/2^l),
        average-pooled (H, W divisible by 2^(levels−1))."""
        feats = [self.encoder(frames)]
        for _ in range(self.config.levels - 1):
            feats.append(F.avg_pool2d(feats[-1], 2))
        return feats

    def match(self, source: list[Tensor], target: list[Tensor], uv: Tensor) -> tuple[Tensor, Tensor]:
        """Coarse-to-fine soft-argmax matching: per level, coarsest first, the expected offset under
        softmax(β_l·correlation) of the window around ``uv`` + flow, times 2^l pixels, is added to the flow.

        Returns:
            flow (N, H, W, 2) pixels; corr (N, (2r+1)², H, W), the finest level's correlation around uv + flow.
        """
        cfg = self.config
        offsets = _offsets(cfg.radius, uv)
        flow = torch.zeros_like(uv)
        for level in reversed(range(cfg.levels)):
            corr = level_correlation(_query(source, level), target[level], uv + flow, level, cfg.radius)
            p = torch.softmax(corr * self.log_sharpness[level].exp(), dim=1)  # (N, D, H, W)
            flow = flow + torch.einsum("ndhw,dc->nhwc", p, offsets) * (2 ** level)
        corr = level_correlation(source[0], target[0], uv + flow, 0, cfg.radius)
        return flow, corr

    def forward(self, source: list[Tensor], target: list[Tensor], uv: Tensor) -> tuple[Tensor, Tensor]:
        """Motion of each source pixel from its static reprojection ``uv`` (N, H, W, 2) in the target frame, given
        :meth:`encode` pyramids of N frame pairs (outside the frame: zero features, in-frame flag 0).

        Returns:
            flow (N, H, W, 2) pixels to add to ``uv`` (exactly 0 for still pixels); log_depth (N, H, W), log of the
            target z-depth over the reprojected one (0 where flow is 0).
        """
        H, W = source[0].shape[-2:]
        match, corr = self.match(source, target, uv)
        size = uv.new_tensor([W, H])
        inside = ((uv >= 0) & (uv <= size)).all(-1).to(corr.dtype)[:, None]  # (N, 1, H, W)
        scaled = (match / self.config.max_flow).permute(0, 3, 1, 2)
        raw = self.out(self.head(torch.cat([corr, source[0], inside, scaled], dim=1)))
        return motion_activations(raw, match, self.config)
