"""Tests for models/backbones/cogvideox.py on a tiny random CogVideoX-I2V (tests/tiny_cogvideox.py): the velocity
is diffusers' transformer output converted by vpred_to_flow, our Euler sampler reproduces the diffusers pipeline's
DDIM latents, and the Hub folder round trip."""
from __future__ import annotations

import shutil

import pytest
import torch

pytest.importorskip("diffusers", reason="the CogVideoX backbone needs diff4splat[diffusers]")

from diffusers import (  # noqa: E402
    CogVideoXDDIMScheduler,
    CogVideoXImageToVideoPipeline,
    CogVideoXTransformer3DModel,
    DDIMScheduler,
)
from safetensors import safe_open  # noqa: E402
from tiny_cogvideox import (  # noqa: E402
    FRAMES,
    HEIGHT,
    SCHEDULER,
    TEXT_LENGTH,
    WIDTH,
    tiny_backbone,
    tiny_components,
    tiny_inputs,
    write_tiny_folder,
)
from torch import nn  # noqa: E402

from models.backbone import LatentFormat  # noqa: E402
from models.backbones.cogvideox import CogVideoXBackbone, vpred_to_flow  # noqa: E402
from models.flow_matching import euler_sample  # noqa: E402

PROMPT = "a cat"

pytestmark = [pytest.mark.usefixtures("one_thread"),  # tests/conftest.py: tiny tensors
              pytest.mark.slow]  # every test here: diffusers costs ~8 s to import (tests/conftest.py)


@pytest.fixture(scope="module")
def backbone():
    return tiny_backbone(seed=0)


def _reference_velocity(backbone, x, t, image_latent, text):
    """What diffusers itself computes at timestep t (the transformer with its own patch embedding, called as
    CogVideoXImageToVideoPipeline.__call__ calls it), converted to ε − x0 with ᾱ_t from a fresh scheduler."""
    abar = CogVideoXDDIMScheduler(**SCHEDULER).alphas_cumprod[t]
    alpha, s = abar ** 0.5, (1 - abar) ** 0.5
    x_t = (alpha + s).float().view(-1, 1, 1, 1, 1) * x
    b, c, n, h, w = x.shape
    latents = x_t.permute(0, 2, 1, 3, 4)  # (B, F, C, H, W)
    image_latents = torch.cat([image_latent.permute(0, 2, 1, 3, 4), latents.new_zeros(b, n - 1, c, h, w)], dim=1)
    with backbone.hub_transformer() as transformer:
        assert type(transformer.patch_embed.proj) is nn.Conv2d
        pipe = backbone.pipeline()
        rotary = pipe._prepare_rotary_positional_embeddings(HEIGHT, WIDTH, n, x.device)
        v = transformer(hidden_states=torch.cat([latents, image_latents], dim=2), encoder_hidden_states=text,
                        timestep=t, ofs=None, image_rotary_emb=rotary, return_dict=False)[0].float()
    return vpred_to_flow(x_t, v.permute(0, 2, 1, 3, 4), alpha, s)


# ---------------------------------------------------------------------------------------------- construction


def test_latent_format_camera_conv_and_names(backbone):
    assert backbone.kind == "cogvideox-i2v"
    assert backbone.latent == LatentFormat(4, 4, 8)
    assert backbone.latent.camera_channels == 6 * 4 * 8 ** 2
    cam = backbone.camera_conv
    assert cam.in_channels == 8 and cam.camera_weight.shape == (32, 6 * 4 * 64, 2, 2)
    assert not cam.camera_weight.any()
    assert backbone.max_sequence_length == TEXT_LENGTH
    assert CogVideoXImageToVideoPipeline.__name__ in CogVideoXBackbone.pipeline_names
    assert len(backbone.transformer_blocks()) == 1


def test_refuses_cogvideox_15_and_non_v_prediction_schedulers():
    parts = tiny_components()
    parts["transformer"] = CogVideoXTransformer3DModel(
        num_attention_heads=2, attention_head_dim=16, in_channels=8, out_channels=4, time_embed_dim=2,
        text_embed_dim=32, num_layers=1, sample_width=2, sample_height=2, sample_frames=9, patch_size=2,
        patch_size_t=2, max_text_seq_length=TEXT_LENGTH, use_rotary_positional_embeddings=True)
    with pytest.raises(ValueError, match="CogVideoX 1.5"):
        CogVideoXBackbone(**parts)
    parts = tiny_components()
    parts["scheduler"] = DDIMScheduler()  # epsilon prediction
    with pytest.raises(ValueError, match="v-prediction"):
        CogVideoXBackbone(**parts)


