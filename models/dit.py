"""Camera-controlled video diffusion transformer (the video generator of Diff4Splat, Pan et al. 2025).

A DiT (Peebles & Xie 2023) over video latents predicting the flow-matching velocity v = ε − x0 (SD3 Eq. 1–3),
conditioned on σ (adaLN-Zero, DiT §3.2), the first-frame latent (concatenated on channels with a frame-0 mask, as
Wan 2.1 I2V), the camera path (packed Plücker rays through a zero-initialised projection added to the patch tokens,
CameraCtrl, He et al. 2024) and text (cross-attention, PixArt-α). Self-attention uses 3D RoPE and QK-norm. Two
runtime switches, never saved: ``gradient_checkpointing`` (recompute each block in the backward pass, Chen et al.
2016) and ``ff_chunk_tokens`` (each block's MLP over at most n tokens at a time, as diffusers'
``enable_forward_chunking``); neither changes the values."""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn
from torch.utils.checkpoint import checkpoint

from diff4splat.utils.checks import check_ranges, ranged
from models.backbone import check_velocity_inputs
from models.layers import (
    CrossAttention,
    Mlp,
    SelfAttention,
    TimestepEmbedder,
    modulated_layer_norm,
    patchify,
    unpatchify,
)
from models.pretrained import PretrainedMixin
from models.rope import rope_3d, rope_split
from models.tracing import tracing

__all__ = ["VideoDiTConfig", "VideoDiTBlock", "FinalLayer", "VideoDiT", "check_dit_inputs"]

SIGMA_SCALE = 1000.0  # σ ∈ [0, 1] is embedded as σ·1000, the DiT/DDPM timestep range.


