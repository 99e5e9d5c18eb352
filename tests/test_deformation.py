"""Tests of models/deformation.py: identity at init, time dependence, activations, reference forward."""
from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F
from helpers import tiny_model

import models.deformation as deformation
from diff4splat.runtime import TorchRuntime
from diff4splat.scene.dynamic import DynamicGaussians
from diff4splat.scene.gaussians import Gaussians
from diff4splat.scene.quaternions import quat_multiply, quat_normalize, quat_to_rotmat
from models.deformation import (
    DeformationConfig,
    DeformationNetwork,
    deformation_activations,
    soft_clamp,
    time_embedding,
    unit_quat_from_raw,
)

IDENTITY = torch.tensor([1.0, 0.0, 0.0, 0.0])


def _net(seed: int = 0, perturb: bool = False, **kw) -> DeformationNetwork:
    torch.manual_seed(seed)
    net = DeformationNetwork(DeformationConfig(**kw))
    if perturb:
        with torch.no_grad():
            net.out_conv.weight.normal_(0.0, 0.5)
            net.out_conv.bias.normal_(0.0, 0.1)
    return net


def test_identity_at_init_exact():
    net = _net()
    feats = torch.randn(2, 64, 8, 8)
    times = torch.linspace(0, 1, 5)
    dm, dq, ds = net(feats, times, upsample=8)
    assert dm.shape == (2, 5, 64, 64, 3) and dq.shape == (2, 5, 64, 64, 4) and ds.shape == (2, 5, 64, 64, 3)
    assert torch.equal(dm, torch.zeros_like(dm))
    assert torch.equal(dq, IDENTITY.expand_as(dq))
    assert torch.equal(ds, torch.zeros_like(ds))


def test_perturbed_deformation_nonzero_and_time_varying():
    net = _net(perturb=True)
    feats = torch.randn(1, 64, 8, 8)
    dm, dq, ds = net(feats, torch.tensor([0.0, 0.5, 1.0]), upsample=8)
    assert dm.abs().max() > 1e-3 and ds.abs().max() > 1e-3
    assert (dq - IDENTITY).abs().max() > 1e-3
    for field in (dm, dq, ds):
        assert (field[:, 0] - field[:, 2]).abs().max() > 1e-4, "deformation must depend on time"
        assert (field[:, 0] - field[:, 1]).abs().max() > 1e-4
    torch.testing.assert_close(dq.norm(dim=-1), torch.ones(dq.shape[:-1]))
    cfg = net.config
    assert dm.abs().max() < cfg.max_offset and ds.abs().max() < cfg.max_log_scale
    # deformation varies across pixels too (driven by the features, not only by time)
    assert (dm[0, 0, 0, 0] - dm[0, 0, 40, 17]).abs().max() > 1e-5


def _reference_forward(net: DeformationNetwork, feats, times, u):
    """Brute force in the order the design states it: per time, FiLM each level at its own
    resolution, upsample, sum; fuse; upsample to pixels; 1×1 conv; activations."""
    cfg = net.config
    B, _, h, w = feats.shape
    levels = [F.gelu(net.in_conv(feats))]
    for down in net.down:
        levels.append(F.gelu(down(levels[-1])))
    outs = []
    for t in times:
        film = net.time_mlp(time_embedding(t[None], cfg.time_frequencies))[0].reshape(cfg.levels, 2, cfg.hidden)
        agg = 0
        for lvl, f in enumerate(levels):
            g, b = film[lvl, 0][None, :, None, None], film[lvl, 1][None, :, None, None]
            agg = agg + F.interpolate(f * (1 + g) + b, size=(h, w), mode="bilinear", align_corners=False)
        x = F.gelu(net.fuse(agg))
        x = F.interpolate(x, scale_factor=u, mode="bilinear", align_corners=False)
        outs.append(net.out_conv(x).permute(0, 2, 3, 1))  # (B, H, W, 10)
    return deformation_activations(torch.stack(outs, 1), cfg.max_offset, cfg.max_log_scale)


def test_matches_reference_forward():
    net = _net(perturb=True, in_channels=16, hidden=8).double()
    feats = torch.randn(2, 16, 6, 4, dtype=torch.float64)
    times = torch.tensor([0.0, 0.3, 1.0], dtype=torch.float64)
    got = net(feats, times, upsample=4)
    ref = _reference_forward(net, feats, times, 4)
    for g, r in zip(got, ref, strict=True):
        torch.testing.assert_close(g, r, atol=1e-10, rtol=1e-10)


