"""VideoDiT (models/dit.py) and the shared blocks it is built from (models/layers.py)."""
import math

import numpy as np
import onnxruntime as ort
import pytest
import torch

import models.dit as dit_module
from diff4splat.runtime import FF_CHUNK_TOKENS, TorchRuntime
from models.bundle import Diff4SplatModel, load_config
from models.dit import VideoDiT, VideoDiTConfig
from models.dit_reference import reference_block
from models.layers import unpatchify
from models.pretrained import count_parameters

CFG = VideoDiTConfig()
B, C, N, H, W = 2, CFG.latent_channels, 2, 4, 6


def _inputs(seed=0, batch=B, n=N, text_len=5):
    g = torch.Generator().manual_seed(seed)
    return dict(
        x=torch.randn(batch, C, n, H, W, generator=g),
        sigma=torch.rand(batch, generator=g),
        image_latent=torch.randn(batch, C, 1, H, W, generator=g),
        plucker=torch.randn(batch, CFG.camera_channels, n, H, W, generator=g),
        text=torch.randn(batch, text_len, CFG.text_dim, generator=g),
    )


def _perturb(model, seed=1, skip=(), scale=0.2):
    """Add noise to every parameter whose name does not start with a prefix in ``skip``."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, p in model.named_parameters():
            if not name.startswith(tuple(skip)):
                p.add_(scale * torch.randn(p.shape, generator=g))
    return model


def _model(seed=0, **perturb):
    torch.manual_seed(seed)
    return _perturb(VideoDiT(VideoDiTConfig()), **perturb).eval()


# ---------------------------------------------------------------------------------------------- layers

def test_config_validation_and_paper_fields():
    with pytest.raises(ValueError, match="num_heads"):
        VideoDiTConfig(hidden_size=30, num_heads=4)
    with pytest.raises(ValueError, match="head_dim"):
        VideoDiTConfig(hidden_size=8, num_heads=2)  # head_dim 4 < 6
    with pytest.raises(ValueError, match="patch_size"):
        VideoDiTConfig(patch_size=(1, 2))
    p = VideoDiTConfig.paper()
    assert (p.depth, p.hidden_size, p.num_heads, p.latent_channels, p.text_dim, p.patch_size) == \
        (32, 4096, 32, 16, 4096, (1, 2, 2))
    assert p.camera_channels == 6 * 4 * 8 * 8


def _expected_parameter_count(cfg: VideoDiTConfig) -> int:
    """Closed-form count of the architecture described in models/dit.py."""
    D, c, hd, M = cfg.hidden_size, cfg.latent_channels, cfg.head_dim, int(cfg.hidden_size * cfg.mlp_ratio)
    P = math.prod(cfg.patch_size)
    lin = lambda i, o: i * o + o  # noqa: E731
    embed = lin((2 * c + 1) * P, D) + lin(cfg.camera_channels * P, D) \
        + lin(cfg.frequency_embedding_size, D) + lin(D, D) + lin(cfg.text_dim, D) + lin(D, D)
    qk = 2 * hd if cfg.qk_norm else 0
    block = (lin(D, 3 * D) + lin(D, D) + qk) + 2 * D + (lin(D, D) + lin(D, 2 * D) + lin(D, D) + qk) \
        + lin(D, M) + lin(M, D) + lin(D, 6 * D)
    final = lin(D, 2 * D) + lin(D, P * c)
    return embed + cfg.depth * block + final


@pytest.mark.slow
def test_parameter_counts_tiny_and_paper_on_meta():
    tiny = VideoDiT(VideoDiTConfig())
    n_tiny = count_parameters(tiny)
    assert n_tiny == _expected_parameter_count(VideoDiTConfig())
    assert n_tiny < 400_000
    with torch.device("meta"):
        paper = VideoDiT(VideoDiTConfig.paper())
    n_paper = count_parameters(paper)
    print(f"VideoDiT parameters: tiny {n_tiny:,}, paper {n_paper:,}")
    assert n_paper == _expected_parameter_count(VideoDiTConfig.paper())
    assert all(p.device.type == "meta" for p in paper.parameters())


def test_shapes_conditioning_and_batch_independence():
    """Each conditioning input changes v; every batch element is computed on its own (no leakage)."""
    model = _model()
    inp = _inputs()
    text_mask = torch.tensor([[True] * 5, [True, True, False, False, False]])
    outs = []
    with torch.no_grad():
        for kwargs in (dict(inp, text_mask=text_mask), dict(inp, text=None), dict(inp, plucker=None, text=None)):
            v = model(**kwargs)
            assert v.shape == (B, C, N, H, W) and v.dtype == torch.float32 and torch.isfinite(v).all()
            outs.append(v)
            single = model(**{k: x[1:] for k, x in kwargs.items() if x is not None},
                           **{k: None for k, x in kwargs.items() if x is None})
            torch.testing.assert_close(single[0], v[1], atol=1e-5, rtol=1e-5)
        assert (outs[0] - outs[1]).abs().max() > 1e-4 and (outs[1] - outs[2]).abs().max() > 1e-4
        v3 = model(**_inputs(n=3, batch=1))
    assert v3.shape == (1, C, 3, H, W)


def test_zero_init_outputs_exactly_zero():
    torch.manual_seed(0)
    model = VideoDiT(VideoDiTConfig())
    v = model(**_inputs(), text_mask=torch.ones(B, 5, dtype=torch.bool))
    assert torch.equal(v, torch.zeros_like(v))


def test_blocks_are_identity_at_init():
    torch.manual_seed(0)
    model = VideoDiT(VideoDiTConfig())
    # Only the final layer is made non-trivial: the output then equals FinalLayer(patch tokens),
    # which holds only if every block (gated self-attn, zero-proj cross-attn, gated MLP) is the identity.
    _perturb(model, skip=[n for n, _ in model.named_parameters() if not n.startswith("final_layer")])
    inp = _inputs()
    tokens = {}
    model.blocks[0].register_forward_pre_hook(lambda m, args: tokens.update(x=args[0]))
    v = model(**inp)
    emb = model.t_embedder(inp["sigma"] * 1000.0)
    ref = unpatchify(model.final_layer(tokens["x"], emb), CFG.patch_size, (N, H // 2, W // 2), C)
    assert torch.equal(v, ref)


def test_conditioning_channels_layout():
    model = _model()
    inp = _inputs()
    seen = {}
    model.x_embedder.register_forward_pre_hook(lambda m, args: seen.update(tokens=args[0]))
    model(**inp)
    grid = (N, H // 2, W // 2)
    video = unpatchify(seen["tokens"], CFG.patch_size, grid, 2 * C + 1)  # (B, 2c+1, n, h, w)
    assert torch.equal(video[:, :C], inp["x"])
    assert torch.equal(video[:, C:2 * C, :1], inp["image_latent"])
    assert torch.equal(video[:, C:2 * C, 1:], torch.zeros_like(video[:, C:2 * C, 1:]))
    assert torch.equal(video[:, 2 * C, 0], torch.ones(B, H, W))
    assert torch.equal(video[:, 2 * C, 1:], torch.zeros(B, N - 1, H, W))


@pytest.mark.slow
def test_zero_camera_projection_makes_plucker_irrelevant():
    model = _model(skip=["camera_embedder"])  # everything non-trivial except the camera branch
    inp = _inputs()
    v = model(**inp)
    other = model(**dict(inp, plucker=100.0 * torch.randn_like(inp["plucker"])))
    none = model(**dict(inp, plucker=None))
    assert torch.equal(v, other) and torch.equal(v, none)
    _perturb(model.camera_embedder, seed=5)  # a trained camera branch does use the rays
    assert not torch.allclose(model(**inp), v, atol=1e-4)


def test_text_cross_attention_and_padding_mask():
    model = _model()
    inp = _inputs(text_len=4)
    v_text = model(**inp)
    v_none = model(**dict(inp, text=None))
    v_other = model(**dict(inp, text=torch.randn_like(inp["text"])))
    assert not torch.allclose(v_text, v_none, atol=1e-4)
    assert not torch.allclose(v_text, v_other, atol=1e-4)

    # Pad the 4 real tokens with 3 junk tokens: masked, they change nothing; unmasked, they do.
    pad_a = torch.cat([inp["text"], torch.randn(B, 3, CFG.text_dim)], dim=1)
    pad_b = torch.cat([inp["text"], 50.0 * torch.randn(B, 3, CFG.text_dim)], dim=1)
    mask = torch.tensor([[True] * 4 + [False] * 3] * B)
    v_a = model(**dict(inp, text=pad_a), text_mask=mask)
    v_b = model(**dict(inp, text=pad_b), text_mask=mask)
    torch.testing.assert_close(v_a, v_b, rtol=0, atol=1e-6)
    torch.testing.assert_close(v_a, v_text, rtol=0, atol=1e-5)
    assert not torch.allclose(model(**dict(inp, text=pad_a)), v_text, atol=1e-4)

    # A sample whose tokens are all padding gets no text, the other sample is unaffected.
    empty = torch.tensor([[False] * 4, [True] * 4])
    v_empty = model(**inp, text_mask=empty)
    torch.testing.assert_close(v_empty[0], v_none[0], rtol=0, atol=1e-6)
    torch.testing.assert_close(v_empty[1], v_text[1], rtol=0, atol=1e-6)


def test_sigma_conditions_the_output():
    model = _model()
    inp = _inputs()
    assert not torch.allclose(model(**inp), model(**dict(inp, sigma=1.0 - inp["sigma"])), atol=1e-4)


@pytest.mark.slow
def test_gradients_reach_every_parameter_after_unzeroing():
    model = _model().train()
    inp = _inputs()
    loss = model(**inp, text_mask=torch.tensor([[True] * 5, [True] * 3 + [False] * 2])).pow(2).mean()
    loss.backward()
    for name, p in model.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name
        assert p.grad.abs().sum() > 0, f"no gradient reaches {name}"


def test_save_and_from_pretrained_round_trip(tmp_path):
    torch.manual_seed(0)
    cfg = VideoDiTConfig(depth=1, patch_size=(1, 2, 2), mlp_ratio=2.0)
    model = _perturb(VideoDiT(cfg)).eval()
    inp = _inputs()
    model.save_pretrained(tmp_path / "dit")
    loaded = VideoDiT.from_pretrained(tmp_path / "dit").eval()
    assert loaded.config == cfg and isinstance(loaded.config.patch_size, tuple)
    assert torch.equal(loaded(**inp), model(**inp))


@pytest.mark.parametrize(
    "change, match",
    [
        (dict(x=torch.randn(B, C, N, H, W - 1)), "x: latent size"),
        (dict(x=torch.randn(B, C + 1, N, H, W)), "x must"),
        (dict(sigma=torch.rand(B, 1)), "sigma must have shape"),
        (dict(sigma=torch.tensor([0.5, 1.5])), r"sigma must lie in \[0, 1\]"),
        (dict(sigma=torch.tensor([0.5, float("nan")])), r"sigma must lie in \[0, 1\]"),
        (dict(image_latent=torch.randn(B, C, 2, H, W)), "image_latent"),
        (dict(plucker=torch.randn(B, 6, N, H, W)), "plucker"),
        (dict(plucker=torch.randn(B, CFG.camera_channels, N + 1, H, W)), "plucker"),
        (dict(text=torch.randn(B, 5, CFG.text_dim + 1)), "text must"),
        (dict(text_mask=torch.ones(B, 4, dtype=torch.bool)), "text_mask"),
        (dict(text_mask=torch.ones(B, 5)), "text_mask"),
        (dict(text=None, text_mask=torch.ones(B, 5, dtype=torch.bool)), "text_mask was given without text"),
    ],
)
def test_bad_inputs_raise_value_error(change, match):
    model = _model()
    kwargs = dict(_inputs(), text_mask=None)
    kwargs.update(change)
    with pytest.raises(ValueError, match=match):
        model(**kwargs)


@pytest.mark.slow
def test_onnx_export_matches_pytorch(tmp_path):
    model = _model()
    inp = _inputs(batch=1)
    args = (inp["x"], inp["sigma"], inp["image_latent"], inp["plucker"], inp["text"],
            torch.tensor([[True, True, True, False, False]]))
    with torch.no_grad():
        expected = model(*args).numpy()
    path = tmp_path / "dit.onnx"
    program = torch.onnx.export(model, args, dynamo=True, opset_version=18, verbose=False)
    program.save(str(path))
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    names = [i.name for i in session.get_inputs()]
    assert names == ["x", "sigma", "image_latent", "plucker", "text", "text_mask"]
    (out,) = session.run(None, {name: a.numpy() for name, a in zip(names, args, strict=True)})
    assert out.shape == expected.shape
    assert np.abs(out - expected).max() <= 1e-4
    assert np.abs(expected).max() > 1e-2  # a non-trivial output was compared


# ---------------------------------------------------------------------------------- gradient checkpointing

def _loss_and_grads(model, inputs):
    model.zero_grad(set_to_none=True)
    mask = torch.tensor([[True] * 5, [True, True, True, False, False]])
    loss = (model(**inputs, text_mask=mask) ** 2).mean()
    loss.backward()
    return loss.detach(), {n: p.grad.clone() for n, p in model.named_parameters()}


def test_gradient_checkpointing_gives_the_same_loss_and_gradients(monkeypatch):
    """dit.gradient_checkpointing recomputes each block in the backward pass (one checkpoint call per block, only
    while training with gradients): the loss and every gradient equal the plain forward's; it is a runtime
    switch, off after construction and never saved in the config."""
    model = _model().train()
    assert model.gradient_checkpointing is False and "gradient_checkpointing" not in vars(model.config)
    inputs = _inputs()
    plain_loss, plain_grads = _loss_and_grads(model, inputs)
    calls = []
    real = dit_module.checkpoint
    monkeypatch.setattr(dit_module, "checkpoint", lambda *a, **k: calls.append(k) or real(*a, **k))
    model.gradient_checkpointing = True
    loss, grads = _loss_and_grads(model, inputs)
    assert len(calls) == CFG.depth and all(k == {"use_reentrant": False} for k in calls)
    torch.testing.assert_close(loss, plain_loss, rtol=0, atol=0)
    assert plain_grads.keys() == grads.keys() and all(g.abs().sum() > 0 for g in grads.values())
    for name, g in grads.items():
        assert torch.equal(g, plain_grads[name]), name  # the same kernels on the same values: bit for bit
    calls.clear()
    with torch.no_grad():  # no gradients, or eval mode: nothing to save memory for, blocks run plainly
        model(**inputs)
    model.eval()
    model(**inputs)
    assert calls == []


def test_a_block_computes_the_op_by_op_reference():
    """VideoDiTBlock against models.dit_reference (the same parameters, each op on its own: LayerNorm then the
    modulation, heads-outer attention, the textbook RoPE, the GELU apart): equal in float64 for one sample (the
    LayerNorm-affine modulation) and two (addcmul), with and without text, with a padding mask, its MLP chunked or
    not, and so are the gradients."""
    model = _model().double()
    block, D = model.blocks[1], CFG.hidden_size
    g = torch.Generator().manual_seed(7)
    rope = dit_module.rope_3d(2, 2, 3, CFG.head_dim, CFG.rope_theta, dtype=torch.float64)
    for batch in (1, 2):
        x, c = torch.randn(batch, 12, D, generator=g, dtype=torch.float64), torch.randn(batch, D, generator=g,
                                                                                       dtype=torch.float64)
        ctx = torch.randn(batch, 4, D, generator=g, dtype=torch.float64)
        mask = torch.tensor([[True, True, False, False], [False] * 4][:batch])
        for context, context_mask in ((None, None), (ctx, None), (ctx, mask)):
            expected = reference_block(block, x, c, rope, context, context_mask)
            for chunk in (None, 5):
                with torch.no_grad():
                    out = block(x, c, rope, context, context_mask, chunk)
                torch.testing.assert_close(out, expected.detach(), rtol=1e-12, atol=1e-12)
        leaves = [t.clone().requires_grad_() for t in (x, c, ctx)]
        grads = torch.autograd.grad(block(*leaves[:2], rope, leaves[2], None, 5).square().sum(), leaves)
        expected = torch.autograd.grad(reference_block(block, *leaves[:2], rope, leaves[2]).square().sum(), leaves)
        for got, want in zip(grads, expected, strict=True):
            torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-10)


def test_a_block_adds_its_chunked_feed_forward_into_its_own_tensor_only():
    """Without autograd a block adds each feed-forward chunk's residual in place, into the sum its own residuals
    made: the caller's tokens stay as they were, and the output is the unchunked block's, for one sample (the
    LayerNorm-affine modulation) and for two."""
    model = _model()
    block, D = model.blocks[0], CFG.hidden_size
    g = torch.Generator().manual_seed(5)
    rope = dit_module.rope_3d(2, 2, 3, CFG.head_dim, CFG.rope_theta)
    for batch in (1, 2):
        x, c = torch.randn(batch, 12, D, generator=g), torch.randn(batch, D, generator=g)
        ctx = torch.randn(batch, 4, D, generator=g)
        before = x.clone()
        with torch.no_grad():
            plain = block(x, c, rope, ctx)
            chunked = block(x, c, rope, ctx, ff_chunk_tokens=5)
        assert torch.equal(x, before)
        assert not torch.equal(plain, x)  # the block does something (its gates are not zero here)
        torch.testing.assert_close(chunked, plain, rtol=1e-5, atol=1e-6)


def test_feed_forward_chunking_gives_the_same_velocity_in_fewer_tokens_at_a_time():
    """dit.ff_chunk_tokens runs each block's MLP over at most that many tokens (N = 2·2·3 = 12 here: chunks of 5,
    5, 2); the velocity is the unchunked one (the MLP acts on each token alone) and so are the gradients. A
    runtime switch, off after construction; TorchRuntime turns it on for sampling."""
    model = _model()
    assert model.ff_chunk_tokens is None and "ff_chunk_tokens" not in vars(model.config)
    inputs = _inputs()
    with torch.no_grad():
        plain = model(**inputs)
    seen = []
    hooks = [b.mlp.register_forward_hook(lambda m, args, out: seen.append(args[0].shape[1])) for b in model.blocks]
    model.ff_chunk_tokens = 5
    with torch.no_grad():
        chunked = model(**inputs)
    for h in hooks:
        h.remove()
    assert seen == [5, 5, 2] * CFG.depth
    torch.testing.assert_close(chunked, plain, rtol=1e-5, atol=1e-6)
    model.ff_chunk_tokens = None
    plain_loss, plain_grads = _loss_and_grads(model.train(), inputs)
    model.ff_chunk_tokens = 5
    loss, grads = _loss_and_grads(model, inputs)
    torch.testing.assert_close(loss, plain_loss, rtol=1e-5, atol=1e-6)
    for name, g in grads.items():
        torch.testing.assert_close(g, plain_grads[name], rtol=1e-4, atol=1e-6, msg=name)
    runtime = TorchRuntime(Diff4SplatModel.random(load_config("tiny")))
    assert runtime.networks["dit"].ff_chunk_tokens == FF_CHUNK_TOKENS