@dataclass
class VideoDiTConfig:
    """Sizes of :class:`VideoDiT`; defaults are the CPU test size.

    Attributes:
        latent_channels: c, channels of the video VAE latent.
        hidden_size: token width D.
        depth: number of transformer blocks.
        num_heads: attention heads; head_dim = hidden_size / num_heads must be even and ≥ 6 (3D RoPE).
        mlp_ratio: feed-forward width / hidden_size.
        patch_size: (pt, ph, pw) latent voxels per token.
        text_dim: width of the text-encoder tokens.
        camera_channels: channels of the packed Plücker tensor (6·4·8·8 for a 4×8×8 VAE).
        frequency_embedding_size: width of the sinusoidal σ features.
        rope_theta: RoPE base wavelength (> 1).
        qk_norm: RMSNorm queries and keys per head.
        norm_eps: epsilon of every LayerNorm / RMSNorm.

    Raises:
        ValueError: a field out of range.
    """

    latent_channels: int = ranged(16)
    hidden_size: int = ranged(32)
    depth: int = ranged(2)
    num_heads: int = ranged(2)
    mlp_ratio: float = 4.0
    patch_size: tuple[int, int, int] = (1, 2, 2)
    text_dim: int = ranged(32)
    camera_channels: int = ranged(1536)
    frequency_embedding_size: int = ranged(256)
    rope_theta: float = 10000.0
    qk_norm: bool = True
    norm_eps: float = 1e-6

    def __post_init__(self):
        self.patch_size = tuple(int(p) for p in self.patch_size)
        check_ranges("VideoDiTConfig", self)
        if len(self.patch_size) != 3 or min(self.patch_size) < 1:
            raise ValueError(f"VideoDiTConfig.patch_size must be 3 positive ints, got {self.patch_size!r}")
        if self.hidden_size % self.num_heads:
            raise ValueError(f"VideoDiTConfig.hidden_size {self.hidden_size} must be divisible by "
                             f"num_heads {self.num_heads}")
        rope_split(self.hidden_size // self.num_heads)  # raises ValueError for an unusable head_dim
        if not self.mlp_ratio > 0:
            raise ValueError(f"VideoDiTConfig.mlp_ratio must be > 0, got {self.mlp_ratio}")
        if not self.rope_theta > 1:
            raise ValueError(f"VideoDiTConfig.rope_theta must be > 1, got {self.rope_theta}")

    @property
    def head_dim(self) -> int:
        return self.hidden_size // self.num_heads

    @classmethod
    def paper(cls) -> VideoDiTConfig:
        """Paper size (docs/DESIGN.md): 32 blocks, hidden 4096, 32 heads, 16 latent channels, patch 1×2×2, T5-XXL
        text."""
        return cls(latent_channels=16, hidden_size=4096, depth=32, num_heads=32, mlp_ratio=4.0,
                   patch_size=(1, 2, 2), text_dim=4096, camera_channels=1536)


class VideoDiTBlock(nn.Module):
    """Transformer block: x += g₁·SelfAttn(modulate(LN(x), β₁, γ₁)) (3D RoPE); x += CrossAttn(LN'(x), text)
    (skipped without text); x += g₂·MLP(modulate(LN(x), β₂, γ₂)); (β, γ, g) = Linear(SiLU(c)) of the σ embedding.
    ``cross_attention`` False builds no text branch (a block conditioned through ``c`` alone, DiT's adaLN-Zero)."""

    def __init__(self, hidden_size: int, num_heads: int, mlp_ratio: float, qk_norm: bool, eps: float,
                 cross_attention: bool = True):
        super().__init__()
        self.norm1 = nn.LayerNorm(hidden_size, elementwise_affine=False, eps=eps)
        self.attn = SelfAttention(hidden_size, num_heads, qk_norm=qk_norm, eps=eps)
        self.norm2 = nn.LayerNorm(hidden_size, elementwise_affine=True, eps=eps) if cross_attention else None
        self.cross_attn = (CrossAttention(hidden_size, hidden_size, num_heads, qk_norm=qk_norm, eps=eps)
                           if cross_attention else None)
        self.norm3 = nn.LayerNorm(hidden_size, elementwise_affine=False, eps=eps)
        self.mlp = Mlp(hidden_size, int(hidden_size * mlp_ratio))
        self.adaLN_modulation = nn.Sequential(nn.SiLU(), nn.Linear(hidden_size, 6 * hidden_size))

    def forward(
        self,
        x: Tensor,  # (B, N, D) video tokens
        c: Tensor,  # (B, D) σ embedding
        rope: tuple[Tensor, Tensor],  # cos, sin: (N, head_dim/2)
        context: Tensor | None = None,  # (B, L, D) projected text tokens
        context_mask: Tensor | None = None,  # (B, L) bool, True = real token
        ff_chunk_tokens: int | None = None,  # the MLP over at most this many tokens at a time (None: all)
    ) -> Tensor:
        """One block on the video tokens.

        Args:
            x: (B, N, D) video tokens, frame-major.
            c: (B, D) σ embedding.
            rope: (cos, sin), each (N, head_dim/2), from :func:`models.rope.rope_3d`.
            context: (B, L, D) projected text tokens, or None (required None without a text branch).
            context_mask: (B, L) bool, True = real token, or None.
            ff_chunk_tokens: the MLP over at most this many tokens at a time; None: all at once.

        Returns (B, N, D). ValueError from :meth:`CrossAttention.forward` for a bad mask.
        """
        shift_msa, scale_msa, gate_msa, shift_mlp, scale_mlp, gate_mlp = self.adaLN_modulation(c).chunk(6, dim=1)
        # Gated residuals as one addcmul each (one pass over the tokens, rounded once).
        x = torch.addcmul(x, gate_msa.unsqueeze(1),
                          self.attn(modulated_layer_norm(x, shift_msa, scale_msa, self.norm1.eps), rope))
        if context is not None:  # a None check on an argument, not on tensor values: exportable
            x = x + self.cross_attn(self.norm2(x), context, context_mask)
        h = modulated_layer_norm(x, shift_mlp, scale_mlp, self.norm3.eps)
        gate = gate_mlp.unsqueeze(1)
        if ff_chunk_tokens is None or h.shape[1] <= ff_chunk_tokens:
            return torch.addcmul(x, gate, self.mlp(h))
        parts = zip(x.split(ff_chunk_tokens, dim=1), h.split(ff_chunk_tokens, dim=1), strict=True)
        if tracing() or (torch.is_grad_enabled() and any(t.requires_grad for t in (x, h, gate))):
            return torch.cat([torch.addcmul(xp, gate, self.mlp(hp)) for xp, hp in parts], dim=1)
        # No autograd: add each chunk's residual into x in place (x is this block's own sum, not the caller's input).
        for xp, hp in parts:
            xp.addcmul_(gate, self.mlp(hp))
        return x


class FinalLayer(nn.Module):
    """adaLN (shift, scale from c) + Linear to one patch of output channels (DiT §3.2)."""

    def __init__(self, hidden_size: int, patch_volume: int, out_channels: int, eps: float):
        super().__init__()
        self.norm_final = nn.LayerNorm(hidden_size, elementwise_affine=False, eps=eps)
        self.linear = nn.Linear(hidden_size, patch_volume * out_channels)
        self.adaLN_modulation = nn.Sequential(nn.SiLU(), nn.Linear(hidden_size, 2 * hidden_size))

    def forward(self, x: Tensor, c: Tensor) -> Tensor:
        """x (B, N, D), c (B, D) → (B, N, pt·ph·pw·out_channels)."""
        shift, scale = self.adaLN_modulation(c).chunk(2, dim=1)
        return self.linear(modulated_layer_norm(x, shift, scale, self.norm_final.eps))


def check_dit_inputs(config: VideoDiTConfig, x: Tensor, sigma: Tensor, image_latent: Tensor, plucker: Tensor | None,
                     text: Tensor | None, text_mask: Tensor | None) -> None:
    """The checks of :meth:`VideoDiT.forward` (shapes static under tracing, the σ range eager only); the ONNX runtime
    makes them too. ValueError as :meth:`VideoDiT.forward`."""
    cfg = config
    check_velocity_inputs(x, sigma, image_latent, plucker, cfg.latent_channels, cfg.camera_channels, cfg.patch_size)
    B = x.shape[0]
    if text is None:
        if text_mask is not None:
            raise ValueError("text_mask was given without text")
    else:
        if text.dim() != 3 or text.shape[0] != B or text.shape[2] != cfg.text_dim or text.shape[1] < 1:
            raise ValueError(f"text must have shape ({B}, L >= 1, {cfg.text_dim}), got {tuple(text.shape)}")
        if text_mask is not None and (text_mask.shape != text.shape[:2] or text_mask.dtype != torch.bool):
            raise ValueError(f"text_mask must be a bool tensor of shape {tuple(text.shape[:2])}, "
                             f"got {text_mask.dtype} {tuple(text_mask.shape)}")
    if not tracing() and bool((~((sigma >= 0) & (sigma <= 1))).any()):
        raise ValueError(f"sigma must lie in [0, 1] (no NaN), got {sigma.tolist()}")


class VideoDiT(nn.Module, PretrainedMixin):
    """Camera- and text-conditioned image-to-video flow-matching DiT (Diff4Splat's generator).

    Attributes:
        gradient_checkpointing: recompute each block in the backward pass (training with gradients only); False
            after construction and loading.
        ff_chunk_tokens: MLP chunk size in tokens, or None; None after construction and loading.
    """

    config_class = VideoDiTConfig

    def __init__(self, config: VideoDiTConfig):
        super().__init__()
        self.config = config
        D, c = config.hidden_size, config.latent_channels
        patch_volume = config.patch_size[0] * config.patch_size[1] * config.patch_size[2]
        # Input tokens: [noisy latent (c), first-frame latent at frame 0 (c), frame-0 mask (1)] per patch.
        self.x_embedder = nn.Linear((2 * c + 1) * patch_volume, D)
        self.camera_embedder = nn.Linear(config.camera_channels * patch_volume, D)
        self.t_embedder = TimestepEmbedder(D, config.frequency_embedding_size)
        self.text_embedder = Mlp(config.text_dim, D, D)  # PixArt-α caption projection
        self.blocks = nn.ModuleList(
            VideoDiTBlock(D, config.num_heads, config.mlp_ratio, config.qk_norm, config.norm_eps)
            for _ in range(config.depth))
        self.final_layer = FinalLayer(D, patch_volume, c, config.norm_eps)
        self.gradient_checkpointing = False
        self.ff_chunk_tokens: int | None = None
        self.initialize_weights()

    def initialize_weights(self) -> None:
        """DiT initialisation (DiT ``initialize_weights``) plus zero-inits for the new branches."""
        def _basic_init(module):
            if isinstance(module, nn.Linear):
                nn.init.xavier_uniform_(module.weight)
                nn.init.zeros_(module.bias)

        self.apply(_basic_init)
        nn.init.normal_(self.t_embedder.mlp[0].weight, std=0.02)
        nn.init.normal_(self.t_embedder.mlp[2].weight, std=0.02)
        for block in self.blocks:
            # adaLN-Zero (DiT §3.2): gates start at 0, so each block starts as the identity.
            nn.init.zeros_(block.adaLN_modulation[-1].weight)
            nn.init.zeros_(block.adaLN_modulation[-1].bias)
            # Zero cross-attention output projection (PixArt-α): the ungated branch starts off too.
            nn.init.zeros_(block.cross_attn.proj.weight)
            nn.init.zeros_(block.cross_attn.proj.bias)
        # Zero final layer (DiT): the untrained network predicts v = 0 everywhere.
        nn.init.zeros_(self.final_layer.adaLN_modulation[-1].weight)
        nn.init.zeros_(self.final_layer.adaLN_modulation[-1].bias)
        nn.init.zeros_(self.final_layer.linear.weight)
        nn.init.zeros_(self.final_layer.linear.bias)
        # Zero camera projection (ControlNet zero-conv, CameraCtrl): an untrained camera branch changes nothing.
        nn.init.zeros_(self.camera_embedder.weight)
        nn.init.zeros_(self.camera_embedder.bias)

    def forward(
        self,
        x: Tensor,  # (B, c, n, h, w) noisy latents x_σ
        sigma: Tensor,  # (B,) noise level in [0, 1]
        image_latent: Tensor,  # (B, c, 1, h, w) first-frame VAE latent
        plucker: Tensor | None = None,  # (B, camera_channels, n, h, w) packed Plücker rays
        text: Tensor | None = None,  # (B, L, text_dim) text-encoder tokens
        text_mask: Tensor | None = None,  # (B, L) bool, True = real token
    ) -> Tensor:
        """Predict the flow-matching velocity v = ε − x0 (σ = 1 is pure noise).

        Args:
            x: (B, c, n, h, w) noisy latent; n, h, w divisible by patch_size.
            sigma: (B,) σ ∈ [0, 1] (checked in eager mode only).
            image_latent: (B, c, 1, h, w) clean first-frame latent.
            plucker: (B, camera_channels, n, h, w) from ``diff4splat.cameras.pack_plucker``, or None (no camera tokens,
                as an untrained camera branch).
            text: (B, L, text_dim) text tokens, or None (no cross-attention).
            text_mask: (B, L) bool, True = real token, or None (all real).

        Returns:
            (B, c, n, h, w) velocity in the parameters' dtype.

        Raises:
            ValueError: an argument of the wrong shape or dtype (named), σ outside [0, 1], or ``text_mask`` without
                ``text``.
        """
        check_dit_inputs(self.config, x, sigma, image_latent, plucker, text, text_mask)
        cfg = self.config
        B, c, n, h, w = x.shape
        pt, ph, pw = cfg.patch_size
        grid = (n // pt, h // ph, w // pw)

        first = (torch.arange(n, device=x.device) == 0).to(x.dtype).view(1, 1, n, 1, 1)  # (1, 1, n, 1, 1)
        cond = image_latent.to(x.dtype) * first  # first-frame latent at frame 0, zeros after
        inputs = torch.cat([x, cond, first.expand(B, 1, n, h, w)], dim=1)  # (B, 2c + 1, n, h, w)
        tokens = self.x_embedder(patchify(inputs, cfg.patch_size))  # (B, N, D)
        if plucker is not None:
            tokens = tokens + self.camera_embedder(patchify(plucker.to(x.dtype), cfg.patch_size))

        emb = self.t_embedder(sigma * SIGMA_SCALE)  # (B, D)
        rope = rope_3d(*grid, cfg.head_dim, cfg.rope_theta, dtype=tokens.dtype, device=x.device)
        context = self.text_embedder(text.to(tokens.dtype)) if text is not None else None
        recompute = self.gradient_checkpointing and self.training and torch.is_grad_enabled()
        for block in self.blocks:
            if recompute:  # activations of the block are recomputed in the backward pass (memory for compute)
                tokens = checkpoint(block, tokens, emb, rope, context, text_mask, self.ff_chunk_tokens,
                                    use_reentrant=False)
            else:
                tokens = block(tokens, emb, rope, context, text_mask, self.ff_chunk_tokens)
        out = self.final_layer(tokens, emb)  # (B, N, pt·ph·pw·c)
        return unpatchify(out, cfg.patch_size, grid, c)