def test_key_times_in_chunks_equal_one_pass_values_and_gradients(monkeypatch):
    """Chunking over key times (bounded hidden memory for long paths) changes no value and no gradient."""
    net = _net(perturb=True)
    feats = torch.randn(2, 64, 4, 6, requires_grad=True)
    times = torch.linspace(0, 1, 7)
    whole = net(feats, times, upsample=4)
    grads = torch.autograd.grad(sum((o * torch.arange(o.numel()).reshape(o.shape).cos()).sum() for o in whole), feats)
    for k in (1, 3):  # key times per chunk (3 leaves a remainder of 1 of the 7); hidden values at B = 2, F = 32, 4×6
        monkeypatch.setattr(deformation, "CHUNK_ELEMENTS", k * 2 * 32 * 4 * 6 + 5)
        parts = net(feats, times, upsample=4)
        for a, b in zip(parts, whole, strict=True):
            torch.testing.assert_close(a, b, rtol=0, atol=1e-6)
        loss = sum((o * torch.arange(o.numel()).reshape(o.shape).cos()).sum() for o in parts)
        torch.testing.assert_close(torch.autograd.grad(loss, feats)[0], grads[0], rtol=1e-5, atol=1e-6)


def test_single_level_and_odd_sizes():
    net = _net(perturb=True, levels=1, in_channels=8, hidden=4).double()
    feats, times = torch.randn(1, 8, 3, 5, dtype=torch.float64), torch.tensor([0.2, 0.7], dtype=torch.float64)
    got = net(feats, times, upsample=2)
    assert got[0].shape == (1, 2, 6, 10, 3)
    for g, r in zip(got, _reference_forward(net, feats, times, 2), strict=True):
        torch.testing.assert_close(g, r, atol=1e-10, rtol=1e-10)


def test_composition_with_canonical_gaussians_matches_the_brute_force_formula():
    """The network's offsets applied by DynamicGaussians.at(t) at a sampled time give μ + Δμ,
    R(q_t) = R(Δq)·R(q) and s·exp(Δs), Gaussian by Gaussian."""
    D = torch.float64
    net = _net(perturb=True, in_channels=8, hidden=4).double()
    times = torch.tensor([0.0, 0.5, 1.0], dtype=D)
    dm, dq, ds = (x[0].reshape(3, -1, x.shape[-1]) for x in net(torch.randn(1, 8, 2, 3, dtype=D), times, 2))
    M = dm.shape[1]
    g = torch.Generator().manual_seed(4)
    canon = Gaussians(torch.randn(M, 3, generator=g, dtype=D), torch.randn(M, 4, generator=g, dtype=D),
                      0.05 + torch.rand(M, 3, generator=g, dtype=D), torch.full((M,), 0.5, dtype=D),
                      torch.rand(M, 1, 3, generator=g, dtype=D))
    scene = DynamicGaussians(canon, times, dm, dq, ds)
    for k, t in enumerate(times.tolist()):
        at = scene.at(t)
        torch.testing.assert_close(at.means, canon.means + dm[k])
        torch.testing.assert_close(at.scales, canon.scales * torch.exp(ds[k]))
        q = quat_normalize(canon.quats)
        torch.testing.assert_close(quat_to_rotmat(at.quats), quat_to_rotmat(dq[k]) @ quat_to_rotmat(q))
        torch.testing.assert_close(at.quats, quat_normalize(quat_multiply(dq[k], q)))
        assert (at.means - canon.means).abs().max() > 1e-4  # the perturbed network really moves them
    assert (scene.at(0.0).means - scene.at(1.0).means).abs().max() > 1e-4


def test_time_embedding_closed_form():
    t = torch.tensor([0.0, 0.25, 1.0], dtype=torch.float64)
    emb = time_embedding(t, 3)
    assert emb.shape == (3, 6)
    for i, tv in enumerate(t.tolist()):
        expect = []
        for k in range(3):
            expect += [math.sin(2**k * math.pi * tv), math.cos(2**k * math.pi * tv)]
        torch.testing.assert_close(emb[i], torch.tensor(expect, dtype=torch.float64))
    assert (emb[0] - emb[2]).abs().max() > 1.0  # t = 0 and t = 1 are distinguishable


