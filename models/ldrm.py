"""Latent Dynamic Reconstruction Model (LDRM; Diff4Splat, Pan et al. 2025, LDRM section).

Video latent (B, c, n, h, w) + packed Plücker rays (B, 6·4·8·8, n, h, w) → pixel-aligned 3D Gaussians on the rays of
the video's source frames and, given times, deformation maps (:mod:`models.deformation`). Patchified latent and
ray tokens are embedded with a fixed 3D sine-cosine position embedding (MAE, He et al. 2022), pass ``depth``
pre-norm transformer blocks over all tokens, and a head (``"upsample"``, ours, or the paper's ``"deconv"``) turns
the token volume into 12 raw channels per pixel (:func:`gaussian_activations`). Options beyond the paper: a sharp
input-view CNN (``image_branch``) and a monocular depth network for frame 0 (``image_depth``). The Gaussians are in
the world frame of the rays; placing them on rays is ``diff4splat.assembly.assemble``'s job. Source frames,
heads and branches: docs/DESIGN.md "Data flow of generate", step 6."""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from typing import ClassVar

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .deformation import DeformationConfig, DeformationNetwork, soft_clamp, unit_quat_from_raw
from .layers import Mlp, SelfAttention, patchify
from .mono_depth import MonoDepth
from .motion import MotionConfig, MotionNetwork
from .pretrained import PretrainedMixin
from .tracing import tracing

__all__ = ["LDRMConfig", "LDRM", "LDRMOutput", "distance_activation", "gaussian_activations", "sincos_position_3d",
           "source_frame_indices", "GAUSSIAN_FRAMES", "check_ldrm_inputs"]

RAW_GAUSSIAN_CHANNELS = 12
"""Raw head channels per pixel: distance 1, scales 3, quaternion 4, opacity 1, colour 3."""

GAUSSIAN_FRAMES = ("latent", "all", "reference")
"""Values of ``LDRMConfig.gaussian_frames`` (:func:`source_frame_indices`)."""
HEADS = ("upsample", "deconv")
"""Values of ``LDRMConfig.head``."""


def source_frame_indices(gaussian_frames: str, num_latent_frames: int, vae_temporal: int = 4) -> list[int]:
    """Video frames whose rays carry a grid of Gaussians, in output order: ``"latent"`` [0, r, …, (n−1)r] with
    r = ``vae_temporal`` (the last frame each causal latent frame encodes), ``"all"`` every frame 0 … r(n−1),
    ``"reference"`` [0].

    Raises:
        ValueError: unknown ``gaussian_frames`` or ``num_latent_frames`` < 1.
    """
    if gaussian_frames not in GAUSSIAN_FRAMES:
        raise ValueError(f"gaussian_frames must be one of {GAUSSIAN_FRAMES}, got {gaussian_frames!r}")
    if int(num_latent_frames) < 1:
        raise ValueError(f"num_latent_frames must be ≥ 1, got {num_latent_frames}")
    if gaussian_frames == "reference":
        return [0]
    if gaussian_frames == "latent":
        return [i * vae_temporal for i in range(num_latent_frames)]
    return list(range(vae_temporal * (num_latent_frames - 1) + 1))


