"""Tests for models/text_encoder.py: byte tokenizer, T5 buckets, masking, paper size, save/load."""
from __future__ import annotations

import warnings

import pytest
import torch

from models.pretrained import count_parameters
from models.text_encoder import (
    PAPER_TEXT_ENCODER,
    ByteTokenizer,
    TextEncoder,
    TextEncoderConfig,
    relative_position_bucket,
)

# T5EncoderModel.from_pretrained("google/t5-v1_1-xxl"): 4,762,310,656 parameters. By hand:
# embedding 32128·4096 + 24·(4·4096·4096 + 3·4096·10240 + 2·4096) + 32·64 + 4096. The encoder-only
# fp16 file t5xxl_fp16.safetensors (9.79 GB) matches it with the tied embedding stored twice:
# (4,762,310,656 + 131,596,288)·2 B = 9.79e9 B.
T5_XXL_ENCODER_PARAMS = 4_762_310_656


def _model(seed: int = 0, **kw) -> TextEncoder:
    torch.manual_seed(seed)
    return TextEncoder(TextEncoderConfig(**kw)).eval()


def test_byte_tokenizer_ids_mask_truncation():
    tok = ByteTokenizer(max_length=8)
    with pytest.warns(UserWarning, match="cut to its first 6"):
        ids, mask = tok(["ab", "", "héllo wörld"])
    assert ids.dtype == torch.long and mask.dtype == torch.bool and ids.shape == (3, 8)
    assert ids[0, :4].tolist() == [1, ord("a") + 3, ord("b") + 3, 2] and ids[0, 4:].tolist() == [0] * 4
    assert ids[1, :2].tolist() == [1, 2] and mask[1].tolist() == [True, True] + [False] * 6
    assert mask[2].all() and ids[2, -1] == 2  # truncated to 6 bytes, eos kept
    assert tok.decode(ids)[:2] == ["ab", ""]
    assert tok.decode(ids)[2] == "héllo"  # "h", "é" (2 bytes), "llo" = 6 bytes
    ids_max, _ = tok(["a"], padding="max_length")
    assert ids_max.shape == (1, 8)
    assert ByteTokenizer(100).decode(ByteTokenizer(100)(["Grüße, 世界"])[0]) == ["Grüße, 世界"]
    for bad in ([], "text", [1]):
        with pytest.raises(ValueError, match="prompts"):
            tok(bad)
    with pytest.raises(ValueError, match="max_length"):
        ByteTokenizer(1)
    with pytest.raises(ValueError, match="padding"):
        tok(["a"], padding="right")


def test_byte_tokenizer_warns_only_when_it_cuts():
    tok = ByteTokenizer(max_length=8)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ids, _ = tok(["abcdef", "héllo"])  # 6 bytes each: room for both
    assert tok.decode(ids) == ["abcdef", "héllo"]
    with pytest.warns(UserWarning, match="max_length 8"):
        ids, _ = tok(["abcdefg"])  # 7 bytes
    assert tok.decode(ids) == ["abcdef"]


def test_relative_position_bucket_known_values():
    # Hand-computed from the T5 definition with 32 buckets, max_distance 128 (16 per direction, 8 exact).
    rel = torch.tensor([0, -1, 1, -7, -8, -15, -16, -32, -64, -127, -128, -1000, 7, 8, 16, 1000])
    expected = [0, 1, 17, 7, 8, 9, 10, 12, 14, 15, 15, 15, 23, 24, 26, 31]
    assert relative_position_bucket(rel, 32, 128).tolist() == expected


def test_attention_layer_matches_explicit_reference():
    model = _model(1)
    x = torch.randn(2, 5, 64)
    mask = torch.tensor([[True] * 5, [True] * 3 + [False] * 2])
    bias = model.position_bias(5) + torch.zeros(2, 5).masked_fill(~mask, float("-inf"))[:, None, None, :]
    attn = model.blocks[0].attn
    out = attn(x, bias)
    # Explicit loops over batch and head: softmax(q k^T + B) v, no 1/√d scaling.
    q = attn.q(x).view(2, 5, 4, 16)
    k = attn.k(x).view(2, 5, 4, 16)
    v = attn.v(x).view(2, 5, 4, 16)
    heads = torch.zeros(2, 5, 4, 16)
    for b in range(2):
        for h in range(4):
            logits = q[b, :, h] @ k[b, :, h].T + bias[b, h]
            heads[b, :, h] = torch.softmax(logits, dim=-1) @ v[b, :, h]
    assert torch.allclose(out, attn.o(heads.reshape(2, 5, 64)), atol=1e-5)


