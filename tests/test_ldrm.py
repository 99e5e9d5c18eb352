"""Tests of models/ldrm.py: shapes, activations, validation, export, layering."""
from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import onnxruntime as ort
import pytest
import torch

from diff4splat.cameras import pack_plucker, plucker_rays
from diff4splat.scene.quaternions import axis_angle_to_quat, quat_to_rotmat
from models.deformation import DeformationConfig
from models.ldrm import (
    LDRM,
    LDRMConfig,
    LDRMOutput,
    gaussian_activations,
    sincos_position_3d,
    source_frame_indices,
)
from models.pretrained import count_parameters

IDENTITY = torch.tensor([1.0, 0.0, 0.0, 0.0])
H = W = 64
T = 9  # → n = 3 latent frames
S = 3  # source frames 0, 4, 8 (gaussian_frames "latent")


def _cameras(T: int = T):
    """A short orbit-like path: camera i rotated about y by 2° per frame and shifted along x."""
    Ks = torch.tensor([[60.0, 0.0, 32.0], [0.0, 55.0, 30.0], [0.0, 0.0, 1.0]]).expand(T, 3, 3)
    angles = torch.arange(T, dtype=torch.float32) * math.radians(2.0)
    R = quat_to_rotmat(axis_angle_to_quat(torch.tensor([0.0, 1.0, 0.0]).expand(T, 3), angles))
    viewmats = torch.eye(4).repeat(T, 1, 1)
    viewmats[:, :3, :3] = R
    viewmats[:, :3, 3] = torch.stack([-0.05 * torch.arange(T, dtype=torch.float32), torch.zeros(T), torch.zeros(T)], -1)
    return viewmats, Ks


