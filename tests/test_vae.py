"""Tests for models/vae.py: shapes, exact temporal causality, posterior, KL, scaling, save/load, paper size."""
from __future__ import annotations

import pytest
import torch
from torch import nn

import models.vae
from models.pretrained import count_parameters
from models.vae import (
    PAPER_VIDEO_VAE,
    CausalConv3d,
    Downsample,
    FrameGroupNorm,
    Upsample,
    VideoVAE,
    VideoVAEConfig,
    causal_mean_pool,
    causal_repeat,
    estimate_latent_scaling,
    kl_divergence,
    sample_posterior,
    upsample2x,
)
from training.eval_metrics import blockiness


def _vae(seed: int = 0, randomize: bool = False) -> VideoVAE:
    """Tiny VAE; ``randomize`` replaces every weight (also the zero-initialised residual convs) by noise,
    so that every path of the network, including the residual branches, takes part in a test."""
    torch.manual_seed(seed)
    vae = VideoVAE(VideoVAEConfig()).eval()
    if randomize:
        with torch.no_grad():
            for p in vae.parameters():
                p.normal_(0.0, 0.3 if p.ndim > 1 else 0.1)
    return vae


def _video(t: int, h: int = 16, w: int = 16, b: int = 1, seed: int = 1) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(b, 3, t, h, w, generator=g) * 2 - 1


@pytest.mark.parametrize("t, n", [(1, 1), (5, 2), (9, 3)])
@pytest.mark.slow
def test_shapes(t, n):
    vae = _vae()
    video = _video(t, 16, 24, b=2)
    mean, logvar = vae.encode(video)
    assert mean.shape == logvar.shape == (2, 4, n, 2, 3)
    recon = vae.decode(mean)
    assert recon.shape == video.shape
    out, m2, lv2 = vae(video, sample_posterior=False)
    assert out.shape == video.shape and torch.equal(m2, mean) and torch.equal(lv2, logvar)
    assert vae.config.num_latent_frames(t) == n and vae.config.num_frames(n) == t


@pytest.mark.slow
def test_encoder_is_exactly_causal_per_group():
    # Frame j belongs to latent group ⌈j/4⌉ (group 0 = frame 0, group 1 = frames 1–4, group 2 = frames 5–8).
    vae = _vae(2, randomize=True)
    video = _video(9)
    with torch.no_grad():
        base, _ = vae.encode(video)
        for j in range(9):
            changed = video.clone()
            changed[:, :, j] = torch.rand(3, 16, 16) * 2 - 1
            mean, _ = vae.encode(changed)
            group = (j + 3) // 4
            assert torch.equal(mean[:, :, :group], base[:, :, :group]), f"frame {j} leaked into earlier latents"
            assert (mean[:, :, group] - base[:, :, group]).abs().max() > 1e-4, f"frame {j} ignored by its group"


def test_convolutions_and_upsampling_above_the_kernel_limit_run_on_windows_of_frames(monkeypatch):
    """Above MAX_KERNEL_ELEMENTS per sample (2³¹ − 1: the paper decoder's last stage) the causal convolutions and
    the 2× upsampling run on windows of frames, each call under the limit, and give the values of one call: the
    whole encode and decode, with the limit lowered to a few frames' worth, against the plain run."""
    vae = _vae(5, randomize=True)
    x = _video(9, b=2)
    calls = []
    conv3d = nn.Conv3d.forward
    monkeypatch.setattr(nn.Conv3d, "forward", lambda self, t: calls.append(t.shape[2]) or conv3d(self, t))
    with torch.no_grad():
        ref = vae.decode(vae.encode(x)[0])
        plain = len(calls)
        monkeypatch.setattr(models.vae, "MAX_KERNEL_ELEMENTS", 3000)  # below one frame of most layers
        got = vae.decode(vae.encode(x)[0])
    torch.testing.assert_close(got, ref, atol=1e-5, rtol=1e-5)
    windows = calls[plain:]
    assert len(windows) > 2 * plain and windows.count(3) > plain  # windows of one frame and the 2 before it
    for mode in ("nearest", "bilinear"):
        frames = torch.randn(1, 8, 9, 4, 4)
        monkeypatch.setattr(models.vae, "MAX_KERNEL_ELEMENTS", 2**31 - 1)
        whole = upsample2x(frames, mode)
        monkeypatch.setattr(models.vae, "MAX_KERNEL_ELEMENTS", 2 * 4 * 8 * 16)  # two frames per call
        assert torch.equal(upsample2x(frames, mode), whole)


