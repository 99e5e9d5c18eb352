"""Causal 3D-convolution video VAE: 4× temporal, 8×8 spatial compression, first frame encoded on its own.

A simplified CogVideoX / Wan-style video VAE (Yang et al. 2024 §2.1; Wan Team 2025 §3.1): convolutions pad time
with replicated past frames and norms are per frame, so latent i depends only on frames ≤ 4i and decoded frame t
only on latents ≤ ⌈t/4⌉; a diagonal Gaussian posterior N(mean, exp(logvar)), logvar clamped to [−30, 20]
(Kingma & Welling 2014; Stable Diffusion's clamp); DC-AE residual shortcuts (Chen et al. 2025 §3.2) around every
resampling block and the bottleneck; nearest or bilinear spatial upsampling (docs/DESIGN.md "Training", stage 0).
No attention in the middle block, no feature cache, no tiling. Tensors ``(B, C, T, H, W)``, pixels in [−1, 1];
latents ``(B, c, n, H/8, W/8)``."""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from diff4splat.utils.checks import check_ranges, ranged
from models.backbone import LatentFormat
from models.pretrained import PretrainedMixin
from models.tracing import tracing

__all__ = ["VideoVAEConfig", "PAPER_VIDEO_VAE", "VideoVAE", "CausalConv3d", "FrameGroupNorm", "ResBlock3d",
           "kl_divergence", "sample_posterior", "estimate_latent_scaling", "LOGVAR_RANGE", "UPSAMPLE_MODES",
           "upsample2x", "check_video", "check_latents"]

LOGVAR_RANGE = (-30.0, 20.0)
"""Clamp of the posterior log-variance (Stable Diffusion ``DiagonalGaussianDistribution``)."""

UPSAMPLE_MODES = ("nearest", "bilinear")
"""The decoder's spatial upsampling (``VideoVAEConfig.upsample``)."""


@dataclass
class VideoVAEConfig:
    """Video VAE hyper-parameters; defaults are the tiny CPU model.

    Attributes:
        in_channels: pixel channels (3, RGB in [−1, 1]).
        latent_channels: c, channels of the latent video.
        base_channels: width of the first level.
        channel_mults: width multiplier per level; ``len − 1`` stride-2 spatial downsamples (4 levels → 8×8).
        temporal_downsample: one flag per downsample, True = also halve time; the decoder mirrors it.
        num_res_blocks: residual blocks per encoder level (the decoder has one more, as in SD/Wan).
        norm_groups: GroupNorm groups; must divide every level width.
        shortcuts: DC-AE residual shortcuts; needs ``latent_channels`` to divide the deepest width.
        upsample: the decoder's spatial 2× upsampling, one of :data:`UPSAMPLE_MODES`; the weights fit either.
        scaling_factor, shift_factor: a and b in z_dit = a·(z − b) (:meth:`VideoVAE.encode_latents`), set with
            :func:`estimate_latent_scaling`.

    Raises ValueError (``__post_init__``) on a non-positive size, a wrong flag count, groups that do not divide the
    widths, an unknown ``upsample`` or ``scaling_factor`` ≤ 0.
    """

    in_channels: int = ranged(3)
    latent_channels: int = ranged(4)
    base_channels: int = ranged(8)
    channel_mults: tuple[int, ...] = (1, 2, 2, 2)
    temporal_downsample: tuple[bool, ...] = (False, True, True)
    num_res_blocks: int = ranged(1)
    norm_groups: int = ranged(4)
    shortcuts: bool = True
    upsample: str = "nearest"
    scaling_factor: float = 1.0
    shift_factor: float = 0.0

    def __post_init__(self) -> None:
        self.channel_mults = tuple(self.channel_mults)
        self.temporal_downsample = tuple(bool(t) for t in self.temporal_downsample)
        check_ranges("VideoVAEConfig", self)
        if len(self.channel_mults) < 1 or any(int(m) < 1 for m in self.channel_mults):
            raise ValueError(f"VideoVAEConfig.channel_mults must be positive ints, got {self.channel_mults}")
        if len(self.temporal_downsample) != len(self.channel_mults) - 1:
            raise ValueError(f"VideoVAEConfig.temporal_downsample needs {len(self.channel_mults) - 1} flags "
                             f"(one per downsample), got {self.temporal_downsample}")
        for width in self.widths:
            if width % self.norm_groups:
                raise ValueError(f"VideoVAEConfig.norm_groups={self.norm_groups} must divide every level "
                                 f"width, got widths {self.widths}")
        if self.shortcuts and self.widths[-1] % self.latent_channels:
            raise ValueError(f"VideoVAEConfig.latent_channels={self.latent_channels} must divide the deepest width "
                             f"{self.widths[-1]} for the channel-averaging shortcuts (or set shortcuts=False)")
        if self.upsample not in UPSAMPLE_MODES:
            raise ValueError(f"VideoVAEConfig.upsample must be one of {UPSAMPLE_MODES}, got {self.upsample!r}")
        if not self.scaling_factor > 0:
            raise ValueError(f"VideoVAEConfig.scaling_factor must be > 0, got {self.scaling_factor}")

    @property
    def widths(self) -> tuple[int, ...]:
        """Channel width of each level."""
        return tuple(self.base_channels * int(m) for m in self.channel_mults)

    @property
    def spatial_factor(self) -> int:
        """Spatial compression per axis (8 for 4 levels)."""
        return 2 ** (len(self.channel_mults) - 1)

    @property
    def temporal_factor(self) -> int:
        """Temporal compression of frames after the first (4 for two temporal downsamples)."""
        return 2 ** sum(self.temporal_downsample)

    @property
    def latent_format(self) -> LatentFormat:
        """Channels and compression as a :class:`models.backbone.LatentFormat`."""
        return LatentFormat(self.latent_channels, self.temporal_factor, self.spatial_factor)

    def num_latent_frames(self, num_frames: int) -> int:
        """n = 1 + (T − 1)/temporal_factor; ValueError unless T = 1 + temporal_factor·k."""
        return self.latent_format.num_latent_frames(num_frames)

    def num_frames(self, num_latent_frames: int) -> int:
        """T = 1 + temporal_factor·(n − 1), the decoded length of n ≥ 1 latent frames."""
        return self.latent_format.num_frames(num_latent_frames)

    @classmethod
    def paper(cls) -> VideoVAEConfig:
        """Paper-scale configuration (:data:`PAPER_VIDEO_VAE`)."""
        return cls(**PAPER_VIDEO_VAE)


