"""Building blocks shared by the transformer networks (DiT ``models.py`` style): sinusoidal timestep embedding,
MLP, adaLN ``modulate``, video patchify/unpatchify, and multi-head self-/cross-attention with QK-norm, 3D RoPE and
key padding masks. ONNX-exportable: no complex dtypes, no Python control flow on tensor values."""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from models.rope import apply_rope
from models.tracing import tracing

__all__ = ["timestep_embedding", "TimestepEmbedder", "Mlp", "modulate", "modulated_layer_norm", "patchify",
           "unpatchify", "QKNorm", "SelfAttention", "CrossAttention"]


def timestep_embedding(t: Tensor, dim: int, max_period: float = 10000.0) -> Tensor:
    """Sinusoidal embedding of scalar times (DiT; Vaswani et al. 2017 §3.5): [cos(t·ω_i)…, sin(t·ω_i)…],
    k = ⌊dim/2⌋, ω_i = max_period^(−i/k), a zero column appended for odd ``dim``.

    Args:
        t: (B,) real times (flow models pass σ·1000).
        dim: embedding width ≥ 2.
        max_period: longest wavelength, in units of t.

    Returns (B, dim) float32 in [−1, 1].

    Raises:
        ValueError: ``t`` is not 1-D or ``dim`` < 2.
    """
    if t.dim() != 1:
        raise ValueError(f"t must have shape (B,), got {tuple(t.shape)}")
    if dim < 2:
        raise ValueError(f"dim must be >= 2, got {dim}")
    half = dim // 2
    freqs = torch.exp(-math.log(max_period) * torch.arange(half, dtype=torch.float32, device=t.device) / half)
    args = t.float()[:, None] * freqs[None]
    emb = torch.cat([torch.cos(args), torch.sin(args)], dim=-1)
    if dim % 2:
        emb = torch.cat([emb, torch.zeros_like(emb[:, :1])], dim=-1)
    return emb


class TimestepEmbedder(nn.Module):
    """Scalar time → vector: sinusoidal features then Linear–SiLU–Linear (DiT §3.2)."""

    def __init__(self, hidden_size: int, frequency_embedding_size: int = 256):
        super().__init__()
        self.frequency_embedding_size = frequency_embedding_size
        self.mlp = nn.Sequential(
            nn.Linear(frequency_embedding_size, hidden_size),
            nn.SiLU(),
            nn.Linear(hidden_size, hidden_size),
        )

    def forward(self, t: Tensor) -> Tensor:
        emb = timestep_embedding(t, self.frequency_embedding_size)
        return self.mlp(emb.to(self.mlp[0].weight.dtype))


class Mlp(nn.Module):
    """Linear → GELU(tanh) → Linear, the transformer feed-forward (DiT / ViT): (..., in) → (..., out).
    On CUDA without autograd, autocast or tracing, the first GEMM applies the GELU in its epilogue
    (``torch._addmm_activation``), writing the hidden activations once; the CPU's epilogue is the erf form, so the CPU
    takes the plain path."""

    def __init__(self, in_features: int, hidden_features: int, out_features: int | None = None):
        super().__init__()
        self.fc1 = nn.Linear(in_features, hidden_features)
        self.act = nn.GELU(approximate="tanh")
        self.fc2 = nn.Linear(hidden_features, out_features or in_features)

    def forward(self, x: Tensor) -> Tensor:
        w = self.fc1.weight
        if x.is_cuda and x.dtype == w.dtype and x.dim() >= 2 and not torch.is_autocast_enabled("cuda") \
                and not (torch.is_grad_enabled() and (x.requires_grad or w.requires_grad)) and not tracing():
            h = torch._addmm_activation(self.fc1.bias, x.reshape(-1, x.shape[-1]), w.t(), use_gelu=True)
            return self.fc2(h.unflatten(0, x.shape[:-1]))
        return self.fc2(self.act(self.fc1(x)))


def modulate(x: Tensor, shift: Tensor, scale: Tensor) -> Tensor:
    """Adaptive LayerNorm affine x·(1 + scale) + shift (DiT §3.2): x (B, N, D), shift, scale (B, D) → (B, N, D)."""
    return x * (1 + scale.unsqueeze(1)) + shift.unsqueeze(1)


