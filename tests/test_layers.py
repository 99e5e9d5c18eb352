"""Tests for models.layers: timestep embedding, modulation, patchify, self-/cross-attention."""
import math

import pytest
import torch
import torch.nn.functional as F

from models.layers import CrossAttention, QKNorm, SelfAttention, modulate, patchify, timestep_embedding, unpatchify
from models.rope import apply_rope, rope_3d


def test_timestep_embedding_closed_form():
    t = torch.tensor([0.0, 3.0, 500.0])
    emb = timestep_embedding(t, 6, max_period=100.0)
    freqs = [100.0 ** (-i / 3) for i in range(3)]
    expected = [[math.cos(tt * f) for f in freqs] + [math.sin(tt * f) for f in freqs] for tt in t.tolist()]
    torch.testing.assert_close(emb, torch.tensor(expected), rtol=0, atol=1e-5)
    assert timestep_embedding(t, 7).shape == (3, 7)
    with pytest.raises(ValueError, match="t must"):
        timestep_embedding(t[:, None], 8)


def test_modulate_is_per_sample_affine():
    x = torch.randn(2, 3, 4)
    shift, scale = torch.randn(2, 4), torch.randn(2, 4)
    out = modulate(x, shift, scale)
    torch.testing.assert_close(out[1, 2], x[1, 2] * (1 + scale[1]) + shift[1])


def test_patchify_linear_equals_conv3d_and_unpatchify_inverts():
    x = torch.randn(2, 3, 4, 6, 8)
    patch = (2, 2, 2)
    conv = torch.nn.Conv3d(3, 5, kernel_size=patch, stride=patch)
    tokens = patchify(x, patch)  # (2, 2·3·4, 3·8)
    assert tokens.shape == (2, 24, 24)
    via_linear = F.linear(tokens, conv.weight.reshape(5, -1), conv.bias)
    via_conv = conv(x).flatten(2).transpose(1, 2)  # frame-major token order
    torch.testing.assert_close(via_linear, via_conv, rtol=1e-5, atol=1e-5)
    assert torch.equal(unpatchify(tokens, patch, (2, 3, 4), 3), x)
    with pytest.raises(ValueError, match="divisible"):
        patchify(x[..., :7], patch)
    with pytest.raises(ValueError, match="tokens"):
        unpatchify(tokens, patch, (2, 3, 3), 3)


def _reference_attention(q, k, v, keep=None):
    logits = q @ k.transpose(-1, -2) / math.sqrt(q.shape[-1])
    if keep is not None:
        logits = logits.masked_fill(~keep[:, None, None, :], float("-inf"))
    return torch.softmax(logits, dim=-1) @ v


def test_self_attention_matches_reference_with_rope():
    torch.manual_seed(0)
    attn = SelfAttention(16, 2, qk_norm=True).double()
    x = torch.randn(2, 12, 16, dtype=torch.float64)
    rope = rope_3d(2, 2, 3, 8, dtype=torch.float64)
    q, k, v = attn.qkv(x).reshape(2, 12, 3, 2, 8).permute(2, 0, 3, 1, 4)
    rms = lambda t, w: t / t.pow(2).mean(-1, keepdim=True).add(1e-6).sqrt() * w  # noqa: E731
    q, k = apply_rope(rms(q, attn.q_norm.weight), *rope), apply_rope(rms(k, attn.k_norm.weight), *rope)
    ref = attn.proj(_reference_attention(q, k, v).transpose(1, 2).reshape(2, 12, 16))
    torch.testing.assert_close(attn(x, rope), ref, rtol=1e-10, atol=1e-10)


def test_cross_attention_mask_matches_reference_and_empty_rows_are_zero():
    torch.manual_seed(0)
    attn = CrossAttention(16, 8, 4, qk_norm=False).double()
    x = torch.randn(3, 5, 16, dtype=torch.float64)
    ctx = torch.randn(3, 4, 8, dtype=torch.float64)
    keep = torch.tensor([[True, True, False, False], [True, True, True, True], [False] * 4])
    out = attn(x, ctx, keep)
    q = attn.q(x).reshape(3, 5, 4, 4).transpose(1, 2)
    k, v = attn.kv(ctx).reshape(3, 4, 2, 4, 4).permute(2, 0, 3, 1, 4)
    ref = attn.proj(_reference_attention(q[:2], k[:2], v[:2], keep[:2]).transpose(1, 2).reshape(2, 5, 16))
    torch.testing.assert_close(out[:2], ref, rtol=1e-10, atol=1e-10)
    assert torch.equal(out[2], torch.zeros_like(out[2]))  # nothing to attend to: zero, not NaN
    with pytest.raises(ValueError, match="context_mask"):
        attn(x, ctx, keep.float())


# ---------------------------------------------------------------------------------------------- VideoDiT


def test_qk_norm_is_rmsnorm_and_runs_bf16_inputs_without_the_fallback_warning(recwarn):
    """QKNorm equals torch's RMSNorm (same weight) in float32, bit for bit; a bfloat16 input (bf16 autocast) is
    normalised in bfloat16 by the fused kernel (no "Mismatch dtype" fallback warning) to the float32 result within
    bfloat16 rounding."""
    g = torch.Generator().manual_seed(0)
    norm, ref = QKNorm(16, eps=1e-6), torch.nn.RMSNorm(16, eps=1e-6)
    with torch.no_grad():
        norm.weight.copy_(torch.rand(16, generator=g) + 0.5)
        ref.weight.copy_(norm.weight)
    x = torch.randn(3, 5, 16, generator=g)
    assert torch.equal(norm(x), ref(x))
    out = norm(x.bfloat16())
    assert out.dtype == torch.bfloat16 and not [w for w in recwarn if "Mismatch dtype" in str(w.message)]
    torch.testing.assert_close(out.float(), ref(x), rtol=2e-2, atol=2e-2)