@dataclass
class LDRMConfig:
    """Sizes and output ranges of :class:`LDRM` (defaults: the tiny CPU model).

    Attributes:
        latent_channels: c, channels of the video latent.
        vae_temporal, vae_spatial: VAE compression; the Plücker input has 6·vae_temporal·vae_spatial² channels.
        patch_size: p, latent pixels per token side (1×p×p patches).
        embed_dim: D, token width; divisible by ``num_heads``, ≥ 6.
        depth, num_heads, mlp_ratio: transformer blocks, attention heads, MLP hidden width / D.
        depth_min, depth_max: range of the predicted ray distance, metres (0 < min < default < max).
        default_depth: distance for a zero raw output, metres.
        scale_base: Gaussian scale per metre of distance for a zero raw output, radians (≈ 0.7/focal in pixels,
            so neighbouring splats overlap).
        scale_log_range: scales lie within distance·scale_base·e^{±scale_log_range}.
        gaussian_frames: one of :data:`GAUSSIAN_FRAMES`.
        head: one of :data:`HEADS`; "upsample" needs ``gaussian_frames`` ≠ "all" and vae_spatial·patch_size a power
            of two.
        head_channels: channels of the first upsampling stage (halved per ×2 stage, at least 16).
        image_branch: channels of the sharp-input-view CNN; 0 = none.
        image_depth: channels of the monocular depth network (:class:`models.mono_depth.MonoDepth`) drawing frame
            0's distance; 0 = none; needs ``image_branch`` > 0.
        image_depth_grid: that network's averaging grid (``MonoDepth`` ``grid``); 0 = every pixel.
        deformation: deformation network config; ``in_channels`` must equal ``embed_dim``.
        motion: config of the motion network (:mod:`models.motion`), or None.

    Raises:
        ValueError: a field out of range or inconsistent, naming it.
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
    gaussian_frames: str = "latent"
    head: str = "upsample"
    head_channels: int = 32
    image_branch: int = 0
    image_depth: int = 0
    image_depth_grid: int = 0
    deformation: DeformationConfig = field(default_factory=DeformationConfig)
    motion: MotionConfig | None = None

    SAVED_DEFAULTS: ClassVar[dict[str, object]] = {"gaussian_frames": "reference", "head": "deconv"}
    """Values of fields missing from a saved ``config.json``: older checkpoints decode frame 0 only, with the
    transposed-convolution head."""

    def __post_init__(self) -> None:
        if isinstance(self.deformation, dict):
            self.deformation = DeformationConfig(**self.deformation)
        if isinstance(self.motion, dict):
            self.motion = MotionConfig(**self.motion)
        for name in ("latent_channels", "vae_temporal", "vae_spatial", "patch_size", "embed_dim", "depth", "num_heads"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"LDRMConfig.{name} must be ≥ 1, got {getattr(self, name)}")
        if self.gaussian_frames not in GAUSSIAN_FRAMES:
            raise ValueError(f"LDRMConfig.gaussian_frames must be one of {GAUSSIAN_FRAMES}, "
                             f"got {self.gaussian_frames!r}")
        if int(self.image_branch) < 0:
            raise ValueError(f"LDRMConfig.image_branch must be ≥ 0, got {self.image_branch}")
        if int(self.image_depth) < 0 or (self.image_depth and not self.image_branch):
            raise ValueError(f"LDRMConfig.image_depth must be ≥ 0 and needs image_branch > 0, got image_depth "
                             f"{self.image_depth}, image_branch {self.image_branch}")
        if int(self.image_depth_grid) < 0:
            raise ValueError(f"LDRMConfig.image_depth_grid must be ≥ 0, got {self.image_depth_grid}")
        if self.head not in HEADS:
            raise ValueError(f"LDRMConfig.head must be one of {HEADS}, got {self.head!r}")
        if self.head == "upsample" and self.gaussian_frames == "all":
            raise ValueError("LDRMConfig.head 'upsample' decodes one grid per latent frame; gaussian_frames 'all' "
                             "needs head 'deconv'")
        up = self.vae_spatial * self.patch_size
        if self.head == "upsample" and up & (up - 1):
            raise ValueError(f"LDRMConfig.head 'upsample' needs vae_spatial·patch_size a power of two, got {up}")
        if int(self.head_channels) < 1:
            raise ValueError(f"LDRMConfig.head_channels must be ≥ 1, got {self.head_channels}")
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
        """Paper-size LDRM (16 blocks of 64-dim tokens, 16 latent channels); the heads, 2×2 patches, deformation width
        and ``scale_base`` = 2e-3 are our choices."""
        return cls(latent_channels=16, patch_size=2, embed_dim=64, depth=16, num_heads=4,
                   scale_base=2e-3, deformation=DeformationConfig(in_channels=64, hidden=64))


@dataclass
class LDRMOutput:
    """Activated per-pixel Gaussian maps of the S source frames (j = 0 the reference frame) and optional deformation
    maps.

    Attributes:
        distance: (B, S, H, W) metres along the pixel's unit ray, in [depth_min, depth_max].
        scales: (B, S, H, W, 3) metres, > 0.
        quats: (B, S, H, W, 4) unit wxyz, world frame.
        opacities: (B, S, H, W) in [0, 1].
        colors: (B, S, H, W, 3) RGB in [0, 1].
        d_means: (B, K, S, H, W, 3) metres, world frame, or None (no times asked for).
        d_quats: (B, K, S, H, W, 4) unit wxyz, or None.
        d_scales: (B, K, S, H, W, 3) log-scale offsets (s_t = s·exp(Δs)), or None.
    """

    distance: Tensor
    scales: Tensor
    quats: Tensor
    opacities: Tensor
    colors: Tensor
    d_means: Tensor | None = None
    d_quats: Tensor | None = None
    d_scales: Tensor | None = None


# A pytree node, so torch.export / torch.onnx can trace forward (None fields are empty subtrees); torch 2.7's own
# deprecated _register_pytree_node warns, which would precede every command's output.
with warnings.catch_warnings():
    warnings.filterwarnings("ignore", message=".*_register_pytree_node.*", category=FutureWarning)
    torch.export.register_dataclass(LDRMOutput, serialized_type_name="diff4splat.LDRMOutput")


def distance_activation(r_d: Tensor, config: LDRMConfig) -> Tensor:
    """Raw distance channel (...) → ray distance (...), metres in [d_min, d_max] (:func:`gaussian_activations`);
    float32 at least."""
    r_d = r_d.to(torch.promote_types(r_d.dtype, torch.float32))
    lo, hi = math.log(config.depth_min), math.log(config.depth_max)
    frac = (math.log(config.default_depth) - lo) / (hi - lo)
    bias = math.log(frac / (1 - frac))  # logit: σ(0 + bias) = frac → distance = default_depth
    return torch.exp(lo + torch.sigmoid(r_d + bias) * (hi - lo))


def gaussian_activations(raw: Tensor, config: LDRMConfig) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """The 12 raw head channels (..., 12) (distance, scales 3, quaternion 4, opacity, colour 3) → activated
    Gaussian parameters, finite for finite input, computed in float32 at least (float64 stays float64).

    distance = exp(log d_min + σ(r_d + b)·(log d_max − log d_min)), b such that r_d = 0 gives ``default_depth``
        (a log-depth variant of GS-LRM's bounded ray distance, Zhang et al. 2024); metres in [d_min, d_max].
    scales = distance · scale_base · exp(soft_clamp(r_s, scale_log_range)), metres > 0.
    quats = normalize(r_q + (1, 0, 0, 0)), unit wxyz.
    opacities = σ(r_o), colors = σ(r_c), in [0, 1] (3DGS, Kerbl et al. 2023).

    Returns distance (...), scales (..., 3), quats (..., 4), opacities (...), colors (..., 3)."""
    raw = raw.to(torch.promote_types(raw.dtype, torch.float32))
    r_d, r_s, r_q, r_o, r_c = raw.split([1, 3, 4, 1, 3], dim=-1)
    distance = distance_activation(r_d[..., 0], config)
    scales = distance[..., None] * config.scale_base * torch.exp(soft_clamp(r_s, config.scale_log_range))
    return distance, scales, unit_quat_from_raw(r_q), torch.sigmoid(r_o[..., 0]), torch.sigmoid(r_c)


def sincos_position_3d(n: int, h: int, w: int, dim: int, device=None, dtype=torch.float32) -> Tensor:
    """Fixed 3D sine-cosine position embedding (MAE 2D recipe, He et al. 2022, extended to t, y, x): d_s =
    2·⌊dim/6⌋ channels each for row and column, the rest for the frame; each axis [sin(p·ω_k), cos(p·ω_k)],
    ω_k = 10000^{−k/(d/2)}. Returns (n·h·w, dim), order (frame, row, column), values in [−1, 1]."""
    d_s = 2 * (dim // 6)
    d_t = dim - 2 * d_s
    exact = torch.promote_types(dtype, torch.float32)  # computed in at least float32, cast once (bfloat16 weights)

    def axis(length: int, d: int) -> Tensor:  # (length, d)
        half = d // 2
        omega = torch.pow(10000.0, -torch.arange(half, device=device, dtype=exact) / max(half, 1))
        ang = torch.arange(length, device=device, dtype=exact)[:, None] * omega[None]
        emb = torch.cat([torch.sin(ang), torch.cos(ang)], dim=-1).to(dtype)
        return F.pad(emb, (0, d - 2 * half))  # odd d: one zero channel

    et, ey, ex = axis(n, d_t), axis(h, d_s), axis(w, d_s)
    return torch.cat([
        et[:, None, None].expand(n, h, w, d_t),
        ey[None, :, None].expand(n, h, w, d_s),
        ex[None, None, :].expand(n, h, w, d_s),
    ], dim=-1).reshape(n * h * w, dim)


class Block(nn.Module):
    """Pre-norm transformer block x + Attn(LN(x)), x + MLP(LN(x)) (ViT, Dosovitskiy et al. 2021); no QK-norm, no
    RoPE."""

    def __init__(self, dim: int, heads: int, mlp_ratio: float) -> None:
        super().__init__()
        self.norm1 = nn.LayerNorm(dim)
        self.attn = SelfAttention(dim, heads, qk_norm=False)
        self.norm2 = nn.LayerNorm(dim)
        self.mlp = Mlp(dim, int(dim * mlp_ratio))

    def forward(self, x: Tensor) -> Tensor:  # (B, N, D) → (B, N, D)
        x = x + self.attn(self.norm1(x))
        return x + self.mlp(self.norm2(x))


class UpsampleHead(nn.Module):
    """Token map → raw Gaussian channels per pixel, with overlap (ours, instead of the paper's kernel = stride
    transposed convolution): log₂ f stages of [3×3 conv C_k → 4·C_{k+1}, ×2 pixel shuffle (Shi et al. 2016), GELU],
    C_{k+1} = max(16, C_k / 2), then a 3×3 conv to 12 channels. (N, D, h, w) → (N, 12, f·h, f·w)."""

    def __init__(self, dim: int, factor: int, channels: int) -> None:
        super().__init__()
        stages, c_in, c = [], dim, channels
        for _ in range(int(round(math.log2(factor)))):
            stages += [nn.Conv2d(c_in, 4 * c, 3, padding=1), nn.PixelShuffle(2), nn.GELU()]
            c_in, c = c, max(16, c // 2)
        self.stages = nn.Sequential(*stages)
        self.out = nn.Conv2d(c_in, RAW_GAUSSIAN_CHANNELS, 3, padding=1)

    def forward(self, x: Tensor) -> Tensor:  # (N, D, h, w) → (N, 12, f·h, f·w)
        return self.out(self.stages(x))


class ImageBranch(nn.Module):
    """Sharp input view (ours): photo + frame 0's raw head output → a raw-channel residual. conv3×3(15 → C), GELU,
    conv3×3(C → C), GELU, conv1×1(C → 12); the last layer starts at zero so a new branch adds exactly 0 (as DiT's
    adaLN-Zero)."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(3 + RAW_GAUSSIAN_CHANNELS, channels, 3, padding=1)
        self.conv2 = nn.Conv2d(channels, channels, 3, padding=1)
        self.out = nn.Conv2d(channels, RAW_GAUSSIAN_CHANNELS, 1)
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)

    def forward(self, image: Tensor, raw: Tensor) -> Tensor:  # (B, 3, H, W) in [−1, 1], (B, 12, H, W)
        """raw + residual: ``image`` (B, 3, H, W) in [−1, 1], ``raw`` (B, 12, H, W) → (B, 12, H, W) raw channels."""
        x = F.gelu(self.conv1(torch.cat([image.to(raw.dtype), raw], dim=1)))
        return raw + self.out(F.gelu(self.conv2(x)))  # (B, 12, H, W)