def modulated_layer_norm(x: Tensor, shift: Tensor, scale: Tensor, eps: float) -> Tensor:
    """``modulate(LayerNorm(x), shift, scale)`` (LayerNorm without affine) in fewer passes over ``x``: for B = 1
    the affine is LayerNorm's own weight and bias (one kernel); otherwise LayerNorm then one ``addcmul``. Same values
    as :func:`modulate` up to intermediate rounding.

    Args:
        x: (B, N, D) tokens.
        shift, scale: (B, D).
        eps: LayerNorm's epsilon.

    Returns (B, N, D) in ``x``'s dtype promoted with ``scale``'s.
    """
    if x.shape[0] == 1 and not tracing():
        dtype = torch.promote_types(x.dtype, scale.dtype)
        return F.layer_norm(x.to(dtype), x.shape[-1:], (1 + scale[0]).to(dtype), shift[0].to(dtype), eps)
    return torch.addcmul(shift.unsqueeze(1), F.layer_norm(x, x.shape[-1:], eps=eps), 1 + scale.unsqueeze(1))


def patchify(x: Tensor, patch: tuple[int, int, int]) -> Tensor:
    """Cut a video (B, C, T, H, W) into non-overlapping (pt, ph, pw) patches, one token each (ViT / DiT):
    → (B, T/pt · H/ph · W/pw, C·pt·ph·pw), tokens frame-major, channels ordered (C, pt, ph, pw) so a Linear equals
    ``Conv3d(kernel_size=patch, stride=patch)``.

    Raises:
        ValueError: ``x`` is not 5-D or a size is not divisible by its patch size.
    """
    if x.dim() != 5:
        raise ValueError(f"x must have shape (B, C, T, H, W), got {tuple(x.shape)}")
    B, C, T, H, W = x.shape
    pt, ph, pw = patch
    if T % pt or H % ph or W % pw:
        raise ValueError(f"x of shape {tuple(x.shape)}: (T, H, W) must be divisible by patch {tuple(patch)}")
    x = x.reshape(B, C, T // pt, pt, H // ph, ph, W // pw, pw)
    x = x.permute(0, 2, 4, 6, 1, 3, 5, 7)  # (B, n, h, w, C, pt, ph, pw)
    return x.reshape(B, (T // pt) * (H // ph) * (W // pw), C * pt * ph * pw)


def unpatchify(tokens: Tensor, patch: tuple[int, int, int], grid: tuple[int, int, int], channels: int) -> Tensor:
    """Inverse of :func:`patchify`: tokens (B, n·h·w, C·pt·ph·pw) on the ``grid`` (n, h, w) → (B, C, n·pt, h·ph, w·pw).

    Raises:
        ValueError: ``tokens`` does not have that shape.
    """
    pt, ph, pw = patch
    n, h, w = grid
    B = tokens.shape[0]
    if tokens.shape != (B, n * h * w, channels * pt * ph * pw):
        raise ValueError(f"tokens must have shape ({B}, {n * h * w}, {channels * pt * ph * pw}), "
                         f"got {tuple(tokens.shape)}")
    x = tokens.reshape(B, n, h, w, channels, pt, ph, pw)
    x = x.permute(0, 4, 1, 5, 2, 6, 3, 7)  # (B, C, n, pt, h, ph, w, pw)
    return x.reshape(B, channels, n * pt, h * ph, w * pw)


class QKNorm(nn.RMSNorm):
    """RMSNorm over one head's channels (QK-norm) with the weight cast to the input's dtype, so bf16 inputs keep
    torch's fused kernel; equal to :class:`torch.nn.RMSNorm` when dtypes agree. (..., head_dim) → same."""

    def forward(self, x: Tensor) -> Tensor:
        return F.rms_norm(x, self.normalized_shape, self.weight.to(x.dtype), self.eps)


class _MultiHead(nn.Module):
    """Head split and per-head QK-norm of the attention modules; no random parameters (the subclasses' projections
    draw from the RNG as if built alone). ValueError: ``dim`` not divisible by ``num_heads``."""

    def __init__(self, dim: int, num_heads: int, qk_norm: bool, eps: float):
        super().__init__()
        if dim % num_heads:
            raise ValueError(f"dim {dim} must be divisible by num_heads {num_heads}")
        self.num_heads = num_heads
        self.head_dim = dim // num_heads
        self.q_norm = QKNorm(self.head_dim, eps=eps) if qk_norm else nn.Identity()
        self.k_norm = QKNorm(self.head_dim, eps=eps) if qk_norm else nn.Identity()


class SelfAttention(_MultiHead):
    """Multi-head self-attention with optional QK-norm (RMSNorm of each head's queries and keys, Dehghani et al. 2023;
    SD3) and RoPE after the norm (Wan / SD3)."""

    def __init__(self, dim: int, num_heads: int, qk_norm: bool = True, eps: float = 1e-6):
        super().__init__(dim, num_heads, qk_norm, eps)
        self.qkv = nn.Linear(dim, 3 * dim)
        self.proj = nn.Linear(dim, dim)

    def forward(
        self,
        x: Tensor,  # (B, N, D)
        rope: tuple[Tensor, Tensor] | None = None,  # cos, sin: (N, head_dim/2) each
    ) -> Tensor:
        """(B, N, D) → (B, N, D), every token attending to every token."""
        B, N, D = x.shape
        weights = self.qkv.weight.chunk(3)  # views of the fused (3D, D) projection: q, k, v rows
        biases = self.qkv.bias.chunk(3)

        def project(i: int, norm: nn.Module | None = None) -> Tensor:  # (B, N, heads, head_dim)
            t = F.linear(x, weights[i], biases[i]).unflatten(-1, (self.num_heads, self.head_dim))
            if norm is None:
                return t
            t = norm(t)
            return t if rope is None else apply_rope(t, *rope, token_dim=-3)

        # One projection at a time: the (B, N, 3D) output of the fused matrix never exists.
        q, k, v = project(0, self.q_norm), project(1, self.k_norm), project(2)
        return self.proj(_attend(q, k, v).reshape(B, N, D))


def _attend(q: Tensor, k: Tensor, v: Tensor, keep: Tensor | None = None) -> Tensor:
    """Scaled dot-product attention on heads-inner tensors: q (B, N, heads, d), k, v (B, L, heads, d), keep (B, L) bool
    or None → (B, N, heads, d); passed to the kernel as transposed views, so no copies."""
    mask = None if keep is None else keep[:, None, None, :]
    return F.scaled_dot_product_attention(q.transpose(1, 2), k.transpose(1, 2), v.transpose(1, 2),
                                          attn_mask=mask).transpose(1, 2)


class CrossAttention(_MultiHead):
    """Multi-head cross-attention from ``x`` to a ``context`` sequence (e.g. text, PixArt-α) with a key padding mask;
    QK-norm as :class:`SelfAttention`, no rotation."""

    def __init__(self, dim: int, context_dim: int, num_heads: int, qk_norm: bool = True, eps: float = 1e-6):
        super().__init__(dim, num_heads, qk_norm, eps)
        self.q = nn.Linear(dim, dim)
        self.kv = nn.Linear(context_dim, 2 * dim)
        self.proj = nn.Linear(dim, dim)

    def forward(
        self,
        x: Tensor,  # (B, N, D)
        context: Tensor,  # (B, L, context_dim)
        context_mask: Tensor | None = None,  # (B, L) bool, True = real token
    ) -> Tensor:
        """``x`` (B, N, D) attends to ``context`` (B, L, context_dim) → (B, N, D). Masked tokens get zero weight; a
        sample with an all-False mask gives exactly zero (tensor ops only, so it traces).

        Raises:
            ValueError: ``context_mask`` given but not a bool tensor of shape (B, L).
        """
        B, N, D = x.shape
        L = context.shape[1]
        if context_mask is not None and (context_mask.shape != (B, L) or context_mask.dtype != torch.bool):
            raise ValueError(f"context_mask must be a bool tensor of shape ({B}, {L}), "
                             f"got {context_mask.dtype} {tuple(context_mask.shape)}")
        q = self.q(x).unflatten(-1, (self.num_heads, self.head_dim))  # (B, N, heads, head_dim)
        k, v = self.kv(context).unflatten(-1, (2, self.num_heads, self.head_dim)).unbind(2)  # (B, L, heads, hd)
        q, k = self.q_norm(q), self.k_norm(k)
        if context_mask is None:
            return self.proj(_attend(q, k, v).reshape(B, N, D))
        has_keys = context_mask.any(dim=1)  # (B,)
        keep = context_mask | ~has_keys[:, None]  # empty rows attend to all keys, then get zeroed
        out = self.proj(_attend(q, k, v, keep).reshape(B, N, D))
        return out * has_keys.to(out.dtype)[:, None, None]
