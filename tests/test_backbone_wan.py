"""The Wan2.2-TI2V-5B backbone (models/backbones/wan.py, issue 30) against diffusers itself, on tiny random components
(tests/tiny_wan.py; nothing is downloaded): the velocity is the diffusers transformer's output called as
``WanImageToVideoPipeline`` calls it, our Euler sampler over the backbone's σ reproduces the pipeline's latents, and
the Hub-layout folder round-trips (and stays loadable by diffusers alone)."""
import json

import pytest

pytest.importorskip("diffusers", reason="the Wan backbone needs diff4splat[diffusers]")
pytestmark = pytest.mark.slow  # every test here: diffusers costs ~8 s to import (tests/conftest.py)
pytest.importorskip("ftfy", reason="diffusers' Wan prompt cleaning needs ftfy (diff4splat[diffusers])")

import diffusers  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from PIL import Image  # noqa: E402
from safetensors import safe_open  # noqa: E402
from safetensors.torch import save_file  # noqa: E402
from tiny_wan import FRAMES, HEIGHT, WIDTH, tiny_wan, tiny_wan_components, write_tiny_wan  # noqa: E402

from models.backbone import LatentFormat  # noqa: E402
from models.backbones.diffusers_backbone import CAMERA_FOLDER, CAMERA_WEIGHTS  # noqa: E402
from models.backbones.wan import WanBackbone  # noqa: E402
from models.flow_matching import euler_sample, sample_logit_normal, shift_sigmas  # noqa: E402