def test_a_bfloat16_network_embeds_times_in_float32():
    """The time MLP of a bfloat16 network sees the float32 embedding rounded once to bfloat16 (error ≤ 2⁻⁸ against
    float64), also through the runtime's LDRM call; embedding bfloat16 times (1/48 rounds by 2⁻¹²) in bfloat16
    is off by up to 0.5 rad in the top octave (2⁵·π·t)."""
    seen = []
    times = torch.tensor([0.0, 1 / 48, 0.5, 47 / 48, 1.0])
    ref = time_embedding(times.double(), 6)
    net = _net(perturb=True).to(torch.bfloat16)
    net.time_mlp.register_forward_pre_hook(lambda m, args: seen.append(args[0]))
    net(torch.randn(1, 64, 8, 8, dtype=torch.bfloat16), times, upsample=8)
    assert seen[-1].dtype == torch.bfloat16 and (seen[-1].double() - ref).abs().max() <= 2**-8
    bf16 = time_embedding(times.to(torch.bfloat16), 6).double()
    assert (bf16 - ref).abs().max() > 0.05  # what the cast before the embedding gave

    runtime = TorchRuntime(tiny_model(dynamic=True), dtype=torch.bfloat16)
    dnet = runtime.networks["ldrm"].deformation
    dnet.time_mlp.register_forward_pre_hook(lambda m, args: seen.append(args[0]))
    c = runtime.config
    n = runtime.latent.num_latent_frames(9)
    latents = torch.randn(1, runtime.latent.latent_channels, n, c.height // 8, c.width // 8)
    plucker = torch.zeros(1, 6 * runtime.latent.temporal_factor * runtime.latent.spatial_factor ** 2, n,
                          c.height // 8, c.width // 8)
    runtime.reconstruct(latents, plucker, times, torch.zeros(1, 3, c.height, c.width))
    ref = time_embedding(times.double(), dnet.config.time_frequencies)
    assert (seen[-1].double() - ref).abs().max() <= 2**-8


def test_activations_zero_identity_and_extremes():
    dm, dq, ds = deformation_activations(torch.zeros(7, 10), 2.0, 3.0)
    assert torch.equal(dm, torch.zeros(7, 3)) and torch.equal(ds, torch.zeros(7, 3))
    assert torch.equal(dq, IDENTITY.expand(7, 4))
    raw = torch.tensor([[1e4] * 10, [-1e4] * 10, [1e4, -1e4] * 5])
    dm, dq, ds = deformation_activations(raw, 2.0, 3.0)
    for x in (dm, dq, ds):
        assert torch.isfinite(x).all()
    assert dm.abs().max() <= 2.0 and ds.abs().max() <= 3.0
    torch.testing.assert_close(dq.norm(dim=-1), torch.ones(3))
    # soft clamp: slope 1 at the origin, bound·tanh(x/bound) in general
    x = torch.tensor([1e-4, 0.7, -5.0])
    torch.testing.assert_close(soft_clamp(x, 2.0), 2.0 * torch.tanh(x / 2.0))
    assert abs(float(soft_clamp(torch.tensor(1e-4), 2.0)) - 1e-4) < 1e-9


def test_unit_quat_from_raw():
    raw = torch.tensor([[0.0, 0.0, 0.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [1.0, 2.0, -2.0, 0.0], [-3.0, 0.0, 4.0, 0.0]])
    q = unit_quat_from_raw(raw)
    assert torch.equal(q[0], IDENTITY)
    assert torch.equal(q[1], IDENTITY), "zero-norm sum falls back to the identity, not NaN"
    torch.testing.assert_close(q[2], torch.tensor([2.0, 2.0, -2.0, 0.0]) / math.sqrt(12))
    torch.testing.assert_close(q[3], torch.tensor([-2.0, 0.0, 4.0, 0.0]) / math.sqrt(20))


def test_gradients_reach_every_parameter_after_perturbation():
    net = _net()
    feats = torch.randn(1, 64, 4, 4)
    times = torch.tensor([0.1, 0.9])
    w = [torch.randn(1, 2, 16, 16, c) for c in (3, 4, 3)]
    # at init only the zero-initialised layer receives gradient (its input is non-zero)
    loss = sum((o * wi).sum() for o, wi in zip(net(feats, times, 4), w, strict=True))
    loss.backward()
    assert net.out_conv.weight.grad.abs().sum() > 0
    net.zero_grad()
    with torch.no_grad():
        net.out_conv.weight.normal_(0.0, 0.5)
    loss = sum((o * wi).sum() for o, wi in zip(net(feats, times, 4), w, strict=True))
    loss.backward()
    for name, p in net.named_parameters():
        assert p.grad is not None and p.grad.abs().sum() > 0, f"no gradient for {name}"


def test_validation_errors():
    net = _net(in_channels=8, hidden=4)
    with pytest.raises(ValueError, match="features"):
        net(torch.randn(1, 7, 4, 4), torch.tensor([0.5]), 2)
    with pytest.raises(ValueError, match="features"):
        net(torch.randn(8, 4, 4), torch.tensor([0.5]), 2)
    with pytest.raises(ValueError, match="times"):
        net(torch.randn(1, 8, 4, 4), torch.tensor([[0.5]]), 2)
    with pytest.raises(ValueError, match="upsample"):
        net(torch.randn(1, 8, 4, 4), torch.tensor([0.5]), 0)
    with pytest.raises(ValueError, match="levels"):
        DeformationConfig(levels=0)
    with pytest.raises(ValueError, match="max_offset"):
        DeformationConfig(max_offset=0.0)


def test_save_load_round_trip(tmp_path):
    net = _net(perturb=True, in_channels=8, hidden=4, levels=2)
    feats, times = torch.randn(1, 8, 4, 4), torch.tensor([0.0, 1.0])
    net.save_pretrained(tmp_path / "deform")
    loaded = DeformationNetwork.from_pretrained(tmp_path / "deform")
    assert loaded.config == net.config
    for a, b in zip(net(feats, times, 2), loaded(feats, times, 2), strict=True):
        assert torch.equal(a, b)