# ---------------------------------------------------------------------------------------------- (a) velocity


def test_velocity_is_the_diffusers_transformer_converted_by_vpred_to_flow(backbone):
    inp = tiny_inputs(backbone, batch=3)
    text, mask = backbone.encode_text([PROMPT, "", "a dog runs"])
    assert text.shape == (3, TEXT_LENGTH, 32) and mask.dtype == torch.bool and mask.all()
    t = torch.tensor([999, 499, 20])
    sigma = backbone.sigmas(1000)[:-1].flip(0)[t].float()  # σ_t as float32
    with torch.no_grad():
        ours = backbone(inp["x"], sigma, inp["image_latent"], inp["plucker"], text, mask)
        ref = _reference_velocity(backbone, inp["x"], t, inp["image_latent"], text)
    assert ours.dtype == torch.float32 and ours.shape == inp["x"].shape
    assert (ours - ref).abs().max().item() <= 1e-6


def test_camera_weights_change_the_velocity_and_text_none_is_the_empty_prompt(backbone):
    inp = tiny_inputs(backbone, batch=2, seed=1)
    sigma = torch.tensor([0.8, 0.3])
    with torch.no_grad():
        empty, mask = backbone.encode_text(["", ""])
        base = backbone(inp["x"], sigma, inp["image_latent"], inp["plucker"], empty, mask)
        assert torch.equal(backbone(inp["x"], sigma, inp["image_latent"], inp["plucker"], None, None), base)
        cam = tiny_backbone(seed=0, camera_std=0.05)
        moved = cam(inp["x"], sigma, inp["image_latent"], inp["plucker"], empty, mask)
    assert (moved - base).abs().max().item() > 1e-3


@pytest.fixture
def cpu_case(backbone):
    """velocity's inputs, built before ``no_implicit_device`` makes the meta device the default."""
    inp = tiny_inputs(backbone, batch=2)
    with torch.no_grad():
        text, mask = backbone.encode_text([PROMPT, ""])
    return dict(inp, sigma=torch.tensor([0.7, 0.1]), text=text, text_mask=mask)


def test_velocity_makes_every_tensor_on_its_inputs_device(backbone, cpu_case, no_implicit_device):
    with torch.no_grad():
        v = backbone(**cpu_case)
    assert v.device.type == "cpu" and torch.isfinite(v).all()


def test_invert_scale_latents_divides_the_image_latent_by_scaling_factor_squared():
    bb = tiny_backbone(seed=0)
    inp = tiny_inputs(bb)
    sigma = torch.tensor([0.6])
    sf = bb.vae.config.scaling_factor
    with torch.no_grad():
        plain = bb(inp["x"], sigma, inp["image_latent"] / sf ** 2, inp["plucker"], None, None)
        bb.vae.register_to_config(invert_scale_latents=True)
        inverted = bb(inp["x"], sigma, inp["image_latent"], inp["plucker"], None, None)
    assert (inverted - plain).abs().max().item() <= 1e-6


def test_velocity_rejects_bad_shapes_and_sizes_other_than_the_learned_embeddings(backbone):
    inp = tiny_inputs(backbone)
    with pytest.raises(ValueError, match="sigma must have shape"):
        backbone(inp["x"], torch.tensor([0.5, 0.5]), inp["image_latent"], inp["plucker"], None, None)
    big = {k: torch.zeros(*v.shape[:3], 4, 4) for k, v in inp.items()}
    with pytest.raises(ValueError, match="learned positional embeddings"):
        backbone(big["x"], torch.tensor([0.5]), big["image_latent"], big["plucker"], None, None)


# ---------------------------------------------------------------------------------------------- DDIM ≡ Euler