@pytest.mark.slow
def test_decoder_is_exactly_causal():
    vae = _vae(3, randomize=True)
    g = torch.Generator().manual_seed(0)
    z = torch.randn(1, 4, 3, 2, 2, generator=g)
    with torch.no_grad():
        base = vae.decode(z)
        for i in range(3):
            changed = z.clone()
            changed[:, :, i] += 1.0
            out = vae.decode(changed)
            first = 0 if i == 0 else 4 * i - 3  # first frame reconstructed from latent i
            assert torch.equal(out[:, :, :first], base[:, :, :first])
            assert (out[:, :, first] - base[:, :, first]).abs().max() > 1e-4


@pytest.mark.slow
def test_streaming_prefix_matches_and_first_frame_is_an_image():
    vae = _vae(4, randomize=True)
    video = _video(9)
    with torch.no_grad():
        full, _ = vae.encode(video)
        prefix, _ = vae.encode(video[:, :, :5])
        image, _ = vae.encode(video[:, :, :1])
    tol = 1e-6 * float(full.abs().max())  # float32 round-off of different-length convolutions
    torch.testing.assert_close(prefix, full[:, :, :2], atol=tol, rtol=0)
    torch.testing.assert_close(image, full[:, :, :1], atol=tol, rtol=0)


def test_building_blocks_against_references():
    # CausalConv3d = Conv3d on [frame0, frame0, x] (replicate past padding), zero spatial padding.
    torch.manual_seed(5)
    conv = CausalConv3d(2, 3)
    x = torch.randn(1, 2, 4, 5, 5)
    padded = torch.cat([x[:, :, :1], x[:, :, :1], x], dim=2)
    ref = nn.functional.conv3d(padded, conv.conv.weight, conv.conv.bias, padding=(0, 1, 1))
    assert torch.allclose(conv(x), ref, atol=1e-6)
    # FrameGroupNorm = GroupNorm of each frame separately.
    norm = FrameGroupNorm(2, 4)
    with torch.no_grad():
        norm.weight.normal_()
        norm.bias.normal_()
    v = torch.randn(2, 4, 3, 5, 5) * torch.tensor([1.0, 10.0, 100.0]).view(1, 1, 3, 1, 1)
    ref = torch.stack([nn.functional.group_norm(v[:, :, t], 2, norm.weight, norm.bias, norm.eps)
                       for t in range(3)], dim=2)
    assert torch.allclose(norm(v), ref, atol=1e-5)


@pytest.mark.slow
def test_posterior_sampling_and_logvar_clamp():
    vae = _vae(6)
    video = _video(5)
    mean, logvar = vae.encode(video)
    g1, g2 = torch.Generator().manual_seed(9), torch.Generator().manual_seed(9)
    z = vae.sample(mean, logvar, g1)
    eps = torch.randn(mean.shape, generator=g2)
    assert torch.allclose(z, mean + torch.exp(0.5 * logvar) * eps)
    big_m, big_lv = torch.full((4000,), 2.0), torch.full((4000,), 2 * torch.log(torch.tensor(0.5)))
    s = sample_posterior(big_m, big_lv, torch.Generator().manual_seed(0))
    assert abs(float(s.mean()) - 2.0) < 0.03 and abs(float(s.std()) - 0.5) < 0.03
    # Force the log-variance half of the encoder output to ±50 → clamped to 20 / −30.
    conv_out = vae.encoder.conv_out.conv
    with torch.no_grad():
        conv_out.weight.zero_()
        for value, expected in ((50.0, 20.0), (-50.0, -30.0)):
            conv_out.bias[4:] = value
            _, lv = vae.encode(video)
            assert torch.equal(lv, torch.full_like(lv, expected))