def check_ldrm_inputs(config: LDRMConfig, latents: Tensor, plucker: Tensor, times: Tensor | None,
                      image: Tensor | None) -> None:
    """The checks of :meth:`LDRM.forward` (shapes static under tracing, the time range eager only); the ONNX runtime
    makes them too. ValueError as :meth:`LDRM.forward`."""
    cfg = config
    if latents.dim() != 5 or latents.shape[1] != cfg.latent_channels:
        raise ValueError(f"latents must have shape (B, {cfg.latent_channels}, n, h, w), got {tuple(latents.shape)}")
    B, _, n, h, w = latents.shape
    if h % cfg.patch_size or w % cfg.patch_size:
        raise ValueError(f"latents: h, w = {h}, {w} must be multiples of patch_size {cfg.patch_size}")
    if plucker.dim() != 5 or plucker.shape[1] != cfg.plucker_channels:
        raise ValueError(f"plucker must have shape (B, {cfg.plucker_channels}, n, h, w), got {tuple(plucker.shape)}")
    if plucker.shape[0] != B or tuple(plucker.shape[2:]) != (n, h, w):
        raise ValueError(f"plucker {tuple(plucker.shape)} must match latents {tuple(latents.shape)} in B, n, h, w "
                         "(equal token counts)")
    if times is not None:
        if times.dim() != 1 or times.shape[0] < 1:
            raise ValueError(f"times must have shape (K,) with K ≥ 1, got {tuple(times.shape)}")
        if not tracing() and not bool(((times >= 0) & (times <= 1)).all()):
            raise ValueError(f"times must lie in [0, 1], got min {float(times.min())}, max {float(times.max())}")
    if cfg.image_branch > 0:
        H, W = h * cfg.vae_spatial, w * cfg.vae_spatial
        if image is None or tuple(image.shape) != (B, 3, H, W):
            got = None if image is None else tuple(image.shape)
            raise ValueError(f"image must have shape ({B}, 3, {H}, {W}) (this LDRM has an image branch), got {got}")