LATENT = (3, HEIGHT // 16, WIDTH // 16)  # (n, h, w) of a FRAMES-frame clip
PROMPT = "a cat walking on grass"


@pytest.fixture
def backbone():
    return tiny_wan()


def _inputs(backbone, batch=2, seed=0):
    g = torch.Generator().manual_seed(seed)
    n, h, w = LATENT
    x = torch.randn(batch, 48, n, h, w, generator=g)
    image_latent = torch.randn(batch, 48, 1, h, w, generator=g)
    plucker = torch.randn(batch, backbone.latent.camera_channels, n, h, w, generator=g)
    return x, image_latent, plucker


def _pipeline_call(transformer, x, image_latent, sigma, text):
    """The transformer called as ``WanImageToVideoPipeline.__call__`` does with ``expand_timesteps=True`` (one
    sample, timestep ``t = σ·1000`` in float32 as ``FlowMatchEulerDiscreteScheduler.timesteps``)."""
    first_frame_mask = torch.ones(1, 1, *x.shape[2:])
    first_frame_mask[:, :, 0] = 0
    latent_model_input = (1 - first_frame_mask) * image_latent + first_frame_mask * x
    t = torch.tensor(sigma, dtype=torch.float32) * 1000
    timestep = (first_frame_mask[0][0][:, ::2, ::2] * t).flatten().unsqueeze(0).expand(x.shape[0], -1)
    return transformer(hidden_states=latent_model_input, timestep=timestep, encoder_hidden_states=text,
                       return_dict=False)[0]


def _image(seed=0):
    rng = np.random.default_rng(seed)
    return Image.fromarray(rng.integers(0, 256, (HEIGHT, WIDTH, 3), dtype=np.uint8))


# ------------------------------------------------------------------ the interface pieces


def test_latent_format_from_the_vae_config(backbone):
    assert backbone.latent == LatentFormat(48, 4, 16)
    assert backbone.latent.camera_channels == 6 * 4 * 16 ** 2
    assert backbone.camera_conv.camera_weight.shape == (24, 6144, 1, 2, 2)
    assert not backbone.camera_conv.camera_weight.any()
    assert len(backbone.transformer_blocks()) == 2
    with pytest.raises(TypeError, match="AutoencoderKLWan"):
        WanBackbone.latent_format(torch.nn.Linear(1, 1))


def test_not_a_ti2v_transformer_is_refused():
    parts = tiny_wan_components()
    parts["transformer"] = diffusers.WanTransformer3DModel(
        patch_size=(1, 2, 2), num_attention_heads=2, attention_head_dim=12, in_channels=36, out_channels=16,
        text_dim=16, ffn_dim=32, num_layers=1)
    with pytest.raises(ValueError, match="TI2V"):
        WanBackbone(**parts)


def test_encode_latents_normalises_per_channel_and_decode_inverts_it(backbone):
    video = torch.rand(1, 3, 5, 32, 32, generator=torch.Generator().manual_seed(0)) * 2 - 1
    c = backbone.vae.config
    mean = torch.tensor(c.latents_mean).view(1, 48, 1, 1, 1)
    std = torch.tensor(c.latents_std).view(1, 48, 1, 1, 1)
    with torch.no_grad():
        z = backbone.vae.encode(video).latent_dist.mode()
        latents = backbone.encode_latents(video)
        assert latents.shape == (1, 48, 2, 2, 2) and latents.dtype == torch.float32
        torch.testing.assert_close(latents, (z - mean) / std)
        torch.testing.assert_close(backbone.decode_latents(latents), backbone.vae.decode(z).sample,
                                   atol=1e-5, rtol=1e-5)
        a = backbone.encode_latents(video, torch.Generator().manual_seed(1))
        b = backbone.encode_latents(video, torch.Generator().manual_seed(1))
    assert torch.equal(a, b) and not torch.equal(a, latents)
    with pytest.raises(ValueError, match="frames"):
        backbone.encode_latents(video[:, :, :4])
    with pytest.raises(ValueError, match="multiples of 16"):
        backbone.encode_latents(video[..., :24])
    with pytest.raises(ValueError, match="latents"):
        backbone.decode_latents(latents[:, :16])


def test_encode_text_is_the_pipelines_prompt_encoding(backbone):
    embeds, mask = backbone.encode_text([PROMPT, ""])
    assert embeds.shape == (2, 512, 16) and embeds.dtype == torch.float32
    assert mask.shape == (2, 512) and mask.dtype == torch.bool and mask.all()
    reference, _ = backbone.pipeline().encode_prompt([PROMPT, ""], do_classifier_free_guidance=False,
                                                     max_sequence_length=512)
    assert torch.equal(embeds, reference)
    used = (embeds != 0).any(-1).sum(1).tolist()
    assert used[0] > used[1] > 0 and not embeds[:, used[0]:].any()  # zeros after each prompt's tokens
    with pytest.raises(TypeError):
        backbone.encode_text(PROMPT)


def test_sigmas_are_the_schedulers_own(backbone):
    before = backbone.scheduler.sigmas.clone()
    sig = backbone.sigmas(6)
    reference = diffusers.FlowMatchEulerDiscreteScheduler(shift=5.0)
    reference.set_timesteps(6)
    assert sig.dtype == torch.float64 and sig.shape == (7,) and sig[0] == 1 and sig[-1] == 0
    assert torch.equal(sig, reference.sigmas.double())
    assert torch.equal(reference.timesteps, reference.sigmas[:-1] * 1000)  # timestep = σ·num_train_timesteps
    assert torch.equal(backbone.scheduler.sigmas, before)  # set_timesteps ran on a copy
    # The Hub folder's scheduler: UniPC with flow sigmas (integer timesteps ⌊1000·σ⌋).
    backbone.scheduler = diffusers.UniPCMultistepScheduler(prediction_type="flow_prediction", use_flow_sigmas=True,
                                                           flow_shift=5.0)
    sig = backbone.sigmas(6)
    assert sig.shape == (7,) and 0.999 < sig[0] < 1 and sig[-1] == 0 and backbone.shift == 5.0
    # A DDPM grid (no sigmas) and an inverted one (Mochi's: σ rising to 1).
    for scheduler in (diffusers.DDIMScheduler(), diffusers.FlowMatchEulerDiscreteScheduler(invert_sigmas=True)):
        backbone.scheduler = scheduler
        with pytest.raises(ValueError, match="flow-matching"):
            backbone.sigmas(6)
    with pytest.raises(ValueError, match="steps"):
        backbone.sigmas(0)


def test_training_sigmas_are_shifted_logit_normal(backbone):
    sig = backbone.training_sigmas(1000, torch.Generator().manual_seed(3))
    expected = shift_sigmas(sample_logit_normal(1000, generator=torch.Generator().manual_seed(3)), 5.0)
    assert sig.shape == (1000,) and sig.dtype == torch.float32 and torch.equal(sig, expected)
    assert 0 < sig.min() and sig.max() < 1 and sig.median() > 0.7  # shift 5 moves the median 0.5 to 5/6


# ------------------------------------------------------------------ (a) the velocity is diffusers' transformer


def test_velocity_is_the_diffusers_transformer_called_as_the_pipeline_does(backbone):
    x, image_latent, plucker = _inputs(backbone)
    sigma = torch.tensor([0.7, 0.25])
    text, mask = backbone.encode_text([PROMPT, ""])
    with torch.no_grad():
        ours = backbone(x, sigma, image_latent, plucker, text, mask)
        with backbone.hub_transformer() as transformer:
            assert isinstance(transformer.patch_embedding, torch.nn.Conv3d)
            reference = torch.cat([_pipeline_call(transformer, x[i:i + 1], image_latent[i:i + 1], s, text[i:i + 1])
                                   for i, s in enumerate(sigma.tolist())])
        # Frame 0 of x is not read; no prompt is the prompt "".
        x2 = x.clone()
        x2[:, :, 0] = torch.randn_like(x2[:, :, 0])
        again = backbone(x2, sigma, image_latent, plucker, text, None)
        no_prompt = backbone(x[1:], sigma[1:], image_latent[1:], plucker[1:], None, None)
        with_empty = backbone(x[1:], sigma[1:], image_latent[1:], plucker[1:], text[1:], mask[1:])
    assert ours.shape == x.shape and ours.dtype == torch.float32
    diff = (ours - reference).abs().max().item()
    print(f"velocity vs the diffusers transformer: max |diff| = {diff:.3g}")
    torch.testing.assert_close(ours, reference, atol=1e-5, rtol=1e-5)
    assert torch.equal(again, ours)
    assert torch.equal(no_prompt, with_empty)


def test_the_camera_branch_is_wired(backbone):
    x, image_latent, plucker = _inputs(backbone)
    sigma = torch.tensor([0.5, 0.5])
    with torch.no_grad():
        before = backbone(x, sigma, image_latent, plucker, None, None)
        assert torch.equal(before, backbone(x, sigma, image_latent, torch.zeros_like(plucker), None, None))
        backbone.camera_conv.camera_weight.normal_(0, 0.02, generator=torch.Generator().manual_seed(0))
        after = backbone(x, sigma, image_latent, plucker, None, None)
    assert (after - before).abs().max() > 1e-3


def test_velocity_shape_errors(backbone):
    x, image_latent, plucker = _inputs(backbone)
    sigma = torch.tensor([0.5, 0.5])
    with pytest.raises(ValueError, match="sigma"):
        backbone(x, sigma[:1], image_latent, plucker, None, None)
    with pytest.raises(ValueError, match="image_latent"):
        backbone(x, sigma, image_latent[:, :, :, :2], plucker, None, None)
    with pytest.raises(ValueError, match="plucker"):
        backbone(x, sigma, image_latent, plucker[:, :6], None, None)
    with pytest.raises(ValueError, match="patch_size"):
        backbone(x[..., :1], sigma, image_latent[..., :1], plucker[..., :1], None, None)
    with pytest.raises(ValueError, match="text"):
        backbone(x, sigma, image_latent, plucker, torch.zeros(1, 512, 16), None)


def test_tensors_are_made_on_the_inputs_device(backbone, request):
    """velocity, the latent normalisation, sigmas and training_sigmas make no tensor on the default device (the
    tokenizer's ids are diffusers' own: the prompts are encoded first, and the "" embedding cached)."""
    x, image_latent, plucker = _inputs(backbone, batch=1)
    video = torch.rand(1, 3, 5, 32, 32, generator=torch.Generator().manual_seed(0)) * 2 - 1
    sigma = torch.tensor([0.6])
    with torch.no_grad():
        text, mask = backbone.encode_text([PROMPT])
        expected = backbone(x, sigma, image_latent, plucker, None, None)
        request.getfixturevalue("no_implicit_device")
        outputs = [backbone(x, sigma, image_latent, plucker, text, mask),
                   backbone(x, sigma, image_latent, plucker, None, None),
                   backbone.decode_latents(backbone.encode_latents(video)), backbone.sigmas(3),
                   backbone.training_sigmas(4, torch.Generator().manual_seed(0))]
    assert all(o.device.type == "cpu" for o in outputs)
    assert torch.equal(outputs[1], expected)


@pytest.mark.real_gpu  # a CUDA generator (the simulated one is the CPU's)
def test_on_the_device(backbone, device, full_float32):
    """The backbone on ``device`` (CUDA where present) agrees with the CPU; outputs on the inputs' device."""
    x, image_latent, plucker = _inputs(backbone, batch=1)
    sigma = torch.tensor([0.7])
    video = torch.rand(1, 3, 5, 32, 32, generator=torch.Generator().manual_seed(0)) * 2 - 1
    with torch.no_grad():
        cpu = [backbone(x, sigma, image_latent, plucker, None, None), backbone.encode_latents(video)]
        backbone.to(device)
        text, mask = backbone.encode_text([""])
        args = [t.to(device) for t in (x, sigma, image_latent, plucker)]
        out = [backbone(*args, None, None), backbone.encode_latents(video.to(device)),
               backbone(*args, text, mask)]
        sig = backbone.training_sigmas(8, torch.Generator(device).manual_seed(0))
    assert text.device == mask.device == sig.device == out[0].device == out[1].device
    assert out[0].device.type == device.type
    if device.type == "cpu":
        assert torch.equal(out[0], out[2])
    else:  # None uses "" encoded once (here on the CPU, first call above); the GPU's encoding differs by rounding
        torch.testing.assert_close(out[0], out[2], atol=1e-5, rtol=1e-5)
    for a, b in zip(out[:2], cpu, strict=True):
        torch.testing.assert_close(a.cpu(), b, atol=1e-4, rtol=1e-4)


# ------------------------------------------------------------------ (b) our sampler reproduces the pipeline


def test_euler_over_the_backbone_sigmas_reproduces_the_pipeline(backbone):
    steps, image = 4, _image()
    noise = torch.randn(1, 48, *LATENT, generator=torch.Generator().manual_seed(5))
    with torch.no_grad(), backbone.hub_transformer():
        pipe = backbone.pipeline(**backbone.pipeline_kwargs())
        pipe.set_progress_bar_config(disable=True)
        reference = pipe(image=image, prompt=PROMPT, height=HEIGHT, width=WIDTH, num_frames=FRAMES,
                         num_inference_steps=steps, guidance_scale=1.0, latents=noise.clone(),
                         output_type="latent", return_dict=False)[0]
        pixels = pipe.video_processor.preprocess(image, height=HEIGHT, width=WIDTH)
    with torch.no_grad():
        image_latent = backbone.encode_latents(pixels.unsqueeze(2))
        text, mask = backbone.encode_text([PROMPT])
        plucker = torch.zeros(1, backbone.latent.camera_channels, *LATENT)
        ours = euler_sample(lambda x, s: backbone(x, s.expand(1), image_latent, plucker, text, mask),
                            noise, backbone.sigmas(steps))
    ours[:, :, :1] = image_latent  # as the pipeline does after its loop
    diff = (ours - reference).abs().max().item()
    print(f"euler_sample vs WanImageToVideoPipeline latents: max |diff| = {diff:.3g}")
    assert reference.shape == ours.shape == (1, 48, *LATENT)
    torch.testing.assert_close(ours, reference, atol=1e-5, rtol=1e-5)
    assert (ours - noise).abs().max() > 0.1  # it did move


# ------------------------------------------------------------------ (c) the Hub folder


@pytest.mark.slow
def test_write_and_load_round_trip(backbone, tmp_path):
    folder = tmp_path / "wan"
    saved = write_tiny_wan(folder, camera_seed=1)
    loaded = WanBackbone.from_pretrained(folder)
    assert loaded.camera_conv.camera_weight.abs().max() > 0
    assert torch.equal(loaded.camera_conv.camera_weight, saved.camera_conv.camera_weight)
    x, image_latent, plucker = _inputs(saved)
    sigma = torch.tensor([0.8, 0.4])
    with torch.no_grad():
        for prompt in (None, PROMPT):
            args = (None, None) if prompt is None else saved.encode_text([prompt, prompt])
            args2 = (None, None) if prompt is None else loaded.encode_text([prompt, prompt])
            assert prompt is None or torch.equal(args[0], args2[0])
            assert torch.equal(saved(x, sigma, image_latent, plucker, *args),
                               loaded(x, sigma, image_latent, plucker, *args2))
    assert torch.equal(saved.sigmas(5), loaded.sigmas(5))

    # transformer/ keeps the checkpoint's key names: exactly a plain WanTransformer3DModel's, no camera_weight.
    with safe_open(str(folder / "transformer" / "diffusion_pytorch_model.safetensors"), "pt") as f:
        keys = set(f.keys())
    plain = diffusers.WanTransformer3DModel.from_config(diffusers.WanTransformer3DModel.load_config(
        folder / "transformer"))
    assert keys == set(plain.state_dict()) and not any("camera" in k for k in keys)
    with safe_open(str(folder / CAMERA_FOLDER / CAMERA_WEIGHTS), "pt") as f:
        assert set(f.keys()) == {"patch_embedding.camera_weight"}

    # diffusers' own classes load the folder.
    index = json.loads((folder / "model_index.json").read_text())
    assert index["_class_name"] == "WanImageToVideoPipeline" and index["expand_timesteps"] is True
    pipe = diffusers.DiffusionPipeline.from_pretrained(folder, local_files_only=True)
    assert isinstance(pipe, diffusers.WanImageToVideoPipeline) and pipe.config.expand_timesteps
    assert isinstance(pipe.transformer.patch_embedding, torch.nn.Conv3d)
    assert torch.equal(pipe.transformer.patch_embedding.weight, saved.camera_conv.weight)


@pytest.mark.slow
def test_a_hub_style_wan_pipeline_folder_loads(tmp_path):
    """Wan-AI/Wan2.2-TI2V-5B-Diffusers's model_index.json says WanPipeline (expand_timesteps true, no
    transformer_2, no image encoder): such a folder, without camera/, loads with zero camera weights."""
    folder = tmp_path / "hub"
    saved = write_tiny_wan(folder)
    (folder / CAMERA_FOLDER / CAMERA_WEIGHTS).unlink()
    (folder / CAMERA_FOLDER).rmdir()
    index = json.loads((folder / "model_index.json").read_text())
    index = {k: v for k, v in index.items() if k not in ("image_encoder", "image_processor")}
    (folder / "model_index.json").write_text(json.dumps({**index, "_class_name": "WanPipeline"}))
    assert isinstance(diffusers.DiffusionPipeline.from_pretrained(folder, local_files_only=True),
                      diffusers.WanPipeline)
    loaded = WanBackbone.from_pretrained(folder)
    assert not loaded.camera_conv.camera_weight.any()
    x, image_latent, plucker = _inputs(saved, batch=1)
    with torch.no_grad():
        assert torch.equal(saved(x, torch.tensor([0.5]), image_latent, plucker, None, None),
                           loaded(x, torch.tensor([0.5]), image_latent, plucker, None, None))


@pytest.mark.slow
def test_folders_that_are_not_wan_ti2v_are_refused(tmp_path):
    folder = tmp_path / "wan"
    write_tiny_wan(folder)
    index_path = folder / "model_index.json"
    index = json.loads(index_path.read_text())

    save_file({"patch_embedding.camera_weight": torch.zeros(24, 6144, 1, 2, 3)},
              str(folder / CAMERA_FOLDER / CAMERA_WEIGHTS))
    with pytest.raises(ValueError, match="camera_weight"):
        WanBackbone.from_pretrained(folder)
    save_file({"camera_weight": torch.zeros(24, 6144, 1, 2, 2)}, str(folder / CAMERA_FOLDER / CAMERA_WEIGHTS))
    with pytest.raises(ValueError, match="camera_weight"):
        WanBackbone.from_pretrained(folder)

    index_path.write_text(json.dumps({**index, "_class_name": "CogVideoXImageToVideoPipeline"}))
    with pytest.raises(ValueError, match="CogVideoXImageToVideoPipeline"):
        WanBackbone.from_pretrained(folder)
    index_path.write_text(json.dumps({**index, "expand_timesteps": False}))  # Wan2.1 / A14B image-to-video
    with pytest.raises(ValueError, match="TI2V"):
        WanBackbone.from_pretrained(folder)
    index_path.unlink()
    with pytest.raises(FileNotFoundError, match="model_index.json"):
        WanBackbone.from_pretrained(folder)