def test_kl_divergence_matches_torch_distributions():
    g = torch.Generator().manual_seed(7)
    mean = torch.randn(3, 4, 2, 2, 2, generator=g, dtype=torch.float64)
    logvar = torch.randn(3, 4, 2, 2, 2, generator=g, dtype=torch.float64)
    q = torch.distributions.Normal(mean, torch.exp(0.5 * logvar))
    p = torch.distributions.Normal(torch.zeros_like(mean), torch.ones_like(mean))
    ref = torch.distributions.kl_divergence(q, p).reshape(3, -1).sum(1)
    assert torch.allclose(kl_divergence(mean, logvar), ref, atol=1e-12)
    assert torch.equal(kl_divergence(torch.zeros(2, 5), torch.zeros(2, 5)), torch.zeros(2))
    with pytest.raises(ValueError, match="same"):
        kl_divergence(mean, logvar[:, :2])


@pytest.mark.slow
def test_scaling_helpers_invert_each_other():
    cfg = VideoVAEConfig(scaling_factor=0.5, shift_factor=0.25)
    torch.manual_seed(8)
    vae = VideoVAE(cfg).eval()
    video = _video(5)
    mean, _ = vae.encode(video)
    lat = vae.encode_latents(video)
    assert torch.allclose(lat, (mean - 0.25) * 0.5)
    assert torch.allclose(vae.decode_latents(lat), vae.decode(mean), atol=1e-6)
    z = torch.randn(10_000) * 3.0 + 1.5
    scale, shift = estimate_latent_scaling(z)
    normalised = (z - shift) * scale
    assert abs(float(normalised.mean())) < 1e-6 and abs(float(normalised.std()) - 1) < 1e-6
    with pytest.raises(ValueError, match="standard deviation"):
        estimate_latent_scaling(torch.ones(5))


def test_invalid_inputs_raise():
    vae = _vae()
    for t in (2, 4, 6, 8):
        with pytest.raises(ValueError, match="T="):
            vae.encode(_video(t))
    with pytest.raises(ValueError, match="multiples of 8"):
        vae.encode(_video(5, 12, 16))
    with pytest.raises(ValueError, match="multiples of 8"):
        vae.encode(_video(5, 16, 20))
    with pytest.raises(ValueError, match="video must have shape"):
        vae.encode(torch.zeros(1, 4, 5, 16, 16))
    with pytest.raises(ValueError, match="latents"):
        vae.decode(torch.zeros(1, 3, 2, 2, 2))
    with pytest.raises(ValueError, match="temporal_downsample"):
        VideoVAEConfig(temporal_downsample=(True, True))
    with pytest.raises(ValueError, match="norm_groups"):
        VideoVAEConfig(base_channels=6)


@pytest.mark.slow
def test_training_step_reduces_reconstruction_loss():
    # The tiny VAE can fit one small clip (5 frames, 8×8 → a 1×1×2 latent grid): Adam must cut the loss.
    torch.manual_seed(10)
    vae = VideoVAE(VideoVAEConfig()).train()
    t = torch.linspace(0, 1, 5).view(1, 1, 5, 1, 1)
    yy, xx = torch.meshgrid(torch.linspace(-1, 1, 8), torch.linspace(-1, 1, 8), indexing="ij")
    video = torch.cat([torch.sin(3 * xx + 2 * t), torch.cos(2 * yy - t), xx * yy * torch.ones_like(t)], dim=1)
    opt = torch.optim.Adam(vae.parameters(), lr=5e-3)
    losses = []
    for _ in range(20):
        recon, mean, logvar = vae(video, sample_posterior=False)
        loss = (recon - video).square().mean() + 1e-6 * kl_divergence(mean, logvar).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    assert losses[-1] < 0.3 * losses[0], losses


