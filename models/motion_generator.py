"""The motion generator: each source pixel's 3D scene flow over the clip, generated as a target of its own before the
video (docs/DESIGN.md, "The motion generator").

Motion is a small tensor (Motion-I2V, Shi et al. SIGGRAPH 2024; LFDM, Ni et al. CVPR 2023: generate the motion
field first, at low dimension): on a ``grid``² of cells over the photograph, for each of ``key_frames`` key times
t_k = k/K (k = 1…K), the mean displacement X(t_k) − X(0) of the cell's surface points divided by their z-depth
(scale-free: a monocular photograph fixes no metric scale), in the reference camera's frame (x right, y down,
z forward), in units of ``motion_scale``. A DiT (Peebles & Xie 2023) over the cells denoises it with flow matching
(:mod:`models.flow_matching`), conditioned on the photograph and its log-depth (one patch per cell, embedded and
added to the cell's token) and, through adaLN-Zero alone (DiT Fig. 5: better than cross-attention), on σ and a pooled
embedding of the prompt (MAGE, Hu et al. CVPR 2022: direction words learned from scratch by a small text transformer).
A learned null embedding stands for the dropped caption (classifier-free guidance, Ho & Salimans 2022).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from diff4splat.utils.checks import check_number, check_ranges, ranged

from .dit import FinalLayer, VideoDiTBlock
from .flow_matching import sample
from .layers import Mlp, TimestepEmbedder
from .pretrained import PretrainedMixin
from .rope import rope_3d
from .text_encoder import TextEncoder, TextEncoderConfig

__all__ = ["MotionGeneratorConfig", "MotionGenerator", "PromptEmbedding", "key_frame_indices", "depth_features",
           "motion_targets", "motion_displacements", "sample_motion"]


@dataclass
class MotionGeneratorConfig:
    """Sizes of :class:`MotionGenerator`.

    Attributes:
        image_size: side of the photograph and depth map it reads, pixels (a multiple of ``grid``).
        grid: cells per side of the motion.
        key_frames: K, key times k/K of the clip (k = 1…K; time 0 has no motion by definition).
        hidden_size, depth, num_heads, mlp_ratio: the transformer over the grid² cell tokens.
        motion_scale: the unit of the motion tensor: displacement over z-depth (dimensionless).
        text: the prompt's text encoder (its tokens are mean-pooled; 320 bytes: a synthetic caption naming several
            objects and the camera runs to ~260).
        text_attention: the cells also cross-attend to the text tokens (PixArt-α), beside the pooled embedding's
            adaLN (the ablation of DiT's finding).
        norm_eps: LayerNorm epsilon.

    Raises:
        ValueError: a field out of range, ``image_size`` not a multiple of ``grid``, or a head width that is not a
            multiple of 6.
    """

    image_size: int = ranged(64)
    grid: int = ranged(16)
    key_frames: int = ranged(4)
    hidden_size: int = ranged(96)
    depth: int = ranged(4)
    num_heads: int = ranged(4)
    mlp_ratio: float = ranged(4.0, check_number, lo=0, lo_open=True)
    motion_scale: float = ranged(0.1, check_number, lo=0, lo_open=True)
    text: TextEncoderConfig = field(default_factory=lambda: TextEncoderConfig(max_length=320))
    text_attention: bool = False
    norm_eps: float = 1e-6

    def __post_init__(self) -> None:
        check_ranges("MotionGeneratorConfig", self)
        if self.image_size % self.grid:
            raise ValueError(f"MotionGeneratorConfig.image_size ({self.image_size}) must be a multiple of grid "
                             f"({self.grid})")
        if self.hidden_size % self.num_heads or (self.hidden_size // self.num_heads) % 6:
            raise ValueError(f"MotionGeneratorConfig.hidden_size ({self.hidden_size}) / num_heads ({self.num_heads}) "
                             "must be a multiple of 6 (3D RoPE)")

    @property
    def channels(self) -> int:
        """Channels of the motion tensor: 3 per key time."""
        return 3 * self.key_frames


def key_frame_indices(num_frames: int, key_frames: int) -> list[int]:
    """The clip frames of the key times k/K, k = 1…K: round(k·(T − 1)/K). Raises ValueError for T − 1 < K."""
    if num_frames - 1 < key_frames:
        raise ValueError(f"a clip of {num_frames} frames has fewer than {key_frames} frames after its first")
    return [round(k * (num_frames - 1) / key_frames) for k in range(1, key_frames + 1)]


def depth_features(depth: Tensor) -> Tensor:
    """(B, 2, H, W): the log z-depth less its median over each map's finite pixels (0 where not finite), and the
    finite flag, from ``depth`` (B, H, W) metres (+inf or NaN: no surface). Scale-free: depth × s gives the same."""
    valid = torch.isfinite(depth) & (depth > 0)
    log_z = torch.where(valid, depth, torch.ones_like(depth)).log()
    median = torch.where(valid, log_z, float("nan")).flatten(1).nanmedian(dim=1).values.nan_to_num(0.0)
    return torch.stack([torch.where(valid, log_z - median[:, None, None], 0.0), valid.to(depth.dtype)], dim=1)


def motion_targets(pixel_tracks: Tensor, valid: Tensor, key_frames: int, grid: int, motion_scale: float
                   ) -> tuple[Tensor, Tensor]:
    """The motion tensor of true dense tracks and each cell's weight.

    Args:
        pixel_tracks: (B, T, H, W, 3) clip-world metres, where frame 0's pixel's surface point is at each frame (the
            reference camera's frame at time 0: its z is the pixel's depth).
        valid: (B, H, W) bool, the pixel's track is known.
        key_frames, grid, motion_scale: as :class:`MotionGeneratorConfig`.

    Returns:
        motion (B, 3K, grid, grid): per cell, key time k-major then xyz, the mean of (X_k − X_0)/z_0 over its valid
        pixels over ``motion_scale`` (0 where none); weight (B, 1, grid, grid) the cell's valid fraction in [0, 1].

    Raises:
        ValueError: H or W not a multiple of ``grid``, or too few frames for ``key_frames``.
    """
    B, T, H, W, _ = pixel_tracks.shape
    if H % grid or W % grid:
        raise ValueError(f"the tracks' {H}×{W} pixels must be a multiple of the grid {grid}")
    keys = key_frame_indices(T, key_frames)
    x0 = pixel_tracks[:, 0]  # (B, H, W, 3)
    ok = valid & torch.isfinite(x0).all(-1) & (x0[..., 2] > 0)
    z0 = torch.where(ok, x0[..., 2], torch.ones_like(x0[..., 2]))
    rel = (pixel_tracks[:, keys] - x0[:, None]) / z0[:, None, ..., None]  # (B, K, H, W, 3)
    rel = torch.where(ok[:, None, ..., None], rel, 0.0)
    rel = rel.permute(0, 1, 4, 2, 3).reshape(B, 3 * key_frames, H, W)
    w = ok.to(rel.dtype)[:, None]
    count = F.adaptive_avg_pool2d(w, grid)
    mean = F.adaptive_avg_pool2d(rel, grid) / count.clamp_min(1e-12)
    return mean / motion_scale, count


def motion_displacements(motion: Tensor, depth: Tensor, motion_scale: float) -> Tensor:
    """(B, K, H, W, 3) metres in the reference camera's frame: each pixel's displacement from time 0 at the key
    times, from ``motion`` (B, 3K, g, g) (:func:`motion_targets`' layout) bilinearly upsampled to ``depth``'s
    (B, H, W) metres pixels and multiplied by their depth; 0 where the depth is not finite."""
    B, C, _, _ = motion.shape
    H, W = depth.shape[-2:]
    up = F.interpolate(motion, size=(H, W), mode="bilinear", align_corners=False) * motion_scale
    up = up.reshape(B, C // 3, 3, H, W).permute(0, 1, 3, 4, 2)
    valid = torch.isfinite(depth) & (depth > 0)
    z = torch.where(valid, depth, torch.zeros_like(depth))
    return up * z[:, None, ..., None]


class PromptEmbedding(NamedTuple):
    """The prompts as the generator reads them: ``pooled`` (B, d_text); with ``text_attention``, ``tokens``
    (B, L, d_text) and ``mask`` (B, L) bool (all False for a dropped caption: no cross-attention), else None."""

    pooled: Tensor
    tokens: Tensor | None = None
    mask: Tensor | None = None

    def cat(self, other: PromptEmbedding) -> PromptEmbedding:
        """Both batches, this one first (token sequences padded to the longer)."""
        if self.tokens is None:
            return PromptEmbedding(torch.cat([self.pooled, other.pooled]))
        L = max(self.tokens.shape[1], other.tokens.shape[1])
        tokens = [F.pad(t, (0, 0, 0, L - t.shape[1])) for t in (self.tokens, other.tokens)]
        masks = [F.pad(m, (0, L - m.shape[1])) for m in (self.mask, other.mask)]
        return PromptEmbedding(torch.cat([self.pooled, other.pooled]), torch.cat(tokens), torch.cat(masks))


class MotionGenerator(nn.Module, PretrainedMixin):
    """Flow-matching velocity of the motion tensor (module docstring); the untrained network predicts v = 0."""

    config_class = MotionGeneratorConfig

    def __init__(self, config: MotionGeneratorConfig):
        super().__init__()
        self.config = config
        D = config.hidden_size
        patch = config.image_size // config.grid
        # photo (3) + depth features (2), one p×p patch per cell → D (DiT's patch embedding)
        self.image_embedder = nn.Sequential(nn.PixelUnshuffle(patch), nn.Conv2d(5 * patch * patch, D, 1))
        self.x_embedder = nn.Linear(config.channels, D)
        self.t_embedder = TimestepEmbedder(D)
        self.text_encoder = TextEncoder(config.text)
        self.text_embedder = Mlp(config.text.d_model, D, D)
        # the dropped caption's pooled embedding
        self.null_text = nn.Parameter(torch.zeros(config.text.d_model))  # device: built where the module is
        self.context_embedder = nn.Linear(config.text.d_model, D) if config.text_attention else None
        self.blocks = nn.ModuleList(
            VideoDiTBlock(D, config.num_heads, config.mlp_ratio, True, config.norm_eps,
                          cross_attention=config.text_attention)
            for _ in range(config.depth))
        self.final_layer = FinalLayer(D, 1, config.channels, config.norm_eps)
        self.initialize_weights()

    def initialize_weights(self) -> None:
        """DiT's initialisation: xavier linears, adaLN-Zero gates, zero cross-attention outputs (PixArt-α) and a zero
        final layer (each block starts as the identity and the network predicts v = 0)."""
        for module in (self.x_embedder, self.text_embedder, self.context_embedder, *self.blocks, self.final_layer):
            if module is None:  # no cross-attention
                continue
            for m in module.modules():
                if isinstance(m, nn.Linear):
                    nn.init.xavier_uniform_(m.weight)
                    nn.init.zeros_(m.bias)
        for block in self.blocks:
            nn.init.zeros_(block.adaLN_modulation[-1].weight)
            nn.init.zeros_(block.adaLN_modulation[-1].bias)
            if block.cross_attn is not None:
                nn.init.zeros_(block.cross_attn.proj.weight)
                nn.init.zeros_(block.cross_attn.proj.bias)
        for p in (*self.final_layer.adaLN_modulation[-1].parameters(), *self.final_layer.linear.parameters()):
            nn.init.zeros_(p)

    def encode_prompts(self, prompts: list[str]) -> PromptEmbedding:
        """The prompts' :class:`PromptEmbedding`: the text encoder's tokens averaged over each prompt's real tokens;
        ``""`` gives the learned null embedding and no tokens (the unconditional branch)."""
        pooled = self.null_text.expand(len(prompts), -1).clone()
        given = [i for i, p in enumerate(prompts) if p]
        if not given:
            return PromptEmbedding(pooled, *((pooled[:, None], pooled.new_zeros(len(prompts), 1, dtype=torch.bool))
                                             if self.config.text_attention else ()))
        tokens, mask = self.text_encoder.encode_text([prompts[i] for i in given])
        m = mask.to(tokens.dtype)[..., None]
        rows = torch.tensor(given, device=pooled.device)
        pooled[rows] = (tokens * m).sum(1) / m.sum(1).clamp_min(1)
        if not self.config.text_attention:
            return PromptEmbedding(pooled)
        all_tokens = tokens.new_zeros(len(prompts), *tokens.shape[1:])
        all_mask = mask.new_zeros(len(prompts), mask.shape[1])
        all_tokens[rows], all_mask[rows] = tokens, mask
        return PromptEmbedding(pooled, all_tokens, all_mask)

    def forward(
        self,
        x: Tensor,  # (B, 3K, g, g) noisy motion x_σ
        sigma: Tensor,  # (B,) noise level in [0, 1]
        image: Tensor,  # (B, 3, S, S) photograph in [−1, 1]
        depth: Tensor,  # (B, 2, S, S) depth_features
        text: PromptEmbedding,  # encode_prompts
    ) -> Tensor:
        """Velocity v = ε − x0 (B, 3K, g, g). Raises ValueError for inputs of the wrong shape (named)."""
        cfg = self.config
        B, g, S = x.shape[0], cfg.grid, cfg.image_size
        for name, t, shape in (("x", x, (B, cfg.channels, g, g)), ("image", image, (B, 3, S, S)),
                               ("depth", depth, (B, 2, S, S)), ("text.pooled", text.pooled, (B, cfg.text.d_model)),
                               ("sigma", sigma, (B,))):
            if tuple(t.shape) != shape:
                raise ValueError(f"MotionGenerator: {name} must have shape {shape}, got {tuple(t.shape)}")
        tokens = self.x_embedder(x.flatten(2).transpose(1, 2))  # (B, g², D)
        tokens = tokens + self.image_embedder(torch.cat([image, depth], 1)).flatten(2).transpose(1, 2)
        c = self.t_embedder(sigma) + self.text_embedder(text.pooled)  # (B, D)
        context = None if self.context_embedder is None else self.context_embedder(text.tokens)  # (B, L, D)
        rope = rope_3d(1, g, g, cfg.hidden_size // cfg.num_heads, dtype=x.dtype, device=x.device)
        for block in self.blocks:
            tokens = block(tokens, c, rope, context, None if context is None else text.mask)
        return self.final_layer(tokens, c).transpose(1, 2).reshape(B, cfg.channels, g, g)


def sample_motion(model: MotionGenerator, image: Tensor, depth: Tensor, prompts: list[str], *, steps: int = 16,
                  guidance: float = 3.0, generator: torch.Generator | None = None) -> Tensor:
    """(B, 3K, g, g) motion (units of ``motion_scale``) for the photographs ``image`` (B, 3, S, S) in [−1, 1] with
    ``depth`` (B, S, S) metres and ``prompts``: Euler steps of the flow from noise drawn on ``generator`` (CPU;
    moved), with classifier-free guidance v_u + w·(v_c − v_u) (``guidance`` w; 1: the conditional branch alone).
    Raises ValueError: ``len(prompts)`` differs from the batch."""
    if len(prompts) != image.shape[0]:
        raise ValueError(f"sample_motion: {len(prompts)} prompts for {image.shape[0]} photographs")
    cfg = model.config
    B = image.shape[0]
    feats = depth_features(depth)
    noise = torch.randn(B, cfg.channels, cfg.grid, cfg.grid, generator=generator, device="cpu").to(image)
    with torch.no_grad():
        cond = model.encode_prompts(prompts)
        both = cond.cat(model.encode_prompts([""] * B)) if guidance != 1 else cond

        def velocity(x: Tensor, sigma: Tensor) -> Tensor:
            n = len(both.pooled) // B
            s = sigma.to(x).expand(B * n)
            v = model(x.repeat(n, 1, 1, 1), s, image.repeat(n, 1, 1, 1), feats.repeat(n, 1, 1, 1), both)
            if n == 1:
                return v
            v_c, v_u = v.chunk(2)
            return v_u + guidance * (v_c - v_u)

        return sample(velocity, noise, steps)