PAPER_VIDEO_VAE: dict = dict(in_channels=3, latent_channels=16, base_channels=96, channel_mults=(1, 2, 4, 4),
                             temporal_downsample=(False, True, True), num_res_blocks=2, norm_groups=32,
                             shortcuts=True, scaling_factor=1.0, shift_factor=0.0)
"""Paper-scale VAE: 4×8×8 compression, 16 latent channels; widths and depth of the Wan 2.1 VAE. Scale and
shift stay 1/0 until estimated with :func:`estimate_latent_scaling`."""


MAX_KERNEL_ELEMENTS = 2**31 - 1
"""Elements of one sample above which :class:`CausalConv3d` and :func:`upsample2x` run on windows of frames
(CUDA kernels index in 32 bits)."""


class CausalConv3d(nn.Module):
    """3D convolution padding time only on the past side with k_t − 1 copies of frame 0; symmetric zero padding
    k//2 in H, W. Output frame i sees input frames ≤ i·s_t."""

    def __init__(self, in_channels: int, out_channels: int, kernel_size: tuple[int, int, int] = (3, 3, 3),
                 stride: tuple[int, int, int] = (1, 1, 1)):
        super().__init__()
        kt, kh, kw = kernel_size
        self.time_pad = kt - 1
        self.conv = nn.Conv3d(in_channels, out_channels, kernel_size, stride=stride, padding=(0, kh // 2, kw // 2))

    def forward(self, x: Tensor) -> Tensor:
        """(B, C_in, T, H, W) → (B, C_out, ⌊(T − 1)/s_t⌋ + 1, ⌊(H − 1)/s_h⌋ + 1, ⌊(W − 1)/s_w⌋ + 1) (odd spatial
        kernels); above :data:`MAX_KERNEL_ELEMENTS` (stride 1 in time) in windows of frames, same values."""
        if self.time_pad:
            x = torch.cat([x[:, :, :1].expand(-1, -1, self.time_pad, -1, -1), x], dim=2)
        c_in, t, h, w = x.shape[1:]
        c = max(c_in, self.conv.out_channels)
        if c * t * h * w <= MAX_KERNEL_ELEMENTS or self.conv.stride[0] != 1 or tracing():
            return self.conv(x)
        # One sample above 2³¹ elements (the paper decoder's last stage at 49 frames, 512²): windows of output
        # frames, each with the time_pad frames before it; the same values, each call within 32-bit indexing.
        step = max(1, MAX_KERNEL_ELEMENTS // (c * h * w) - self.time_pad)
        return torch.cat([self.conv(x[:, :, s:s + step + self.time_pad]) for s in range(0, t - self.time_pad, step)],
                         dim=2)


class FrameGroupNorm(nn.GroupNorm):
    """GroupNorm with statistics per frame (causal in time); (B, C, T, H, W) → same."""

    def forward(self, x: Tensor) -> Tensor:
        b, c, t, h, w = x.shape
        y = super().forward(x.transpose(1, 2).reshape(b * t, c, h, w))
        return y.reshape(b, t, c, h, w).transpose(1, 2)


class ResBlock3d(nn.Module):
    """x + conv(SiLU(norm(conv(SiLU(norm(x)))))) with causal 3×3×3 convolutions (1×1×1 skip if widths differ).
    The second convolution starts at zero so each block starts as its skip path (Goyal et al. 2017 §5.1)."""

    def __init__(self, in_channels: int, out_channels: int, groups: int):
        super().__init__()
        self.norm1 = FrameGroupNorm(groups, in_channels)
        self.conv1 = CausalConv3d(in_channels, out_channels)
        self.norm2 = FrameGroupNorm(groups, out_channels)
        self.conv2 = CausalConv3d(out_channels, out_channels)
        nn.init.zeros_(self.conv2.conv.weight)
        nn.init.zeros_(self.conv2.conv.bias)
        self.skip = nn.Conv3d(in_channels, out_channels, 1) if in_channels != out_channels else nn.Identity()

    def forward(self, x: Tensor) -> Tensor:
        """(B, in_channels, T, H, W) → (B, out_channels, T, H, W)."""
        h = self.conv1(F.silu(self.norm1(x)))
        return self.skip(x) + self.conv2(F.silu(self.norm2(h)))


def causal_mean_pool(x: Tensor, temporal: bool) -> Tensor:
    """DC-AE down shortcut: 2×2 spatial mean and, with ``temporal``, frame 0 alone then means of frames
    (2i − 1, 2i). (B, C, T, H, W) → (B, C, T', H/2, W/2); half precision pooled in float32, returned in its dtype."""
    if temporal and x.shape[2] > 1:
        b, c, t, h, w = x.shape
        x = torch.cat([x[:, :, :1], x[:, :, 1:].reshape(b, c, (t - 1) // 2, 2, h, w).mean(3)], dim=2)
    if x.dtype in (torch.float16, torch.bfloat16):
        return F.avg_pool3d(x.float(), (1, 2, 2)).to(x.dtype)
    return F.avg_pool3d(x, (1, 2, 2))


def causal_repeat(x: Tensor, temporal: bool) -> Tensor:
    """DC-AE up shortcut (time only): with ``temporal`` frame 0 stays alone and every later frame becomes two.
    (B, C, n, H, W) → (B, C, 1 + 2(n − 1), H, W), else unchanged."""
    return torch.cat([x[:, :, :1], x[:, :, 1:].repeat_interleave(2, dim=2)], dim=2) if temporal else x


class Downsample(nn.Module):
    """Causal 3×3×3 convolution, stride (2 if temporal else 1, 2, 2), plus :func:`causal_mean_pool` of the input when
    ``shortcut``."""

    def __init__(self, channels: int, temporal: bool, shortcut: bool = True):
        super().__init__()
        self.temporal, self.shortcut = temporal, shortcut
        self.conv = CausalConv3d(channels, channels, stride=(2 if temporal else 1, 2, 2))

    def forward(self, x: Tensor) -> Tensor:
        """(B, C, T, H, W) → (B, C, T', H/2, W/2), T' = 1 + (T − 1)/2 if temporal else T (even H, W; odd T if
        temporal)."""
        y = self.conv(x)
        return y + causal_mean_pool(x, self.temporal) if self.shortcut else y


def upsample2x(x: Tensor, mode: str) -> Tensor:
    """(B, C, T, H, W) → (B, C, T, 2H, 2W), frames never mixed: ``nearest`` copies into 2×2, ``bilinear`` uses
    half-pixel weights 3/4, 1/4 (``align_corners=False``, edges clamped).

    Raises:
        ValueError: ``mode`` is not one of :data:`UPSAMPLE_MODES`.
    """
    if mode not in UPSAMPLE_MODES:
        raise ValueError(f"mode must be one of {UPSAMPLE_MODES}, got {mode!r}")
    kw = dict(scale_factor=(1.0, 2.0, 2.0), mode="trilinear" if mode == "bilinear" else "nearest",
              **({"align_corners": False} if mode == "bilinear" else {}))
    per_frame = 4 * x.shape[1] * x.shape[3] * x.shape[4]  # output elements of one frame of one sample
    if per_frame * x.shape[2] <= MAX_KERNEL_ELEMENTS or tracing():
        return F.interpolate(x, **kw)
    step = max(1, MAX_KERNEL_ELEMENTS // per_frame)  # frames never mix: windows of frames give the same values
    return torch.cat([F.interpolate(x[:, :, s:s + step], **kw) for s in range(0, x.shape[2], step)], dim=2)


class Upsample(nn.Module):
    """2× in H, W (:func:`upsample2x`) then a causal conv; ``temporal``: the conv gives 2C channels, frame 0 keeps
    the first C and later frame i becomes frames 2i − 1, 2i. ``shortcut`` adds the input repeated by
    :func:`causal_repeat`."""

    def __init__(self, channels: int, temporal: bool, shortcut: bool = True, mode: str = "nearest"):
        super().__init__()
        self.temporal, self.shortcut, self.mode = temporal, shortcut, mode
        self.conv = CausalConv3d(channels, channels * (2 if temporal else 1))

    def forward(self, x: Tensor) -> Tensor:
        """(B, C, n, H, W) → (B, C, 1 + 2(n − 1), 2H, 2W) if temporal, else (B, C, n, 2H, 2W). ValueError from
        :func:`upsample2x` on a bad mode."""
        x = upsample2x(x, self.mode)
        y = self.conv(x)
        if self.temporal:
            b, c2, n, h, w = y.shape
            c = c2 // 2
            rest = y[:, :, 1:].reshape(b, 2, c, n - 1, h, w).permute(0, 2, 3, 1, 4, 5).reshape(b, c, 2 * (n - 1), h, w)
            y = torch.cat([y[:, :c, :1], rest], dim=2)
        return y + causal_repeat(x, self.temporal) if self.shortcut else y


class Encoder(nn.Module):
    """(B, 3, T, H, W) → (B, 2c, n, H/8, W/8), mean and logvar on channels; the shortcut adds the deepest features
    averaged over groups of width/c channels to the mean."""

    def __init__(self, config: VideoVAEConfig):
        super().__init__()
        self.shortcuts, self.latent_channels = config.shortcuts, config.latent_channels
        widths, g = config.widths, config.norm_groups
        self.conv_in = CausalConv3d(config.in_channels, widths[0])
        layers: list[nn.Module] = []
        cin = widths[0]
        for i, width in enumerate(widths):
            for _ in range(config.num_res_blocks):
                layers.append(ResBlock3d(cin, width, g))
                cin = width
            if i < len(widths) - 1:
                layers.append(Downsample(width, config.temporal_downsample[i], config.shortcuts))
        layers += [ResBlock3d(cin, cin, g), ResBlock3d(cin, cin, g)]
        self.layers = nn.Sequential(*layers)
        self.norm_out = FrameGroupNorm(g, cin)
        self.conv_out = CausalConv3d(cin, 2 * config.latent_channels)

    def forward(self, x: Tensor) -> Tensor:
        """(B, in_channels, T, H, W), T = 1 + t·k → moments (B, 2c, 1 + k, H/s, W/s): mean, then unclamped logvar;
        t, s the config's temporal and spatial factors. Unchecked (:meth:`VideoVAE.encode` checks)."""
        h = self.layers(self.conv_in(x))
        out = self.conv_out(F.silu(self.norm_out(h)))
        if not self.shortcuts:
            return out
        b, width, n, hh, ww = h.shape
        c = self.latent_channels
        mean_shortcut = h.reshape(b, c, width // c, n, hh, ww).mean(2)
        return torch.cat([out[:, :c] + mean_shortcut, out[:, c:]], dim=1)


class Decoder(nn.Module):
    """(B, c, n, h, w) → (B, 3, 1 + 4(n − 1), 8h, 8w), mirror of :class:`Encoder`; the shortcut adds the latent,
    each channel repeated width/c times, after the first convolution."""

    def __init__(self, config: VideoVAEConfig):
        super().__init__()
        self.shortcuts = config.shortcuts
        widths, g = config.widths, config.norm_groups
        cin = widths[-1]
        self.conv_in = CausalConv3d(config.latent_channels, cin)
        layers: list[nn.Module] = [ResBlock3d(cin, cin, g), ResBlock3d(cin, cin, g)]
        for i in reversed(range(len(widths))):
            for _ in range(config.num_res_blocks + 1):
                layers.append(ResBlock3d(cin, widths[i], g))
                cin = widths[i]
            if i > 0:
                layers.append(Upsample(cin, config.temporal_downsample[i - 1], config.shortcuts, config.upsample))
        self.layers = nn.Sequential(*layers)
        self.norm_out = FrameGroupNorm(g, cin)
        self.conv_out = CausalConv3d(cin, config.in_channels)

    def forward(self, z: Tensor) -> Tensor:
        """Unscaled latents (B, c, n, h, w) → video (B, in_channels, 1 + t·(n − 1), s·h, s·w), nominally in [−1, 1]."""
        h = self.conv_in(z)
        if self.shortcuts:
            h = h + z.repeat_interleave(h.shape[1] // z.shape[1], dim=1)
        return self.conv_out(F.silu(self.norm_out(self.layers(h))))


def sample_posterior(mean: Tensor, logvar: Tensor, generator: torch.Generator | None = None) -> Tensor:
    """z = mean + exp(logvar/2)·ε, ε ~ N(0, I) (Kingma & Welling 2014 §2.4); differentiable in mean and logvar.

    Args:
        mean, logvar: (B, c, n, h, w), same shape.
        generator: ε is drawn on its device (a CPU generator gives the same ε everywhere), then moved to ``mean``'s.

    Raises:
        ValueError: shape mismatch.
    """
    if mean.shape != logvar.shape:
        raise ValueError(f"logvar shape {tuple(logvar.shape)} must equal mean shape {tuple(mean.shape)}")
    device = mean.device if generator is None else generator.device
    eps = torch.randn(mean.shape, generator=generator, device=device, dtype=mean.dtype).to(mean.device)
    return mean + torch.exp(0.5 * logvar) * eps


def kl_divergence(mean: Tensor, logvar: Tensor) -> Tensor:
    """KL(N(mean, exp(logvar)) ‖ N(0, I)) = ½ Σ (mean² + exp(logvar) − 1 − logvar) in nats (Kingma & Welling
    2014, App. B), summed per batch item: (B, ...) → (B,).

    Raises:
        ValueError: shape mismatch or a 0-dim input.
    """
    if mean.shape != logvar.shape or mean.ndim < 1:
        raise ValueError(f"mean {tuple(mean.shape)} and logvar {tuple(logvar.shape)} must have the same (B, ...) shape")
    kl = 0.5 * (mean.square() + logvar.exp() - 1.0 - logvar)
    return kl.reshape(kl.shape[0], -1).sum(dim=1)


def estimate_latent_scaling(latents: Tensor) -> tuple[float, float]:
    """(scaling_factor, shift_factor) = (1/std, mean) over all entries, so a·(z − b) is zero-mean unit-variance
    (Rombach et al. 2022 §4.3.2; Flux adds the shift).

    Raises:
        ValueError: fewer than 2 entries or zero std.
    """
    if latents.numel() < 2:
        raise ValueError(f"latents: need at least 2 entries to estimate a std, got {latents.numel()}")
    std = float(latents.double().std())
    if std == 0:
        raise ValueError("latents: standard deviation is 0, cannot scale")
    return 1.0 / std, float(latents.double().mean())


def check_video(config: VideoVAEConfig, video: Tensor) -> None:
    """The checks of :meth:`VideoVAE.encode` (static, safe under tracing): ``video`` (B, in_channels, T, H, W),
    T = 1 + temporal_factor·k, H, W positive multiples of spatial_factor; ValueError otherwise."""
    if video.ndim != 5 or video.shape[1] != config.in_channels:
        raise ValueError(f"video must have shape (B, {config.in_channels}, T, H, W), got {tuple(video.shape)}")
    config.num_latent_frames(video.shape[2])
    h, w = video.shape[-2:]
    if h % config.spatial_factor or w % config.spatial_factor or h == 0 or w == 0:
        raise ValueError(f"video: H={h}, W={w} must be positive multiples of {config.spatial_factor}")


def check_latents(config: VideoVAEConfig, z: Tensor) -> None:
    """The checks of :meth:`VideoVAE.decode`: ``z`` (B, latent_channels, n, h, w), n, h, w ≥ 1; ValueError otherwise."""
    if z.ndim != 5 or z.shape[1] != config.latent_channels or 0 in z.shape:
        raise ValueError(f"latents must have shape (B, {config.latent_channels}, n, h, w) with n, h, w >= 1, "
                         f"got {tuple(z.shape)}")


class VideoVAE(nn.Module, PretrainedMixin):
    """Causal video VAE: (B, 3, T, H, W) pixels in [−1, 1] ↔ (B, c, n, H/8, W/8) latents."""

    config_class = VideoVAEConfig

    def __init__(self, config: VideoVAEConfig):
        super().__init__()
        self.config = config
        self.encoder = Encoder(config)
        self.decoder = Decoder(config)

    def encode(self, video: Tensor) -> tuple[Tensor, Tensor]:
        """(B, 3, T, H, W) in [−1, 1], T = 1 + 4k → mean, logvar (B, c, 1 + k, H/8, W/8), logvar clamped to
        [−30, 20]. ValueError from :func:`check_video`."""
        check_video(self.config, video)
        moments = self.encoder(video)
        mean, logvar = moments.chunk(2, dim=1)
        return mean, logvar.clamp(*LOGVAR_RANGE)

    def sample(self, mean: Tensor, logvar: Tensor, generator: torch.Generator | None = None) -> Tensor:
        """Posterior sample, :func:`sample_posterior`."""
        return sample_posterior(mean, logvar, generator)

    def decode(self, z: Tensor) -> Tensor:
        """Raw latents (B, c, n, h, w) → (B, 3, 1 + 4(n − 1), 8h, 8w), nominally in [−1, 1] (not clamped).
        ValueError from :func:`check_latents`."""
        check_latents(self.config, z)
        return self.decoder(z)

    def forward(self, video: Tensor, sample_posterior: bool = True,
                generator: torch.Generator | None = None) -> tuple[Tensor, Tensor, Tensor]:
        """Encode, sample (or take the mean), decode: → reconstruction (B, 3, T, H, W), mean, logvar (for
        :func:`kl_divergence`)."""
        mean, logvar = self.encode(video)
        z = self.sample(mean, logvar, generator) if sample_posterior else mean
        return self.decode(z), mean, logvar

    def encode_latents(self, video: Tensor, generator: torch.Generator | None = None) -> Tensor:
        """Video (B, 3, T, H, W) in [−1, 1] → DiT latents a·(z − b) (B, c, n, H/8, W/8) (``scaling_factor``,
        ``shift_factor``), z the posterior mean, or a sample drawn with ``generator``. ValueError from
        :func:`check_video`."""
        mean, logvar = self.encode(video)
        z = mean if generator is None else self.sample(mean, logvar, generator)
        return (z - self.config.shift_factor) * self.config.scaling_factor

    def decode_latents(self, latents: Tensor) -> Tensor:
        """DiT latents → video, decode(latents / a + b); inverse of :meth:`encode_latents`."""
        return self.decode(latents / self.config.scaling_factor + self.config.shift_factor)