@pytest.mark.slow
def test_save_from_pretrained_round_trip(tmp_path):
    vae = _vae(11, randomize=True)
    vae.config.scaling_factor = 0.7
    vae.save_pretrained(tmp_path / "vae")
    loaded = VideoVAE.from_pretrained(tmp_path / "vae").eval()
    assert loaded.config == vae.config and isinstance(loaded.config.channel_mults, tuple)
    for k, v in vae.state_dict().items():
        assert torch.equal(v, loaded.state_dict()[k]), k
    video = _video(5)
    with torch.no_grad():
        assert torch.equal(vae.encode_latents(video), loaded.encode_latents(video))


def test_tiny_and_paper_parameter_counts():
    tiny = count_parameters(VideoVAE(VideoVAEConfig()))
    print(f"tiny VideoVAE parameters: {tiny:,}")
    assert 5_000 < tiny < 500_000
    with torch.device("meta"):
        paper = VideoVAE(VideoVAEConfig.paper())
        mean, _ = paper.encode(torch.empty(1, 3, 17, 64, 64))
    n = count_parameters(paper)
    print(f"paper VideoVAE parameters: {n:,} (encoder {count_parameters(paper.encoder):,})")
    assert mean.shape == (1, 16, 5, 8, 8)
    assert paper.config.latent_channels == PAPER_VIDEO_VAE["latent_channels"] == 16
    assert (paper.config.spatial_factor, paper.config.temporal_factor) == (8, 4)
    # Same order of magnitude as the Wan 2.1 VAE (127 M) it borrows widths from; ours has no attention.
    assert 5e7 < n < 3e8


def test_dc_ae_shortcuts_against_explicit_references():
    torch.manual_seed(7)
    x = torch.randn(2, 4, 5, 8, 8)  # T = 5 = 1 + 2·2
    # Down: frame 0 alone, then the means of frames (1, 2) and (3, 4); 2×2 spatial means.
    ref = torch.stack([x[:, :, 0], (x[:, :, 1] + x[:, :, 2]) / 2, (x[:, :, 3] + x[:, :, 4]) / 2], dim=2)
    ref = ref.reshape(2, 4, 3, 4, 2, 4, 2).mean((4, 6))
    torch.testing.assert_close(causal_mean_pool(x, True), ref)
    torch.testing.assert_close(causal_mean_pool(x, False), x.reshape(2, 4, 5, 4, 2, 4, 2).mean((4, 6)))
    # Up: frame 0 alone, every later frame twice (frames 2i − 1 and 2i come from latent i).
    z = torch.randn(1, 2, 3, 4, 4)
    torch.testing.assert_close(causal_repeat(z, True), z[:, :, [0, 1, 1, 2, 2]])
    # The blocks add exactly these paths to their convolutions: zero the convolutions to see them alone.
    down, up = Downsample(4, True), Upsample(4, True)
    with torch.no_grad():
        for m in (down, up):
            m.conv.conv.weight.zero_()
            m.conv.conv.bias.zero_()
    torch.testing.assert_close(down(x), causal_mean_pool(x, True))
    z4 = torch.randn(1, 4, 3, 4, 4)
    nearest = z4.repeat_interleave(2, dim=3).repeat_interleave(2, dim=4)
    torch.testing.assert_close(up(z4), causal_repeat(nearest, True))