def test_vpred_to_flow_and_a_ddim_step_is_an_euler_step_in_closed_form():
    """x_t = αx0 + sε, v = αε − sx0: vpred_to_flow gives ε − x0, and diffusers' DDIM step t → t' equals the Euler
    step of dx/dσ = ε − x0 from σ_t to σ_t' in x = x_t/(α + s) (float64, all four steps of a 4-step schedule)."""
    g = torch.Generator().manual_seed(0)
    x0, eps = torch.randn(2, 4, 3, 2, 2, generator=g, dtype=torch.float64), \
        torch.randn(2, 4, 3, 2, 2, generator=g, dtype=torch.float64)
    sched = CogVideoXDDIMScheduler(**SCHEDULER)
    sched.set_timesteps(4)
    abar = torch.cat([sched.alphas_cumprod, torch.ones(1, dtype=torch.float64)])  # index −1: set_alpha_to_one
    for t in sched.timesteps.tolist():
        t_prev = t - 1000 // 4
        a, s = abar[t] ** 0.5, (1 - abar[t]) ** 0.5
        a2, s2 = abar[t_prev] ** 0.5, (1 - abar[t_prev]) ** 0.5
        x_t, v = a * x0 + s * eps, a * eps - s * x0
        flow = vpred_to_flow(x_t, v, a.expand(2), s.expand(2))
        torch.testing.assert_close(flow, eps - x0, rtol=0, atol=1e-12)
        ddim = sched.step(v, t, x_t, return_dict=False)[0]
        sigma, sigma2 = s / (a + s), s2 / (a2 + s2)
        euler = x_t / (a + s) + (sigma2 - sigma) * flow
        torch.testing.assert_close(euler * (a2 + s2), ddim, rtol=0, atol=1e-12)
        torch.testing.assert_close(euler, (1 - sigma2) * x0 + sigma2 * eps, rtol=0, atol=1e-12)


def test_sigmas_follow_the_scheduler_timesteps(backbone):
    sched = CogVideoXDDIMScheduler(**SCHEDULER)
    abar = sched.alphas_cumprod
    table = (1 - abar) ** 0.5 / (abar ** 0.5 + (1 - abar) ** 0.5)
    for steps, timesteps in ((4, [999, 749, 499, 249]), (3, [999, 666, 332]), (50, None)):
        sig = backbone.sigmas(steps)
        assert sig.dtype == torch.float64 and sig.shape == (steps + 1,)
        assert sig[0].item() == 1.0 and sig[-1].item() == 0.0 and bool((sig[1:] < sig[:-1]).all())
        sched.set_timesteps(steps)
        assert timesteps is None or sched.timesteps.tolist() == timesteps
        assert torch.equal(sig[:-1], table[sched.timesteps])
        assert torch.equal(backbone.timesteps(sig[:-1].float()), sched.timesteps)  # float32 σ map back exactly
    for bad in (0, 1001, True, 2.0):
        with pytest.raises(ValueError):
            backbone.sigmas(bad)


def test_training_sigmas_are_sigmas_of_uniform_timesteps(backbone):
    a = backbone.training_sigmas(4096, torch.Generator().manual_seed(0))
    b = backbone.training_sigmas(4096, torch.Generator().manual_seed(0))
    assert a.dtype == torch.float32 and a.shape == (4096,) and torch.equal(a, b)
    t = backbone.timesteps(a)
    assert torch.equal(backbone.sigmas(1000)[:-1].flip(0)[t].float(), a)
    assert t.min().item() < 50 and t.max().item() > 950 and abs(t.double().mean().item() - 499.5) < 20
    with pytest.raises(ValueError):
        backbone.training_sigmas(0, torch.Generator())


# ---------------------------------------------------------------------------------------------- VAE, text


def test_encode_latents_scales_the_posterior_and_decode_inverts_the_scale(backbone):
    g = torch.Generator().manual_seed(0)
    video = torch.rand(1, 3, FRAMES, HEIGHT, WIDTH, generator=g) * 2 - 1
    with torch.no_grad():
        dist = backbone.vae.encode(video).latent_dist
        mean = backbone.encode_latents(video)
        sample = backbone.encode_latents(video, generator=torch.Generator().manual_seed(3))
        decoded = backbone.decode_latents(mean)
        direct = backbone.vae.decode(dist.mode()).sample
    assert mean.shape == (1, 4, 3, 2, 2) and mean.dtype == torch.float32
    torch.testing.assert_close(mean, 0.7 * dist.mode(), rtol=0, atol=1e-6)
    torch.testing.assert_close(sample, 0.7 * dist.sample(torch.Generator().manual_seed(3)), rtol=0, atol=1e-6)
    assert decoded.shape == video.shape
    torch.testing.assert_close(decoded, direct, rtol=0, atol=1e-5)
    with pytest.raises(ValueError):
        backbone.encode_latents(video[:, :, :8])
    with pytest.raises(ValueError):
        backbone.encode_latents(video[..., :12])
    with pytest.raises(TypeError):
        backbone.encode_text(PROMPT)