class LDRM(nn.Module, PretrainedMixin):
    """Video latent + camera path (+ photo) → pixel-aligned Gaussians of the source frames (+ deformation maps)
    (module docstring)."""

    config_class = LDRMConfig

    def __init__(self, config: LDRMConfig) -> None:
        super().__init__()
        self.config = config
        p, d = config.patch_size, config.embed_dim
        self.embed = nn.Linear((config.latent_channels + config.plucker_channels) * p * p, d)
        self.blocks = nn.ModuleList(Block(d, config.num_heads, config.mlp_ratio) for _ in range(config.depth))
        self.norm = nn.LayerNorm(d)
        up = config.vae_spatial * p
        kt = config.vae_temporal if config.gaussian_frames == "all" else 1
        self.head = (nn.ConvTranspose3d(d, RAW_GAUSSIAN_CHANNELS, kernel_size=(kt, up, up), stride=(kt, up, up))
                     if config.head == "deconv" else UpsampleHead(d, up, config.head_channels))
        self.image_branch = ImageBranch(config.image_branch) if config.image_branch > 0 else None
        self.image_depth = (MonoDepth(config.image_depth, grid=config.image_depth_grid) if config.image_depth > 0
                            else None)
        self.deformation = DeformationNetwork(config.deformation)
        self.motion = MotionNetwork(config.motion) if config.motion is not None else None
        for module in [self.embed, *self.blocks.modules()]:
            if isinstance(module, nn.Linear):  # ViT/DiT initialisation
                nn.init.xavier_uniform_(module.weight)
                nn.init.zeros_(module.bias)

    def features(
        self,
        latents: Tensor,  # (B, c, n, h, w)
        plucker: Tensor,  # (B, 6·4·8·8, n, h, w)
    ) -> Tensor:  # (B, D, n', h/p, w/p)
        """The transformer's token volume: latents (B, c, n, h, w) (h, w multiples of p) and packed Plücker rays
        (cast to the latents' dtype) → (B, D, n', h/p, w/p), n' = n, or 1 for ``gaussian_frames`` "reference".
        Unchecked."""
        cfg = self.config
        p = cfg.patch_size
        B, _, n, h, w = latents.shape
        hp, wp = h // p, w // p
        tokens = torch.cat([patchify(latents, (1, p, p)), patchify(plucker.to(latents.dtype), (1, p, p))], dim=-1)
        x = self.embed(tokens) + sincos_position_3d(n, hp, wp, cfg.embed_dim, latents.device, latents.dtype)
        for block in self.blocks:
            x = block(x)
        x = self.norm(x)
        volume = x.transpose(1, 2).reshape(B, cfg.embed_dim, n, hp, wp)
        return volume[:, :, :1] if cfg.gaussian_frames == "reference" else volume

    def head_maps(self, volume: Tensor) -> Tensor:  # (B, D, n', h', w') → (B, 12, S, H, W)
        """Raw Gaussian channels (B, 12, S, H, W) of the S source frames from a :meth:`features` volume
        (B, D, n', h', w'); H = h'·p·vae_spatial; S = n', or vae_temporal·(n' − 1) + 1 for "all" (the deconv head's
        first vae_temporal − 1 frames dropped)."""
        cfg = self.config
        B, D, nv, hp, wp = volume.shape
        if cfg.head == "deconv":
            raw = self.head(volume)  # (B, 12, S', H, W)
        else:  # each latent frame's token map decoded on its own: (B·n', D, hp, wp) → (B·n', 12, H, W)
            frames = self.head(volume.transpose(1, 2).reshape(B * nv, D, hp, wp))
            raw = frames.reshape(B, nv, RAW_GAUSSIAN_CHANNELS, *frames.shape[-2:]).transpose(1, 2)
        if cfg.gaussian_frames == "all":
            raw = raw[:, :, cfg.vae_temporal - 1:]  # the causal first latent frame encodes frame 0 only
        return raw

    def forward(
        self,
        latents: Tensor,  # (B, c, n, h, w)
        plucker: Tensor,  # (B, 6·4·8·8, n, h, w) from diff4splat.cameras.pack_plucker
        times: Tensor | None = None,  # (K,) in [0, 1]
        image: Tensor | None = None,  # (B, 3, H, W) in [−1, 1], the photograph (frame 0)
    ) -> LDRMOutput:
        """The source frames' Gaussians (H = 8h, W = 8w pixels) and their deformation at ``times``.

        Args:
            latents: (B, c, n, h, w) video latent.
            plucker: (B, 6·vae_temporal·vae_spatial², n, h, w) packed Plücker rays (``pack_plucker``).
            times: (K,) clip times in [0, 1], or None (static: no deformation network run).
            image: (B, 3, H, W) frame 0 in [−1, 1]; required with an image branch, ignored without.

        Returns:
            :class:`LDRMOutput`: maps (B, S, H, W, ·), S = len(:func:`source_frame_indices`); deformation maps
            (B, K, S, H, W, ·) or None.

        Raises:
            ValueError: wrong rank/channels of ``latents`` or ``plucker``, mismatched B, n, h, w, h, w not multiples of
                patch_size, ``times`` not (K,) in [0, 1], ``image`` missing or misshapen with an image branch.
        """
        check_ldrm_inputs(self.config, latents, plucker, times, image)
        cfg = self.config
        volume = self.features(latents, plucker)
        raw = self.head_maps(volume)
        if self.image_branch is not None:  # frame 0 only; a select, not a cat, keeps S symbolic when exporting
            first = torch.arange(raw.shape[2], device=raw.device) == 0
            frame0 = self.image_branch(image, raw[:, :, 0])  # (B, 12, H, W)
            if self.image_depth is not None:  # frame 0's distance from the photograph alone
                frame0 = torch.cat([self.image_depth(image.to(raw.dtype))[:, None], frame0[:, 1:]], dim=1)
            raw = torch.where(first[:, None, None], frame0[:, :, None], raw)
        raw = raw.permute(0, 2, 3, 4, 1)  # (B, S, H, W, 12)
        distance, scales, quats, opacities, colors = gaussian_activations(raw, cfg)
        out = LDRMOutput(distance, scales, quats, opacities, colors)
        if times is not None:
            S, nf = raw.shape[1], volume.shape[2]
            B, _, _, hp, wp = volume.shape
            # Contiguous: a channels-last view gives out_conv's weight gradient other strides, and DDP warns.
            feats = volume.transpose(1, 2).reshape(B * nf, cfg.embed_dim, hp, wp).contiguous()
            d = self.deformation(feats, times, cfg.vae_spatial * cfg.patch_size)  # each (B·nf, K, H, W, ·)
            maps = [m.reshape(B, nf, *m.shape[1:]).transpose(1, 2) for m in d]  # (B, K, nf, H, W, ·)
            if cfg.gaussian_frames == "all":  # frame f belongs to latent frame ⌈f / r⌉
                index = (torch.arange(S, device=raw.device) + cfg.vae_temporal - 1) // cfg.vae_temporal
                maps = [m.index_select(2, index) for m in maps]
            out.d_means, out.d_quats, out.d_scales = maps
        return out