def test_padding_does_not_change_token_outputs():
    model = _model(2)
    alone, mask_alone = model.encode_text(["a cat"])
    batch, mask_batch = model.encode_text(["a cat", "a much longer prompt about a dog running"])
    n = int(mask_alone.sum())
    assert n == 7 and int(mask_batch[0].sum()) == n and mask_batch.shape[1] > n
    assert torch.allclose(batch[0, :n], alone[0, :n], atol=1e-5)
    assert torch.equal(batch[0, n:], torch.zeros_like(batch[0, n:]))  # padded rows are zeroed
    padded, _ = model.encode_text(["a cat"], padding="max_length")
    assert padded.shape == (1, 64, 64) and torch.allclose(padded[0, :n], alone[0, :n], atol=1e-5)
    # No absolute positions: left padding (masked keys) shifts every index yet changes nothing.
    ids, mask = model.tokenizer(["a cat"])
    left_ids = torch.cat([torch.zeros(1, 5, dtype=torch.long), ids], dim=1)
    left_mask = torch.cat([torch.zeros(1, 5, dtype=torch.bool), mask], dim=1)
    left = model(left_ids, left_mask)
    assert torch.allclose(left[0, 5:], alone[0], atol=1e-5)


def test_mask_is_needed_and_prompts_differ():
    model = _model(3)
    a, _ = model.encode_text(["a red car", "a red cat"])
    assert a.shape == (2, 11, 64)
    assert not torch.allclose(a[0], a[1], atol=1e-3)
    # The first tokens differ too: attention mixes in the later, different byte (bidirectional).
    assert (a[0, 0] - a[1, 0]).abs().max() > 1e-4
    # Without the mask the padding would leak into real tokens.
    ids, mask = model.tokenizer(["a cat", "a much longer prompt"])
    unmasked = model(ids)[0, : int(mask[0].sum())]
    masked = model(ids, mask)[0, : int(mask[0].sum())]
    assert (unmasked - masked).abs().max() > 1e-4


def test_empty_prompt_and_errors():
    model = _model(4)
    tokens, mask = model.encode_text([""])
    assert tokens.shape == (1, 2, 64) and mask.tolist() == [[True, True]]
    assert torch.isfinite(tokens).all()
    with pytest.raises(ValueError, match="prompts"):
        model.encode_text([])
    with pytest.raises(ValueError, match="ids must lie"):
        model(torch.tensor([[1, 300]]))
    with pytest.raises(ValueError, match="at least one real token"):
        model(torch.tensor([[1, 2]]), torch.tensor([[False, False]]))
    with pytest.raises(ValueError, match="mask"):
        model(torch.tensor([[1, 2]]), torch.tensor([[1, 1]]))
    with pytest.raises(ValueError, match="vocab_size"):
        TextEncoderConfig(vocab_size=100)


def test_gradients_reach_every_parameter():
    model = _model(5).train()
    ids, mask = model.tokenizer(["gradient check", "x"])
    model(ids, mask).square().sum().backward()
    for name, p in model.named_parameters():
        assert p.grad is not None and p.grad.abs().sum() > 0, name


def test_save_from_pretrained_round_trip(tmp_path):
    model = _model(6, num_layers=1, max_length=32)
    model.save_pretrained(tmp_path / "t5")
    loaded = TextEncoder.from_pretrained(tmp_path / "t5").eval()
    assert loaded.config == model.config and loaded.tokenizer.max_length == 32
    for k, v in model.state_dict().items():
        assert torch.equal(v, loaded.state_dict()[k]), k
    a, _ = model.encode_text(["round trip"])
    b, _ = loaded.encode_text(["round trip"])
    assert torch.equal(a, b)


def test_tiny_and_paper_parameter_counts():
    tiny = count_parameters(TextEncoder(TextEncoderConfig()))
    print(f"tiny TextEncoder parameters: {tiny:,}")
    assert 5_000 < tiny < 500_000
    with torch.device("meta"):
        paper = TextEncoder(TextEncoderConfig.paper())
    n = count_parameters(paper)
    print(f"paper TextEncoder (T5-v1.1-XXL encoder shape) parameters: {n:,}")
    assert abs(n - T5_XXL_ENCODER_PARAMS) / T5_XXL_ENCODER_PARAMS < 0.01
    assert n == T5_XXL_ENCODER_PARAMS  # same layout, so the count is exact
    assert PAPER_TEXT_ENCODER["d_model"] == 4096
    tokens = paper(torch.ones(1, 3, dtype=torch.long, device="meta"))
    assert tokens.shape == (1, 3, 4096)
