"""Small building blocks shared by the transformer networks (DiT ``models.py`` style).

Generic pieces, free of any one network's config: sinusoidal timestep embedding, MLP, adaLN
``modulate``, video patchify/unpatchify, and multi-head self-/cross-attention with QK-norm, 3D RoPE
and key padding masks. Everything is ONNX-exportable: no complex dtypes and no Python control flow
on tensor values.
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from models.rope import apply_rope
from models.tracing import tracing

__all__ = [
    "timestep_embedding",
    "TimestepEmbedder",
    "Mlp",
    "modulate",
    "modulated_layer_norm",
    "patchify",
    "unpatchify",
    "QKNorm",
    "SelfAttention",
    "CrossAttention",
]


def timestep_embedding(t: Tensor, dim: int, max_period: float = 10000.0) -> Tensor:
    """Sinusoidal embedding of scalar times (DiT ``TimestepEmbedder``; Vaswani et al. 2017 §3.5).

    emb = [cos(t·ω_0), …, cos(t·ω_{k−1}), sin(t·ω_0), …, sin(t·ω_{k−1})], k = ⌊dim/2⌋,
    ω_i = max_period^(−i/k); a zero column is appended when ``dim`` is odd.

    Args:
        t: (B,) real times, any range (DiT uses integer steps 0…1000; flow models pass σ·1000).
        dim: embedding width ≥ 2.
        max_period: longest wavelength, in units of t.

    Returns:
        (B, dim) float32 in [−1, 1].

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
        """t: (B,) → (B, hidden_size)."""
        emb = timestep_embedding(t, self.frequency_embedding_size)
        return self.mlp(emb.to(self.mlp[0].weight.dtype))


class Mlp(nn.Module):
    """Linear → GELU(tanh) → Linear, the transformer feed-forward (DiT / ViT).

    On CUDA, where autograd records nothing and no autocast runs, the first Linear's GEMM applies the GELU in its
    epilogue (``torch._addmm_activation``: cuBLASLt's GELU epilogue, the tanh form; ATen's CUDA fallback runs
    ``gelu_(…, "tanh")``), so the (…, hidden) activations are written once instead of written, read and written
    again (at the paper size 0.87 GB a block, 28 GB a sampling step; benchmarks/dit_traffic.py). The CPU's
    ``_addmm_activation`` applies the erf form, so the CPU, autograd, autocast and tracing take the plain path.
    """

    def __init__(self, in_features: int, hidden_features: int, out_features: int | None = None):
        super().__init__()
        self.fc1 = nn.Linear(in_features, hidden_features)
        self.act = nn.GELU(approximate="tanh")
        self.fc2 = nn.Linear(hidden_features, out_features or in_features)

    def forward(self, x: Tensor) -> Tensor:
        """x: (..., in_features) → (..., out_features)."""
        w = self.fc1.weight
        if x.is_cuda and x.dtype == w.dtype and x.dim() >= 2 and not torch.is_autocast_enabled("cuda") \
                and not (torch.is_grad_enabled() and (x.requires_grad or w.requires_grad)) and not tracing():
            h = torch._addmm_activation(self.fc1.bias, x.reshape(-1, x.shape[-1]), w.t(), use_gelu=True)
            return self.fc2(h.unflatten(0, x.shape[:-1]))
        return self.fc2(self.act(self.fc1(x)))


def modulate(x: Tensor, shift: Tensor, scale: Tensor) -> Tensor:
    """Adaptive LayerNorm affine: x·(1 + scale) + shift, per sample (DiT §3.2, adaLN).

    Args:
        x: (B, N, D) normalised tokens.
        shift, scale: (B, D) regressed from the conditioning vector.

    Returns:
        (B, N, D).
    """
    return x * (1 + scale.unsqueeze(1)) + shift.unsqueeze(1)


