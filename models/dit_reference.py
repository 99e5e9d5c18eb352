"""The DiT block written op by op, as DiT, PixArt-α and RoFormer write it: the reference the tests hold
:class:`models.dit.VideoDiTBlock` to. Same parameters; LayerNorm then the modulation (DiT §3.2), heads-outer q, k,
v, QK-norm, RoPE as products of even and odd channels (RoFormer Eq. 14), text cross-attention (PixArt-α) and the
GELU as its own op."""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from models.dit import VideoDiTBlock
from models.layers import CrossAttention, SelfAttention, modulate

__all__ = ["reference_block"]


def reference_block(
    block: VideoDiTBlock,
    x: Tensor,  # (B, N, D) video tokens
    c: Tensor,  # (B, D) σ embedding
    rope: tuple[Tensor, Tensor],  # cos, sin: (N, head_dim/2)
    context: Tensor | None = None,  # (B, L, D) projected text tokens
    context_mask: Tensor | None = None,  # (B, L) bool, True = real token
) -> Tensor:
    """``block(x, c, rope, context, context_mask)`` computed op by op: (B, N, D)."""
    shift_msa, scale_msa, gate_msa, shift_mlp, scale_mlp, gate_mlp = block.adaLN_modulation(c).chunk(6, dim=1)
    D = x.shape[-1]
    h = modulate(F.layer_norm(x, (D,), eps=block.norm1.eps), shift_msa, scale_msa)
    x = x + gate_msa.unsqueeze(1) * _self_attention(block.attn, h, rope)
    if context is not None:
        x = x + _cross_attention(block.cross_attn, block.norm2(x), context, context_mask)
    h = modulate(F.layer_norm(x, (D,), eps=block.norm3.eps), shift_mlp, scale_mlp)
    h = block.mlp.fc2(F.gelu(block.mlp.fc1(h), approximate="tanh"))
    return x + gate_mlp.unsqueeze(1) * h


def _heads(t: Tensor, num_heads: int) -> Tensor:
    """(B, N, heads·d) → (B, heads, N, d)."""
    return t.unflatten(-1, (num_heads, -1)).transpose(1, 2)


def _merge(t: Tensor) -> Tensor:
    """(B, heads, N, d) → (B, N, heads·d)."""
    return t.transpose(1, 2).flatten(-2)


def _rope(x: Tensor, cos: Tensor, sin: Tensor) -> Tensor:
    """RoFormer Eq. 14 on consecutive channel pairs of x (…, N, D), tables (N, D/2)."""
    pairs = x.unflatten(-1, (x.shape[-1] // 2, 2))
    x0, x1 = pairs[..., 0], pairs[..., 1]
    cos, sin = cos.to(x.dtype), sin.to(x.dtype)
    return torch.stack([x0 * cos - x1 * sin, x0 * sin + x1 * cos], dim=-1).flatten(-2)


def _self_attention(attn: SelfAttention, x: Tensor, rope: tuple[Tensor, Tensor] | None) -> Tensor:
    q, k, v = (_heads(t, attn.num_heads) for t in attn.qkv(x).chunk(3, dim=-1))
    q, k = attn.q_norm(q), attn.k_norm(k)
    if rope is not None:
        q, k = _rope(q, *rope), _rope(k, *rope)
    return attn.proj(_merge(F.scaled_dot_product_attention(q, k, v)))


def _cross_attention(attn: CrossAttention, x: Tensor, context: Tensor, mask: Tensor | None) -> Tensor:
    q = attn.q_norm(_heads(attn.q(x), attn.num_heads))
    k, v = (_heads(t, attn.num_heads) for t in attn.kv(context).chunk(2, dim=-1))
    k = attn.k_norm(k)
    if mask is None:
        return attn.proj(_merge(F.scaled_dot_product_attention(q, k, v)))
    has_keys = mask.any(dim=1)  # a sample without a real token gets zero cross-attention
    keep = (mask | ~has_keys[:, None])[:, None, None, :]
    out = attn.proj(_merge(F.scaled_dot_product_attention(q, k, v, attn_mask=keep)))
    return out * has_keys.to(out.dtype)[:, None, None]