# ---------------------------------------------------------------------------------------------- (b) pipeline


@pytest.mark.parametrize("steps", [4, 5])
def test_euler_over_sigmas_reproduces_the_pipelines_ddim_latents(backbone, steps):
    g = torch.Generator().manual_seed(1)
    image = torch.rand(1, 3, HEIGHT, WIDTH, generator=g)  # [0, 1], as the pipeline's image processor expects
    noise = torch.randn(1, backbone.latent.num_latent_frames(FRAMES), 4, 2, 2, generator=g)  # (B, F, C, h, w)
    plucker = torch.randn(1, backbone.latent.camera_channels, noise.shape[1], 2, 2, generator=g)
    with torch.no_grad():
        with backbone.hub_transformer():
            pipe = backbone.pipeline()
            pipe.set_progress_bar_config(disable=True)
            ref = pipe(image=image, prompt=PROMPT, height=HEIGHT, width=WIDTH, num_frames=FRAMES,
                       num_inference_steps=steps, guidance_scale=1.0, use_dynamic_cfg=False,
                       generator=torch.Generator().manual_seed(7), latents=noise.clone(), output_type="latent",
                       max_sequence_length=TEXT_LENGTH).frames
        # The pipeline samples the image posterior with its generator: the same seed gives the same image latent.
        image_latent = backbone.encode_latents((2 * image - 1).unsqueeze(2), generator=torch.Generator().manual_seed(7))
        text, mask = backbone.encode_text([PROMPT])
        ours = euler_sample(lambda x, s: backbone(x, s.expand(1), image_latent, plucker, text, mask),
                            noise.permute(0, 2, 1, 3, 4), backbone.sigmas(steps))
    diff = (ours.permute(0, 2, 1, 3, 4) - ref).abs().max().item()
    assert diff <= 1e-5, diff
    assert ref.abs().max().item() > 0.1  # a real comparison


# ---------------------------------------------------------------------------------------------- (c) Hub folder


@pytest.mark.slow
def test_write_load_round_trip_keeps_camera_weights_and_the_diffusers_layout(tmp_path):
    written = write_tiny_folder(tmp_path, camera_std=0.05)
    loaded = CogVideoXBackbone.from_pretrained(tmp_path)
    assert loaded.camera_conv.camera_weight.abs().sum().item() > 0
    assert torch.equal(loaded.camera_conv.camera_weight, written.camera_conv.camera_weight)
    inp = tiny_inputs(written, batch=2)
    sigma = torch.tensor([0.9, 0.2])
    with torch.no_grad():
        text, mask = written.encode_text([PROMPT, ""])
        text2, mask2 = loaded.encode_text([PROMPT, ""])
        assert torch.equal(text, text2)
        v1 = written(inp["x"], sigma, inp["image_latent"], inp["plucker"], text, mask)
        v2 = loaded(inp["x"], sigma, inp["image_latent"], inp["plucker"], text2, mask2)
    assert torch.equal(v1, v2)
    assert torch.equal(written.sigmas(7), loaded.sigmas(7))
    plain = CogVideoXTransformer3DModel.from_config(written.transformer.config)
    with safe_open(str(tmp_path / "transformer" / "diffusion_pytorch_model.safetensors"), "pt") as f:
        assert set(f.keys()) == set(plain.state_dict())
    pipe = CogVideoXImageToVideoPipeline.from_pretrained(tmp_path, local_files_only=True)
    assert type(pipe.transformer.patch_embed.proj) is nn.Conv2d
    assert isinstance(pipe.scheduler, CogVideoXDDIMScheduler)
    shutil.rmtree(tmp_path / "camera")  # a folder fresh from the Hub: the camera branch starts at zero
    assert not CogVideoXBackbone.from_pretrained(tmp_path).camera_conv.camera_weight.any()