def modulated_layer_norm(x: Tensor, shift: Tensor, scale: Tensor, eps: float) -> Tensor:
    """``modulate(LayerNorm(x), shift, scale)`` (LayerNorm without its own affine; DiT §3.2 adaLN) in fewer passes
    over ``x``.

    One sample (B = 1, as sampling runs): the per-sample affine is LayerNorm's own weight 1 + scale and bias shift,
    one kernel that reads ``x`` once and rounds once; the normalise-multiply-add chain read and wrote the tokens three
    times (at the paper size, 13,312 × 4,096 bfloat16 tokens: 0.65 GB against 0.22 GB per call, twice a block).
    Several samples, or while tracing: LayerNorm, then one ``addcmul``. Same values as :func:`modulate` up to
    the rounding of the intermediate (exactly in float64).

    Args:
        x: (B, N, D) tokens.
        shift, scale: (B, D) regressed from the conditioning vector.
        eps: LayerNorm's epsilon.

    Returns:
        (B, N, D), dtype of ``x`` promoted with ``scale``'s (as :func:`modulate`; float32 under autocast, which
        runs LayerNorm in float32). Raises nothing of its own (LayerNorm's errors for mismatched sizes).
    """
    if x.shape[0] == 1 and not tracing():
        dtype = torch.promote_types(x.dtype, scale.dtype)
        return F.layer_norm(x.to(dtype), x.shape[-1:], (1 + scale[0]).to(dtype), shift[0].to(dtype), eps)
    return torch.addcmul(shift.unsqueeze(1), F.layer_norm(x, x.shape[-1:], eps=eps), 1 + scale.unsqueeze(1))


def patchify(x: Tensor, patch: tuple[int, int, int]) -> Tensor:
    """Cut a video into non-overlapping pt×ph×pw patches, one token each (ViT / DiT patchify).

    Token order is frame-major ((f·h' + y)·w' + x); the channels of a token are ordered
    (C, pt, ph, pw), i.e. the flattening of a ``Conv3d`` weight, so ``Linear`` on these tokens
    equals ``Conv3d(kernel_size=patch, stride=patch)``.

    Args:
        x: (B, C, T, H, W), T, H, W divisible by ``patch``.
        patch: (pt, ph, pw).

    Returns:
        (B, T/pt · H/ph · W/pw, C·pt·ph·pw).

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
    """Inverse of :func:`patchify`.

    Args:
        tokens: (B, n·h·w, channels·pt·ph·pw).
        patch: (pt, ph, pw).
        grid: (n, h, w) token grid.
        channels: C.

    Returns:
        (B, C, n·pt, h·ph, w·pw).

    Raises:
        ValueError: ``tokens`` does not have the stated shape.
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
    """RMSNorm over one head's channels (QK-norm) computed in the input's dtype: under bf16 autocast the queries
    and keys arrive in bfloat16, and a float32 weight keeps torch from its fused kernel (it warns "Mismatch dtype
    between input and weight" and falls back to the unfused composite); the weight (ones at init) is cast to
    the input's dtype instead. Identical to :class:`torch.nn.RMSNorm` when the dtypes already agree.

    x: (..., head_dim) → (..., head_dim), same dtype.
    """

    def forward(self, x: Tensor) -> Tensor:
        """x: (..., head_dim) → (..., head_dim), RMS-normalised and scaled by the weight, in x's dtype."""
        return F.rms_norm(x, self.normalized_shape, self.weight.to(x.dtype), self.eps)


class _MultiHead(nn.Module):
    """Head split and per-head QK-norm shared by :class:`SelfAttention` and :class:`CrossAttention`.

    Holds no random parameters (RMSNorm weights start at 1), so the subclasses' projections are initialised
    from the RNG in the same order as if they were built alone.

    Raises:
        ValueError: ``dim`` not divisible by ``num_heads``.
    """

    def __init__(self, dim: int, num_heads: int, qk_norm: bool, eps: float):
        super().__init__()
        if dim % num_heads:
            raise ValueError(f"dim {dim} must be divisible by num_heads {num_heads}")
        self.num_heads = num_heads
        self.head_dim = dim // num_heads
        self.q_norm = QKNorm(self.head_dim, eps=eps) if qk_norm else nn.Identity()
        self.k_norm = QKNorm(self.head_dim, eps=eps) if qk_norm else nn.Identity()