def _inputs(seed: int = 0, channels: int = 4):
    g = torch.Generator().manual_seed(seed)
    viewmats, Ks = _cameras()
    plucker = pack_plucker(plucker_rays(viewmats, Ks, W, H)[None])  # (1, 1536, 3, 8, 8)
    latents = torch.randn(1, channels, 3, H // 8, W // 8, generator=g)
    return latents, plucker


def _model(seed: int = 0, **kw) -> LDRM:
    torch.manual_seed(seed)
    return LDRM(LDRMConfig(**kw))


def test_shapes_finite_and_ranges():
    model = _model()
    latents, plucker = _inputs()
    assert plucker.shape == (1, 1536, 3, 8, 8)
    out = model(latents, plucker, torch.linspace(0, 1, T))
    cfg = model.config
    assert out.distance.shape == (1, S, H, W) and out.opacities.shape == (1, S, H, W)
    assert out.scales.shape == (1, S, H, W, 3) and out.colors.shape == (1, S, H, W, 3)
    assert out.quats.shape == (1, S, H, W, 4)
    assert out.d_means.shape == (1, T, S, H, W, 3) and out.d_quats.shape == (1, T, S, H, W, 4)
    assert out.d_scales.shape == (1, T, S, H, W, 3)
    for name, value in vars(out).items():
        assert torch.isfinite(value).all(), name
    assert cfg.depth_min <= out.distance.min() and out.distance.max() <= cfg.depth_max
    assert (out.scales > 0).all() and ((out.opacities >= 0) & (out.opacities <= 1)).all()
    assert ((out.colors >= 0) & (out.colors <= 1)).all()
    torch.testing.assert_close(out.quats.norm(dim=-1), torch.ones(1, S, H, W))
    assert out.distance.std() > 0, "per-pixel maps must vary across pixels"


def test_patch_size_two_and_batch():
    model = _model(patch_size=2)
    latents, plucker = _inputs()
    out = model(latents.repeat(2, 1, 1, 1, 1), plucker.repeat(2, 1, 1, 1, 1), torch.tensor([0.0, 1.0]))
    assert out.distance.shape == (2, S, H, W) and out.d_means.shape == (2, 2, S, H, W, 3)
    torch.testing.assert_close(out.distance[0], out.distance[1])


def test_identity_deformation_at_init_exact():
    out = _model()(*_inputs(), torch.linspace(0, 1, T))
    assert torch.equal(out.d_means, torch.zeros_like(out.d_means))
    assert torch.equal(out.d_quats, IDENTITY.expand_as(out.d_quats))
    assert torch.equal(out.d_scales, torch.zeros_like(out.d_scales))


def test_perturbed_deformation_varies_with_time():
    model = _model()
    with torch.no_grad():
        model.deformation.out_conv.weight.normal_(0.0, 0.5)
    out = model(*_inputs(), torch.tensor([0.0, 0.5, 1.0]))
    assert out.d_means.abs().max() > 1e-3
    assert (out.d_means[:, 0] - out.d_means[:, 2]).abs().max() > 1e-4
    assert (out.d_quats[:, 0] - out.d_quats[:, 1]).abs().max() > 1e-4
    assert (out.d_scales[:, 1] - out.d_scales[:, 2]).abs().max() > 1e-4


@pytest.mark.slow
def test_static_scene_skips_deformation_network():
    model = _model()
    calls = []
    model.deformation.register_forward_hook(lambda *args: calls.append(1))
    out = model(*_inputs(), None)
    assert calls == [] and out.d_means is None and out.d_quats is None and out.d_scales is None
    model(*_inputs(), torch.tensor([0.5]))
    assert calls == [1]


def test_reference_frame_uses_other_frames():
    """Frame-0 maps depend on later latent frames through attention over all tokens."""
    model = _model()
    latents, plucker = _inputs()
    base = model(latents, plucker).distance[:, 0]
    changed = latents.clone()
    changed[:, :, 2] += 1.0
    assert (model(changed, plucker).distance[:, 0] - base).abs().max() > 1e-5


def _identity_blocks(model: LDRM) -> LDRM:
    """Zero every block's residual branches so each token is its own embedding (no attention mixing)."""
    with torch.no_grad():
        for block in model.blocks:
            for layer in (block.attn.proj, block.mlp.fc2):
                layer.weight.zero_()
                layer.bias.zero_()
    return model


def _poked(model: LDRM, r: int, c: int):
    """For each latent frame s: where (S, H, W) the distance maps change when latent pixel (r, c) of frame s moves."""
    latents, plucker = _inputs()
    base = model(latents, plucker).distance[0]
    for s in range(S):
        poked = latents.clone()
        poked[:, :, s, r, c] += 1.0
        yield (model(poked, plucker).distance[0] - base).abs() > 0


@pytest.mark.parametrize("patch", [1, 2])
@pytest.mark.slow
def test_deconv_head_reads_each_source_frame_patch_locally(patch):
    """With every block an identity, pixel (i, j) of source frame s depends only on the latent pixels of its
    own patch in latent frame s: checks patchify order, the source-frame layout and the transposed convolution."""
    size = 8 * patch
    r, c = 5, 2
    for s, diff in enumerate(_poked(_identity_blocks(_model(patch_size=patch, head="deconv")), r, c)):
        expect = torch.zeros(S, H, W, dtype=torch.bool)
        r0, c0 = (r // patch) * size, (c // patch) * size
        expect[s, r0:r0 + size, c0:c0 + size] = True
        assert torch.equal(diff, expect), s


@pytest.mark.parametrize("patch", [1, 2])
@pytest.mark.slow
def test_upsample_head_overlaps_neighbouring_tokens_within_its_receptive_field(patch):
    """The upsampling head: a poked token changes its own f×f block (f = 8p) and, unlike the transposed
    convolution, pixels of the neighbouring blocks — but nothing in other source frames and nothing beyond the
    closed-form receptive field: a 3×3 conv at scale 2^k adds f/2^k output pixels per side, the last one 1 pixel,
    so f + f/2 + … + 2 + 1 = 2f − 1 pixels around the block."""
    f = 8 * patch
    r, c = 5, 2
    for s, diff in enumerate(_poked(_identity_blocks(_model(patch_size=patch)), r, c)):
        r0, c0 = (r // patch) * f, (c // patch) * f
        inside = torch.zeros(S, H, W, dtype=torch.bool)
        inside[s, max(0, r0 - 2 * f + 1):r0 + 3 * f - 1, max(0, c0 - 2 * f + 1):c0 + 3 * f - 1] = True
        assert not (diff & ~inside).any(), s
        assert diff[s, r0:r0 + f, c0:c0 + f].all(), s
        assert diff[s, r0 + f:r0 + f + f // 2, c0:c0 + f].any(), "no overlap with the next block down"
        assert diff[s, r0 - f:r0, c0:c0 + f].any(), "no overlap with the block above"


@pytest.mark.parametrize("head", ["upsample", "deconv"])
def test_features_and_head_maps_are_the_forward_before_activation(head):
    """forward = gaussian_activations of head_maps(features(·)) (no image branch); features is the token volume
    (B, D, n, h, w) and head_maps gives (B, 12, S, H, W)."""
    model = _model(head=head)
    latents, plucker = _inputs()
    volume = model.features(latents, plucker)
    assert volume.shape == (1, model.config.embed_dim, 3, H // 8, W // 8)
    raw = model.head_maps(volume)
    assert raw.shape == (1, 12, S, H, W)
    out = model(latents, plucker)
    for got, want in zip(gaussian_activations(raw.permute(0, 2, 3, 4, 1), model.config),
                         (out.distance, out.scales, out.quats, out.opacities, out.colors), strict=True):
        torch.testing.assert_close(got, want)


def test_source_frame_indices_closed_form():
    assert source_frame_indices("latent", 5) == [0, 4, 8, 12, 16]
    assert source_frame_indices("all", 3) == list(range(9))
    assert source_frame_indices("reference", 5) == [0]
    assert source_frame_indices("latent", 1) == [0] == source_frame_indices("all", 1)
    with pytest.raises(ValueError, match="gaussian_frames"):
        source_frame_indices("every", 3)
    with pytest.raises(ValueError, match="gaussian_frames"):
        LDRMConfig(gaussian_frames="every")
    with pytest.raises(ValueError, match="image_branch"):
        LDRMConfig(image_branch=-1)
    with pytest.raises(ValueError, match="head"):
        LDRMConfig(head="pixelshuffle")
    with pytest.raises(ValueError, match="gaussian_frames 'all'"):
        LDRMConfig(gaussian_frames="all")  # the upsampling head decodes latent frames; "all" needs "deconv"
    with pytest.raises(ValueError, match="power of two"):
        LDRMConfig(vae_spatial=6)
    with pytest.raises(ValueError, match="head_channels"):
        LDRMConfig(head_channels=0)


@pytest.mark.slow
def test_all_frames_mode_maps_each_frame_to_its_latent_frame():
    """gaussian_frames="all": S = T grids; video frame f reads latent frame ⌈f/4⌉ (causal: frame 0 alone in
    latent frame 0, frames 1–4 in latent frame 1, …), and its deformation is that latent frame's."""
    model = _identity_blocks(_model(gaussian_frames="all", head="deconv"))
    with torch.no_grad():
        model.deformation.out_conv.weight.normal_(0.0, 0.5)
    latents, plucker = _inputs()
    out = model(latents, plucker, torch.tensor([0.0, 1.0]))
    assert out.distance.shape == (1, T, H, W) and out.d_means.shape == (1, 2, T, H, W, 3)
    owner = [-(-f // 4) for f in range(T)]
    assert owner == [0, 1, 1, 1, 1, 2, 2, 2, 2]
    for f in range(T):  # frames of one latent frame share its deformation map
        torch.testing.assert_close(out.d_means[0, :, f], out.d_means[0, :, 4 * owner[f]], atol=0, rtol=0)
    poked = latents.clone()
    poked[:, :, 1] += 1.0
    changed = (model(poked, plucker).distance[0] - out.distance[0]).flatten(1).abs().amax(1) > 0
    assert changed.tolist() == [o == 1 for o in owner]


def test_reference_mode_one_grid():
    out = _model(gaussian_frames="reference")(*_inputs(), torch.tensor([0.5]))
    assert out.distance.shape == (1, 1, H, W) and out.d_means.shape == (1, 1, 1, H, W, 3)


def test_image_branch_zero_init_then_reads_the_photo_for_frame_0_only():
    latents, plucker = _inputs()
    image = torch.rand(1, 3, H, W, generator=torch.Generator().manual_seed(1)) * 2 - 1
    plain = _model()
    branched = _model(image_branch=8)
    missing = branched.load_state_dict(plain.state_dict(), strict=False).missing_keys
    assert missing and all(k.startswith("image_branch.") for k in missing)
    a, b = plain(latents, plucker), branched(latents, plucker, image=image)
    for name in ("distance", "scales", "quats", "opacities", "colors"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name  # zero-init: exactly the plain LDRM
    with torch.no_grad():
        branched.image_branch.out.weight.normal_(0.0, 0.3)
    c, d = branched(latents, plucker, image=image), branched(latents, plucker, image=-image)
    assert (c.colors[:, 0] - d.colors[:, 0]).abs().max() > 1e-3, "frame 0 reads the photo"
    assert torch.equal(c.colors[:, 1:], d.colors[:, 1:]), "later source frames do not"
    with pytest.raises(ValueError, match="image"):
        branched(latents, plucker)
    with pytest.raises(ValueError, match="image"):
        branched(latents, plucker, image=image[..., :32, :])


def test_activations_at_zero_give_defaults():
    cfg = LDRMConfig()
    d, s, q, o, c = gaussian_activations(torch.zeros(5, 12), cfg)
    torch.testing.assert_close(d, torch.full((5,), cfg.default_depth))
    torch.testing.assert_close(s, torch.full((5, 3), cfg.default_depth * cfg.scale_base))
    assert torch.equal(q, IDENTITY.expand(5, 4))
    assert torch.equal(o, torch.full((5,), 0.5)) and torch.equal(c, torch.full((5, 3), 0.5))


def test_activations_extremes_and_monotone():
    cfg = LDRMConfig()
    raw = torch.cat([torch.full((1, 12), 1e4), torch.full((1, 12), -1e4),
                     torch.tensor([[1e4, -1e4] * 6]), torch.tensor([[-1e4, 1e4] * 6])])
    d, s, q, o, c = gaussian_activations(raw, cfg)
    for x in (d, s, q, o, c):
        assert torch.isfinite(x).all()
    lo, hi = cfg.depth_min * (1 - 1e-5), cfg.depth_max * (1 + 1e-5)
    assert ((d >= lo) & (d <= hi)).all()
    torch.testing.assert_close(d[:2], torch.tensor([cfg.depth_max, cfg.depth_min]))
    bound = math.exp(cfg.scale_log_range) * 1.0001
    ratio = s / (d[:, None] * cfg.scale_base)
    assert (s > 0).all() and (ratio <= bound).all() and (ratio >= 1 / bound).all()
    torch.testing.assert_close(q.norm(dim=-1), torch.ones(4))
    assert ((o >= 0) & (o <= 1)).all() and ((c >= 0) & (c <= 1)).all()
    ramp = torch.zeros(50, 12)
    ramp[:, 0] = torch.linspace(-8, 8, 50)
    depth = gaussian_activations(ramp, cfg)[0]
    assert (depth.diff() > 0).all(), "distance increases with its raw channel"


@pytest.mark.slow
def test_ldrm_returns_tensors_and_imports_no_pipeline_layer():
    """Layering: the network module builds no Gaussians; turning its maps into a scene is the pipeline's
    job (``diff4splat.assembly.assemble.to_gaussians``), and importing it loads no pipeline-layer module."""
    code = ("import sys, models.ldrm as m; "
            "bad = [k for k in sys.modules if k.split('.')[:2] in (['diff4splat', 'pipeline'], ['diff4splat', 'cli'], "
            "['diff4splat', 'export'], ['diff4splat', 'onnx_runtime'])]; "
            "assert not bad, bad; "
            "assert not hasattr(m, 'to_gaussians') and not hasattr(m, 'Gaussians'), 'models.ldrm builds Gaussians'; "
            "assert not hasattr(m.LDRM, 'to_gaussians')")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr


def test_validation_errors():
    model = _model()
    latents, plucker = _inputs()
    with pytest.raises(ValueError, match="latents"):
        model(latents[0], plucker)
    with pytest.raises(ValueError, match="latents"):
        model(torch.randn(1, 5, 3, 8, 8), plucker)
    with pytest.raises(ValueError, match="plucker"):
        model(latents, plucker[:, :, :2])  # fewer frames → mismatched token counts
    with pytest.raises(ValueError, match="plucker"):
        model(latents, plucker[:, :, :, :4])
    with pytest.raises(ValueError, match="plucker"):
        model(latents, plucker[:, :768])
    with pytest.raises(ValueError, match="times"):
        model(latents, plucker, torch.tensor([0.0, 1.5]))
    with pytest.raises(ValueError, match="times"):
        model(latents, plucker, torch.tensor([-0.1]))
    with pytest.raises(ValueError, match="times"):
        model(latents, plucker, torch.tensor([[0.5]]))
    with pytest.raises(ValueError, match="patch_size"):
        _model(patch_size=3)(latents, plucker)
    with pytest.raises(ValueError, match="in_channels"):
        LDRMConfig(embed_dim=32)  # deformation.in_channels stays 64
    with pytest.raises(ValueError, match="default_depth"):
        LDRMConfig(default_depth=200.0)


def test_position_embedding_unique_and_closed_form():
    pe = sincos_position_3d(3, 4, 5, 64)
    assert pe.shape == (60, 64)
    assert torch.cdist(pe, pe).add(torch.eye(60) * 10).min() > 1e-3, "every token position is distinct"
    # token (frame 2, row 1, col 3): first frame channel is sin(2·ω₀) = sin(2); d_t = 24, d_s = 20
    idx = 2 * 20 + 1 * 5 + 3
    assert math.isclose(float(pe[idx, 0]), math.sin(2.0), rel_tol=1e-6)
    assert math.isclose(float(pe[idx, 24]), math.sin(1.0), rel_tol=1e-6)
    assert math.isclose(float(pe[idx, 44]), math.sin(3.0), rel_tol=1e-6)
    assert math.isclose(float(pe[idx, 44 + 10]), math.cos(3.0), rel_tol=1e-6)
    # in bfloat16 (the LDRM's latents with bfloat16 weights): the float64 values rounded once, at the paper's
    # 13 × 32 × 32 token grid (computed in bfloat16 the angles were off by up to 0.03)
    ref = sincos_position_3d(13, 32, 32, 96, dtype=torch.float64)
    bf16 = sincos_position_3d(13, 32, 32, 96, dtype=torch.bfloat16)
    assert bf16.dtype == torch.bfloat16 and torch.equal(bf16, ref.to(torch.bfloat16))


@pytest.mark.slow
def test_gradients_reach_every_parameter_with_its_strides():
    """Every parameter gets a non-zero gradient laid out as the parameter is (the layout DDP's gradient buckets
    assume: the deformation network's 1×1 out_conv, fed channels-last token features, once got (F, 1, F, F)
    strides for its (10, F, 1, 1) weight and DDP warned on every run)."""
    model = _model()
    with torch.no_grad():
        model.deformation.out_conv.weight.normal_(0.0, 0.3)
    latents, plucker = _inputs()
    latents = latents[..., :4, :4]
    plucker = plucker[..., :4, :4]
    out = model(latents, plucker, torch.tensor([0.2, 0.8]))
    g = torch.Generator().manual_seed(3)
    loss = sum((v * torch.randn(v.shape, generator=g)).sum() for v in vars(out).values())
    loss.backward()
    for name, p in model.named_parameters():
        assert p.grad is not None and p.grad.abs().sum() > 0, f"no gradient for {name}"
        assert p.grad.stride() == p.stride(), (name, p.grad.stride(), p.stride())


@pytest.mark.slow
def test_save_load_round_trip(tmp_path):
    model = _model(patch_size=2, deformation=DeformationConfig(hidden=8, levels=2))
    with torch.no_grad():
        model.deformation.out_conv.weight.normal_(0.0, 0.3)
    inputs = (*_inputs(), torch.tensor([0.0, 1.0]))
    model.save_pretrained(tmp_path / "ldrm")
    loaded = LDRM.from_pretrained(tmp_path / "ldrm")
    assert loaded.config == model.config and isinstance(loaded.config.deformation, DeformationConfig)
    a, b = model(*inputs), loaded(*inputs)
    for name in vars(a):
        assert torch.equal(getattr(a, name), getattr(b, name)), name


def test_paper_config_on_meta():
    cfg = LDRMConfig.paper()
    with torch.device("meta"):
        model = LDRM(cfg)
    n = count_parameters(model)
    tiny = count_parameters(LDRM(LDRMConfig()))
    D = cfg.embed_dim
    per_block = 2 * 2 * D + (3 * D * D + 3 * D) + (D * D + D) + (4 * D * D + 4 * D) + (4 * D * D + D)
    assert count_parameters(model.blocks) == cfg.depth * per_block
    assert cfg.depth == 16 and cfg.embed_dim == 64 and cfg.latent_channels == 16
    assert count_parameters(model.embed) == (16 + 1536) * 4 * D + D
    print(f"LDRM parameters: paper {n:,} (meta), tiny {tiny:,}")
    assert tiny < 400_000 < n


@pytest.mark.slow
def test_onnx_export_matches_eager(tmp_path):
    torch.manual_seed(0)
    model = _model().eval()
    with torch.no_grad():
        model.deformation.out_conv.weight.normal_(0.0, 0.3)
    latents, plucker = _inputs()
    latents, plucker = latents[..., :4, :4], plucker[..., :4, :4]
    times = torch.tensor([0.0, 0.5, 1.0])
    path = tmp_path / "ldrm.onnx"
    torch.onnx.export(model, (latents, plucker, times), str(path), dynamo=True, opset_version=18, verbose=False)
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    feeds = {i.name: x.numpy() for i, x in zip(session.get_inputs(), (latents, plucker, times), strict=True)}
    got = session.run(None, feeds)
    with torch.no_grad():
        ref = model(latents, plucker, times)
    names = ["distance", "scales", "quats", "opacities", "colors", "d_means", "d_quats", "d_scales"]
    assert len(got) == len(names)
    for name, value in zip(names, got, strict=True):
        np.testing.assert_allclose(value, getattr(ref, name).numpy(), atol=1e-4, rtol=1e-4, err_msg=name)
    assert isinstance(ref, LDRMOutput)


def test_checkpoint_without_gaussian_frames_loads_as_reference(tmp_path):
    """A config.json written before every-frame decoding and the upsampling head existed keeps its meaning:
    frame 0 only, through the transposed convolution its weights were trained with."""
    model = _model(head="deconv")
    model.save_pretrained(tmp_path / "ldrm")
    path = tmp_path / "ldrm" / "config.json"
    data = json.loads(path.read_text())
    assert data.pop("gaussian_frames") == "latent" and data.pop("head") == "deconv"
    path.write_text(json.dumps(data))
    old = LDRM.from_pretrained(tmp_path / "ldrm")
    assert old.config.gaussian_frames == "reference" and old.config.head == "deconv"
    out = old(*_inputs())
    assert out.distance.shape == (1, 1, H, W)
    torch.testing.assert_close(out.distance[:, 0], model(*_inputs()).distance[:, 0], atol=0, rtol=0)
