"""Latent Dynamic Reconstruction Model (LDRM; Diff4Splat, Pan et al. 2025, LDRM section).

Decodes a video latent plus the camera path (Plücker rays packed to latent resolution) into
pixel-aligned 3D Gaussians of the reference frame (frame 0) and, when times are given, deformation
maps at those times (:mod:`models.deformation`).

Architecture (B scenes, latent (B, c, n, h, w), patch p, tokens N = n·(h/p)·(w/p), width D):

1. Patchify latents and packed Plücker rays (1×p×p each) → (B, N, c·p²) and (B, N, 1536·p²),
   concatenate channel-wise, ``Linear`` → (B, N, D) plus a fixed 3D sine-cosine position
   embedding (per axis as in MAE, He et al. 2022; channels split over t, y, x).
2. ``depth`` pre-norm transformer blocks (ViT/DiT: x += Attn(LN(x)); x += MLP(LN(x))) with
   self-attention over all spatio-temporal tokens, then a final LayerNorm.
3. Reference latent frame's tokens → (B, D, 1, h/p, w/p) → ``ConvTranspose3d`` with
   kernel = stride = (1, 8p, 8p) (undoing patching and the VAE's 8×8 spatial compression)
   → 12 raw channels per pixel of frame 0 → activations (:func:`gaussian_activations`).
4. The same reference tokens as a (B, D, h/p, w/p) map feed the deformation network.

Gaussians are predicted in the world frame in which the Plücker rays are given (the network
sees world-frame rays). The network returns plain tensors (:class:`LDRMOutput`); placing each
pixel's Gaussian on its camera ray (``diff4splat.pipeline.to_gaussians``) is the pipeline's job.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .deformation import DeformationConfig, DeformationNetwork, soft_clamp, unit_quat_from_raw
from .layers import Mlp, SelfAttention, patchify
from .pretrained import PretrainedMixin

__all__ = ["LDRMConfig", "LDRM", "LDRMOutput", "gaussian_activations", "sincos_position_3d"]

RAW_GAUSSIAN_CHANNELS = 12
"""Raw head channels per pixel: distance 1, scales 3, quaternion 4, opacity 1, colour 3."""


@dataclass
class LDRMConfig:
    """Sizes and output ranges of :class:`LDRM` (defaults: the tiny CPU model, ~0.3 M parameters).

    Attributes:
        latent_channels: c, channels of the video latent.
        vae_temporal, vae_spatial: VAE compression (4× time, 8×8 space); the Plücker input has
            6·vae_temporal·vae_spatial² channels (``pack_plucker``).
        patch_size: p, latent pixels per token side (1×p×p patches).
        embed_dim: D, token width; divisible by ``num_heads``.
        depth: number of transformer blocks.
        num_heads: attention heads.
        mlp_ratio: MLP hidden width / D.
        depth_min, depth_max: range of the predicted ray distance, metres (0 < min < default < max).
        default_depth: distance for a zero raw output, metres.
        scale_base: Gaussian scale per metre of distance for a zero raw output, radians: about
            0.7 of a pixel's angular size 1/focal (0.01 ↔ focal ≈ 70 px, the tiny 64 px model at 50° fov),
            so neighbouring pixel-aligned splats overlap without each covering many pixels.
        scale_log_range: bound of the log-scale adjustment; scales lie within
            distance·scale_base·e^{±scale_log_range}.
        deformation: config of the deformation network; its ``in_channels`` must equal ``embed_dim``.
    """

    latent_channels: int = 4
    vae_temporal: int = 4
    vae_spatial: int = 8
    patch_size: int = 1
    embed_dim: int = 64
    depth: int = 2
    num_heads: int = 4
    mlp_ratio: float = 4.0
    depth_min: float = 0.1
    depth_max: float = 100.0
    default_depth: float = 2.0
    scale_base: float = 0.01
    scale_log_range: float = 4.0
    deformation: DeformationConfig = field(default_factory=DeformationConfig)

    def __post_init__(self) -> None:
        if isinstance(self.deformation, dict):
            self.deformation = DeformationConfig(**self.deformation)
        for name in ("latent_channels", "vae_temporal", "vae_spatial", "patch_size", "embed_dim", "depth", "num_heads"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"LDRMConfig.{name} must be ≥ 1, got {getattr(self, name)}")
        if self.embed_dim % self.num_heads:
            raise ValueError(f"LDRMConfig.embed_dim ({self.embed_dim}) must be divisible by "
                             f"num_heads ({self.num_heads})")
        if self.embed_dim < 6:
            raise ValueError(f"LDRMConfig.embed_dim must be ≥ 6 for the 3D position embedding, got {self.embed_dim}")
        if not 0 < self.depth_min < self.default_depth < self.depth_max:
            raise ValueError("LDRMConfig needs 0 < depth_min < default_depth < depth_max, got "
                             f"{self.depth_min}, {self.default_depth}, {self.depth_max}")
        for name in ("scale_base", "scale_log_range", "mlp_ratio"):
            if not float(getattr(self, name)) > 0:
                raise ValueError(f"LDRMConfig.{name} must be > 0, got {getattr(self, name)}")
        if self.deformation.in_channels != self.embed_dim:
            raise ValueError(f"LDRMConfig.deformation.in_channels ({self.deformation.in_channels}) must equal "
                             f"embed_dim ({self.embed_dim})")

    @property
    def plucker_channels(self) -> int:
        """6·vae_temporal·vae_spatial² (1536 for 4×8×8)."""
        return 6 * self.vae_temporal * self.vae_spatial**2

    @classmethod
    def paper(cls) -> LDRMConfig:
        """Paper-size LDRM (docs/DESIGN.md: 16 blocks, 64-dim tokens; 16 latent channels; 2×2 patches).

        Heads (4 × 16 dims), patch size 2, the deformation width 64 and ``scale_base`` = 2e-3
        (≈ 1/focal for a ~500 px focal length at the paper's 480×720-class resolution) are our
        choices, not published numbers. Only instantiated on ``torch.device("meta")`` in tests.
        """
        return cls(latent_channels=16, patch_size=2, embed_dim=64, depth=16, num_heads=4,
                   scale_base=2e-3, deformation=DeformationConfig(in_channels=64, hidden=64))


@dataclass
class LDRMOutput:
    """Activated per-pixel Gaussian maps of the reference frame and optional deformation maps.

    Attributes:
        distance: (B, H, W) metres along the pixel's unit ray, in [depth_min, depth_max].
        scales: (B, H, W, 3) metres, > 0.
        quats: (B, H, W, 4) unit wxyz, world frame.
        opacities: (B, H, W) in [0, 1] (open interval except where sigmoid saturates in float).
        colors: (B, H, W, 3) RGB in [0, 1].
        d_means: (B, K, H, W, 3) metres, world frame, or None (static: no times asked for).
        d_quats: (B, K, H, W, 4) unit wxyz (identity (1,0,0,0)), or None.
        d_scales: (B, K, H, W, 3) log-scale offsets (s_t = s·exp(Δs)), or None.
    """

    distance: Tensor
    scales: Tensor
    quats: Tensor
    opacities: Tensor
    colors: Tensor
    d_means: Tensor | None = None
    d_quats: Tensor | None = None
    d_scales: Tensor | None = None


# Register the output as a pytree node so torch.export / torch.onnx (dynamo) can trace the
# model's forward directly; the None deformation fields of a static scene are empty subtrees.
torch.export.register_dataclass(LDRMOutput, serialized_type_name="diff4splat.LDRMOutput")


def gaussian_activations(raw: Tensor, config: LDRMConfig) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Map the 12 raw head channels (..., 12) to activated Gaussian parameters; finite for any finite input.

    distance = exp(log d_min + σ(r_d + b)·(log d_max − log d_min)), with b chosen so r_d = 0 gives
        ``default_depth``; a sigmoid in log-depth (scale-uniform; our variant of the near/far-bounded
        sigmoid ray distance of pixel-aligned LRMs such as GS-LRM, Zhang et al. 2024), values in
        [d_min, d_max] metres (reached exactly only where the sigmoid saturates in float).
    scales = distance · scale_base · exp(soft_clamp(r_s, scale_log_range)): a pixel footprint
        (distance/focal with scale_base ≈ 1/focal) times a learned factor in e^{±range}; metres > 0.
    quats = normalize(r_q + (1, 0, 0, 0)): unit wxyz; zero raw → identity.
    opacities = σ(r_o) in [0, 1] (3DGS, Kerbl et al. 2023).
    colors = σ(r_c) in [0, 1].

    Args:
        raw: (..., 12) in channel order distance, scales (3), quaternion (4), opacity, colour (3).

    Returns:
        distance (...), scales (..., 3), quats (..., 4), opacities (...), colors (..., 3).
    """
    r_d, r_s, r_q, r_o, r_c = raw.split([1, 3, 4, 1, 3], dim=-1)
    lo, hi = math.log(config.depth_min), math.log(config.depth_max)
    frac = (math.log(config.default_depth) - lo) / (hi - lo)
    bias = math.log(frac / (1 - frac))  # logit: σ(0 + bias) = frac → distance = default_depth
    distance = torch.exp(lo + torch.sigmoid(r_d[..., 0] + bias) * (hi - lo))
    scales = distance[..., None] * config.scale_base * torch.exp(soft_clamp(r_s, config.scale_log_range))
    return distance, scales, unit_quat_from_raw(r_q), torch.sigmoid(r_o[..., 0]), torch.sigmoid(r_c)


def sincos_position_3d(n: int, h: int, w: int, dim: int, device=None, dtype=torch.float32) -> Tensor:
    """Fixed 3D sine-cosine position embedding (MAE 2D recipe, He et al. 2022, extended to t, y, x).

    Channels: ``dim − 2·d_s`` for the frame index, ``d_s`` each for row and column, with
    d_s = 2·⌊dim/6⌋; each axis uses [sin(p·ω_k), cos(p·ω_k)], ω_k = 10000^{−k/(d/2)}.

    Returns:
        (n·h·w, dim), token order (frame, row, column) row-major; values in [−1, 1].
    """
    d_s = 2 * (dim // 6)
    d_t = dim - 2 * d_s

    def axis(length: int, d: int) -> Tensor:  # (length, d)
        half = d // 2
        omega = torch.pow(10000.0, -torch.arange(half, device=device, dtype=dtype) / max(half, 1))
        ang = torch.arange(length, device=device, dtype=dtype)[:, None] * omega[None]
        emb = torch.cat([torch.sin(ang), torch.cos(ang)], dim=-1)
        return F.pad(emb, (0, d - 2 * half))  # odd d: one zero channel

    et, ey, ex = axis(n, d_t), axis(h, d_s), axis(w, d_s)
    return torch.cat([
        et[:, None, None].expand(n, h, w, d_t),
        ey[None, :, None].expand(n, h, w, d_s),
        ex[None, None, :].expand(n, h, w, d_s),
    ], dim=-1).reshape(n * h * w, dim)


class Block(nn.Module):
    """Pre-norm transformer block: x + Attn(LN(x)), then x + MLP(LN(x)) (ViT, Dosovitskiy et al. 2021).

    Attention and MLP are the shared :class:`models.layers.SelfAttention` (no QK-norm, no RoPE:
    positions enter as the additive sine-cosine embedding) and :class:`models.layers.Mlp`.
    """

    def __init__(self, dim: int, heads: int, mlp_ratio: float) -> None:
        super().__init__()
        self.norm1 = nn.LayerNorm(dim)
        self.attn = SelfAttention(dim, heads, qk_norm=False)
        self.norm2 = nn.LayerNorm(dim)
        self.mlp = Mlp(dim, int(dim * mlp_ratio))

    def forward(self, x: Tensor) -> Tensor:  # (B, N, D) → (B, N, D)
        x = x + self.attn(self.norm1(x))
        return x + self.mlp(self.norm2(x))


def _tracing() -> bool:
    """True while torch.export / dynamo / jit trace the model (value checks are then skipped)."""
    return torch.compiler.is_exporting() or torch.compiler.is_compiling() or torch.jit.is_tracing()


class LDRM(nn.Module, PretrainedMixin):
    """Video latent + camera path → pixel-aligned Gaussians of frame 0 (+ deformation maps)."""

    config_class = LDRMConfig

    def __init__(self, config: LDRMConfig) -> None:
        super().__init__()
        self.config = config
        p, d = config.patch_size, config.embed_dim
        self.embed = nn.Linear((config.latent_channels + config.plucker_channels) * p * p, d)
        self.blocks = nn.ModuleList(Block(d, config.num_heads, config.mlp_ratio) for _ in range(config.depth))
        self.norm = nn.LayerNorm(d)
        up = config.vae_spatial * p
        self.head = nn.ConvTranspose3d(d, RAW_GAUSSIAN_CHANNELS, kernel_size=(1, up, up), stride=(1, up, up))
        self.deformation = DeformationNetwork(config.deformation)
        for module in [self.embed, *self.blocks.modules()]:
            if isinstance(module, nn.Linear):  # ViT/DiT initialisation
                nn.init.xavier_uniform_(module.weight)
                nn.init.zeros_(module.bias)

    def _check_inputs(self, latents: Tensor, plucker: Tensor, times: Tensor | None) -> None:
        cfg = self.config
        if latents.dim() != 5 or latents.shape[1] != cfg.latent_channels:
            raise ValueError(f"latents must have shape (B, {cfg.latent_channels}, n, h, w), got {tuple(latents.shape)}")
        B, _, n, h, w = latents.shape
        if h % cfg.patch_size or w % cfg.patch_size:
            raise ValueError(f"latents: h, w = {h}, {w} must be multiples of patch_size {cfg.patch_size}")
        if plucker.dim() != 5 or plucker.shape[1] != cfg.plucker_channels:
            raise ValueError(f"plucker must have shape (B, {cfg.plucker_channels}, n, h, w), "
                             f"got {tuple(plucker.shape)}")
        if plucker.shape[0] != B or tuple(plucker.shape[2:]) != (n, h, w):
            raise ValueError(f"plucker {tuple(plucker.shape)} must match latents {tuple(latents.shape)} in B, n, h, w "
                             "(equal token counts)")
        if times is not None:
            if times.dim() != 1 or times.shape[0] < 1:
                raise ValueError(f"times must have shape (K,) with K ≥ 1, got {tuple(times.shape)}")
            if not _tracing() and not bool(((times >= 0) & (times <= 1)).all()):
                raise ValueError(f"times must lie in [0, 1], got min {float(times.min())}, max {float(times.max())}")

    def forward(
        self,
        latents: Tensor,  # (B, c, n, h, w)
        plucker: Tensor,  # (B, 6·4·8·8, n, h, w) from diff4splat.cameras.pack_plucker
        times: Tensor | None = None,  # (K,) in [0, 1]
    ) -> LDRMOutput:
        """Predict the reference frame's Gaussians (H = 8h, W = 8w pixels) and deformation at ``times``.

        Args:
            latents: (B, c, n, h, w) video latent, c = ``config.latent_channels``.
            plucker: (B, 6·vae_temporal·vae_spatial², n, h, w) packed Plücker rays (``pack_plucker``).
            times: (K,) clip times in [0, 1], or None for a static scene (the deformation network
                is then not run and the deformation fields are None).

        Returns:
            :class:`LDRMOutput` with activated maps (see :func:`gaussian_activations` for formulas)
            and deformation maps (B, K, H, W, ·) or None.

        Raises:
            ValueError: wrong rank/channels of ``latents`` or ``plucker``; ``plucker`` not matching
                ``latents`` in B, n, h, w; h, w not multiples of patch_size; ``times`` not (K,) or
                outside [0, 1].
        """
        self._check_inputs(latents, plucker, times)
        cfg = self.config
        p = cfg.patch_size
        B, _, n, h, w = latents.shape
        hp, wp = h // p, w // p
        tokens = torch.cat([patchify(latents, (1, p, p)), patchify(plucker.to(latents.dtype), (1, p, p))], dim=-1)
        x = self.embed(tokens) + sincos_position_3d(n, hp, wp, cfg.embed_dim, latents.device, latents.dtype)
        for block in self.blocks:
            x = block(x)
        x = self.norm(x)
        ref = x[:, : hp * wp].transpose(1, 2).reshape(B, cfg.embed_dim, hp, wp)  # frame-0 tokens
        raw = self.head(ref[:, :, None])[:, :, 0].permute(0, 2, 3, 1)  # (B, H, W, 12)
        distance, scales, quats, opacities, colors = gaussian_activations(raw, cfg)
        out = LDRMOutput(distance, scales, quats, opacities, colors)
        if times is not None:
            out.d_means, out.d_quats, out.d_scales = self.deformation(ref, times, cfg.vae_spatial * p)
        return out