class SelfAttention(_MultiHead):
    """Multi-head self-attention with optional QK-norm and rotary positions.

    QK-norm: RMSNorm over each head's query and key channels before the dot product, which
    bounds attention logits and stabilises large-scale training (Dehghani et al. 2023, ViT-22B;
    Esser et al. 2024, SD3). RoPE (if given) is applied after the norm, as in Wan / SD3.
    """

    def __init__(self, dim: int, num_heads: int, qk_norm: bool = True, eps: float = 1e-6):
        super().__init__(dim, num_heads, qk_norm, eps)
        self.qkv = nn.Linear(dim, 3 * dim)
        self.proj = nn.Linear(dim, dim)

    def forward(
        self,
        x: Tensor,  # (B, N, D)
        rope: tuple[Tensor, Tensor] | None = None,  # cos, sin: (N, head_dim/2) each
    ) -> Tensor:
        """Attend every token to every token; returns (B, N, D)."""
        B, N, D = x.shape
        weights = self.qkv.weight.chunk(3)  # views of the fused (3D, D) projection: q, k, v rows
        biases = self.qkv.bias.chunk(3)

        def project(i: int, norm: nn.Module | None = None) -> Tensor:  # (B, N, heads, head_dim)
            t = F.linear(x, weights[i], biases[i]).unflatten(-1, (self.num_heads, self.head_dim))
            if norm is None:
                return t
            t = norm(t)
            return t if rope is None else apply_rope(t, *rope, token_dim=-3)

        # One projection at a time: the (B, N, 3D) output of the fused matrix never exists (at the paper size,
        # 13,312 tokens, it was 0.33 GB alive beside the rotated queries and keys; benchmarks/dit_memory.py).
        q, k, v = project(0, self.q_norm), project(1, self.k_norm), project(2)
        return self.proj(_attend(q, k, v).reshape(B, N, D))


def _attend(q: Tensor, k: Tensor, v: Tensor, keep: Tensor | None = None) -> Tensor:
    """Scaled dot-product attention on heads-inner tensors: q (B, N, heads, d), k and v (B, L, heads, d), keep
    (B, L) bool or None → (B, N, heads, d).

    The projections' own layout: their outputs are split into heads by a view, normalised and rotated in place of
    a transposed copy, and handed to ``scaled_dot_product_attention`` as (B, heads, N, d) views, which its kernels
    take as they are; they write the output in the query's layout, so (B, N, heads·d) is a view again. Transposing
    first made the kernels write heads-outer and cost a copy of the output per attention (0.22 GB at the paper
    size, twice a block)."""
    mask = None if keep is None else keep[:, None, None, :]
    return F.scaled_dot_product_attention(q.transpose(1, 2), k.transpose(1, 2), v.transpose(1, 2),
                                          attn_mask=mask).transpose(1, 2)


class CrossAttention(_MultiHead):
    """Multi-head cross-attention from tokens to a context sequence, with a key padding mask.

    Queries come from ``x``; keys/values from ``context`` (e.g. text tokens, as in PixArt-α).
    QK-norm as in :class:`SelfAttention`; no positional rotation.
    """

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
        """Attend each token of ``x`` (B, N, D) to ``context`` (B, L, context_dim); returns (B, N, D).

        Masked context tokens get exactly zero attention weight. A sample whose mask is all False
        has nothing to attend to: its output is exactly zero (not NaN). This is done with tensor
        ops only (the mask row is opened to all keys, then the result is multiplied by 0), so the
        module traces/exports without data-dependent branches.

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