@pytest.mark.slow
def test_bottleneck_shortcuts_average_and_duplicate_channels():
    vae = _vae(3)
    c, width = vae.config.latent_channels, vae.config.widths[-1]
    feats = {}
    vae.encoder.layers.register_forward_hook(lambda m, i, o: feats.setdefault("h", o))
    with torch.no_grad():
        vae.encoder.conv_out.conv.weight.zero_()
        vae.encoder.conv_out.conv.bias.zero_()
        mean, _ = vae.encode(_video(5))
    h = feats["h"]
    torch.testing.assert_close(mean, h.reshape(1, c, width // c, *h.shape[2:]).mean(2))  # groups of width/c
    z = torch.randn(1, c, 2, 2, 2)
    with torch.no_grad():
        vae.decoder.conv_in.conv.weight.zero_()
        vae.decoder.conv_in.conv.bias.zero_()
        seen = {}
        vae.decoder.layers.register_forward_pre_hook(lambda m, i: seen.setdefault("in", i[0]))
        vae.decode(z)
    torch.testing.assert_close(seen["in"], z.repeat_interleave(width // c, dim=1))


def test_shortcuts_can_be_switched_off_and_need_divisible_widths():
    off = VideoVAE(VideoVAEConfig(shortcuts=False))
    assert count_parameters(off) == count_parameters(VideoVAE(VideoVAEConfig()))  # parameter-free paths
    assert off.decode(torch.zeros(1, 4, 2, 2, 2)).shape == (1, 3, 5, 16, 16)
    with pytest.raises(ValueError, match="latent_channels=3 must divide"):
        VideoVAEConfig(latent_channels=3)
    VideoVAEConfig(latent_channels=3, shortcuts=False)  # no channel averaging: any count


def test_upsample2x_against_closed_forms():
    """nearest copies each value into 2×2; bilinear (half-pixel centres) gives 3/4 of the nearer and 1/4 of the
    farther input per axis, edges clamped; frames never mix; an unknown mode raises."""
    x = torch.randn(2, 3, 4, 5, 6, generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(upsample2x(x, "nearest"), x.repeat_interleave(2, 3).repeat_interleave(2, 4))

    def axis(v: torch.Tensor, dim: int) -> torch.Tensor:  # 1D half-pixel linear 2× along dim
        n = v.shape[dim]
        prev = v.index_select(dim, torch.tensor([0, *range(n - 1)]))
        nxt = v.index_select(dim, torch.tensor([*range(1, n), n - 1]))
        even, odd = 0.75 * v + 0.25 * prev, 0.75 * v + 0.25 * nxt  # outputs 2i and 2i + 1
        return torch.stack([even, odd], dim + 1).flatten(dim, dim + 1)

    torch.testing.assert_close(upsample2x(x, "bilinear"), axis(axis(x, 3), 4))
    with pytest.raises(ValueError, match="mode must be one of"):
        upsample2x(x, "bicubic")
    with pytest.raises(ValueError, match="upsample must be one of"):
        VideoVAEConfig(upsample="bicubic")


@pytest.mark.slow
def test_bilinear_decoder_has_no_8x8_blocks_where_nearest_has():
    """The same random weights decoding the same random latents: with nearest upsampling the shortcuts copy every
    latent pixel into its own 8×8 block (the border/inside ratio of squared neighbour differences ≫ 1); with
    bilinear upsampling the borders are like anywhere else. The weights are the same tensors either way."""
    z = torch.randn(2, 4, 2, 4, 4, generator=torch.Generator().manual_seed(3))
    ratios = {}
    for mode in ("nearest", "bilinear"):
        torch.manual_seed(0)
        vae = VideoVAE(VideoVAEConfig(upsample=mode)).eval()
        with torch.no_grad():
            ratios[mode] = blockiness(vae.decode(z), 8)
    assert ratios["nearest"] > 2.0 and ratios["bilinear"] < 1.3, ratios
    a, b = VideoVAE(VideoVAEConfig()), VideoVAE(VideoVAEConfig(upsample="bilinear"))
    assert a.state_dict().keys() == b.state_dict().keys()
    assert all(v.shape == b.state_dict()[k].shape for k, v in a.state_dict().items())
