"""Tests for models.layers: timestep embedding, modulation, patchify, self-/cross-attention."""
import collections
import math
from unittest import mock

import pytest
import torch
import torch.nn.functional as F
from simulated_cuda import simulated_cuda
from torch.utils._python_dispatch import TorchDispatchMode

from models.layers import (
    CrossAttention,
    Mlp,
    QKNorm,
    SelfAttention,
    modulate,
    modulated_layer_norm,
    patchify,
    timestep_embedding,
    unpatchify,
)
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


def test_modulated_layer_norm_is_modulate_of_layer_norm():
    """One sample runs LayerNorm with the modulation as its own affine, several run LayerNorm then one addcmul:
    both are modulate(LayerNorm(x)) in float64 with its gradients (gradcheck); in bfloat16 the one-sample kernel
    rounds once, so it is no further from the float64 result than the chain; bf16 autocast gives modulate's
    dtype."""
    g = torch.Generator().manual_seed(0)
    for batch in (1, 3):
        x = torch.randn(batch, 5, 8, generator=g, dtype=torch.float64) * 3 + 1
        shift, scale = torch.randn(batch, 8, generator=g, dtype=torch.float64), torch.randn(batch, 8, generator=g,
                                                                                           dtype=torch.float64)
        ref = modulate(F.layer_norm(x, (8,), eps=1e-6), shift, scale)
        torch.testing.assert_close(modulated_layer_norm(x, shift, scale, 1e-6), ref, rtol=0, atol=1e-12)
        args = tuple(t.clone().requires_grad_() for t in (x, shift, scale))
        assert torch.autograd.gradcheck(lambda *a: modulated_layer_norm(*a, 1e-6), args)
    x, shift, scale = (t.bfloat16() for t in (torch.randn(1, 256, 64, generator=g), torch.randn(1, 64, generator=g),
                                              torch.randn(1, 64, generator=g)))
    truth = modulate(F.layer_norm(x.double(), (64,), eps=1e-6), shift.double(), scale.double())
    fused, chain = modulated_layer_norm(x, shift, scale, 1e-6), modulate(F.layer_norm(x, (64,), eps=1e-6), shift, scale)
    assert fused.dtype == chain.dtype == torch.bfloat16
    assert float((fused.double() - truth).abs().mean()) <= float((chain.double() - truth).abs().mean())
    with torch.autocast("cpu", dtype=torch.bfloat16):
        for batch in (1, 2):
            xb, sb = x.expand(batch, -1, -1), shift.expand(batch, -1)
            expected = modulate(F.layer_norm(xb, (64,), eps=1e-6), sb, sb)
            assert modulated_layer_norm(xb, sb, sb, 1e-6).dtype == expected.dtype


def test_attention_merges_the_heads_without_copying_the_tokens():
    """Self- and cross-attention hand the heads to the attention kernel as views of the projections' outputs, and
    read its output back as a view: no op of theirs copies the tokens (a transposed layout costs one copy per
    attention, 0.22 GB at the paper size)."""
    class Ops(TorchDispatchMode):
        def __init__(self):
            super().__init__()
            self.seen, self.copies = collections.Counter(), []

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            out = func(*args, **(kwargs or {}))
            name = func.overloadpacket.__name__
            self.seen[name] += 1
            if name in ("clone", "contiguous", "copy_", "_to_copy") and out.numel() >= x.numel() // 4:
                self.copies.append((name, tuple(out.shape)))
            return out

    torch.manual_seed(0)
    attn, cross = SelfAttention(64, 4), CrossAttention(64, 32, 4)
    x, ctx, rope = torch.randn(2, 48, 64), torch.randn(2, 7, 32), rope_3d(2, 4, 6, 16)
    keep = torch.tensor([[True] * 3 + [False] * 4, [True] * 7])
    with torch.no_grad(), Ops() as ops:
        attn(x, rope), cross(x, ctx), cross(x, ctx, keep)
    assert ops.seen["_scaled_dot_product_flash_attention_for_cpu"] + ops.seen["scaled_dot_product_attention"] >= 3
    assert ops.copies == []


def test_feed_forward_applies_its_gelu_in_the_gemm_epilogue_on_cuda_only():
    """Without autograd on CUDA (here the simulated device, which runs ``_addmm_activation`` as CUDA does: the tanh
    GELU) the first GEMM applies the GELU, and the output is the plain path's; on the CPU, whose
    ``_addmm_activation`` applies the erf form, and with autograd, the plain path runs."""
    torch.manual_seed(0)
    mlp, x = Mlp(16, 64, 8), torch.randn(2, 5, 16) * 2
    with torch.no_grad():
        plain, erf = (mlp.fc2(F.gelu(mlp.fc1(x), approximate=form)) for form in ("tanh", "none"))
    spy = mock.patch.object(torch, "_addmm_activation", wraps=torch._addmm_activation)
    with spy as fused, torch.no_grad():
        assert torch.equal(mlp(x), plain) and fused.call_count == 0
    with simulated_cuda(), spy as fused:
        cuda_mlp, cuda_x = mlp.to("cuda"), x.to("cuda")
        with torch.no_grad():
            out = cuda_mlp(cuda_x)
        assert fused.call_count == 1 and out.device.type == "cuda"
        torch.testing.assert_close(out.cpu(), plain, rtol=1e-6, atol=1e-6)
    assert float((erf - plain).abs().max()) > 1e-5  # the two GELU forms differ: the check above can tell them apart


@pytest.mark.cuda
def test_feed_forward_gelu_epilogue_matches_the_plain_path_on_a_gpu():
    """On a GPU, in bfloat16: cuBLASLt's GELU epilogue against the separate GEMM and tanh GELU, to bfloat16
    rounding."""
    torch.manual_seed(0)
    mlp = Mlp(256, 1024).to("cuda", torch.bfloat16)
    x = torch.randn(3, 77, 256, device="cuda", dtype=torch.bfloat16)
    with torch.no_grad():
        fused = mlp(x)
        plain = mlp.fc2(mlp.act(mlp.fc1(x)))
    torch.testing.assert_close(fused.float(), plain.float(), rtol=2e-2, atol=2e-2)


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
