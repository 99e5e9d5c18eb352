import pytest
import torch

from helpers import EXAMPLE_IMAGE, tiny_model
from diff4splat.cameras import camera_rays
from diff4splat.io import load_image
from diff4splat.pipeline import Diff4SplatPipeline

FRAMES = 9


@pytest.fixture(scope="module")
def image():
    return load_image(EXAMPLE_IMAGE, size=(64, 64))


def _run(pipe, image, prompt="", frames=FRAMES, **kw):
    cams = pipe.default_cameras("orbit", frames)
    return pipe(image, cams, prompt, steps=kw.pop("steps", 2), **kw)


def test_untrained_deformation_gives_a_static_scene_with_pixel_aligned_gaussians(image):
    pipe = Diff4SplatPipeline(tiny_model())
    res = _run(pipe, image)
    assert res.scene.is_static and res.scene.times is None  # zero-init deformation = identity → stored as static
    assert res.prune_stats["before"] == 64 * 64
    g = res.scene.canonical
    assert torch.isfinite(g.means).all() and (g.scales > 0).all()
    # the reference camera (identity) sees each Gaussian at its own pixel centre
    if res.prune_stats["after"] == res.prune_stats["before"]:
        uv = (res.cameras.Ks[0] @ g.means.T).T
        uv = uv[:, :2] / uv[:, 2:]
        _, d = camera_rays(res.cameras.viewmats[:1], res.cameras.Ks[:1], 64, 64)
        jj, ii = torch.meshgrid(torch.arange(64) + 0.5, torch.arange(64) + 0.5, indexing="xy")
        torch.testing.assert_close(uv, torch.stack([jj, ii], -1).reshape(-1, 2), atol=1e-3, rtol=0)


def test_dynamic_head_gives_deformation_at_every_frame_time(image):
    pipe = Diff4SplatPipeline(tiny_model(dynamic=True))
    res = _run(pipe, image)
    scene = res.scene
    assert not scene.is_static
    torch.testing.assert_close(scene.times, res.cameras.times)
    assert scene.d_means.shape == (FRAMES, scene.num_gaussians, 3)
    assert scene.d_means.abs().max() > 0
    assert not torch.equal(scene.at(0.0).means, scene.at(1.0).means)


def test_empty_prompt_never_calls_the_text_encoder(image, monkeypatch):
    model = tiny_model()
    calls = []
    monkeypatch.setattr(model.text_encoder, "forward", lambda *a, **k: calls.append(1) or (_ for _ in ()).throw(AssertionError("called")))
    pipe = Diff4SplatPipeline(model)
    _run(pipe, image, prompt="")
    _run(pipe, image, prompt="   ")
    assert calls == []


def test_prompt_conditions_the_sample_once_cross_attention_is_trained(image):
    model = tiny_model()
    with torch.no_grad():  # un-zero the cross-attention output projections (zero-init at construction)
        for name, p in model.dit.named_parameters():
            if "cross" in name and p.dim() == 2 and p.abs().sum() == 0:
                p.normal_(0, 0.2)
        for name, p in model.dit.named_parameters():  # and the final layer, so v ≠ 0
            if p.abs().sum() == 0:
                p.normal_(0, 0.05)
    pipe = Diff4SplatPipeline(model)
    calls = []
    model.text_encoder.register_forward_hook(lambda *a: calls.append(1))
    a = _run(pipe, image, prompt="a cat turns its head")
    b = _run(pipe, image, prompt="the camera flies over a city")
    c = _run(pipe, image, prompt="")
    assert len(calls) == 2
    assert not torch.allclose(a.latents, b.latents) and not torch.allclose(a.latents, c.latents)


def test_same_seed_same_scene_other_seed_other_latents(image):
    pipe = Diff4SplatPipeline(tiny_model(active_dit=True))
    a, b, c = _run(pipe, image, seed=1), _run(pipe, image, seed=1), _run(pipe, image, seed=2)
    assert torch.equal(a.latents, b.latents) and torch.equal(a.scene.canonical.means, b.scene.canonical.means)
    assert not torch.equal(a.latents, c.latents)
    # the photograph's own latent replaces the sampled first latent frame
    assert torch.equal(a.latents[:, :, 0], c.latents[:, :, 0])


def test_heun_costs_two_evaluations_per_step_but_the_last(image):
    model = tiny_model()
    pipe = Diff4SplatPipeline(model)
    calls = []
    model.dit.register_forward_hook(lambda *a: calls.append(1))
    _run(pipe, image, steps=4, sampler="heun")
    assert len(calls) == 2 * 4 - 1
    calls.clear()
    _run(pipe, image, steps=4, sampler="euler")
    assert len(calls) == 4


@pytest.mark.parametrize("bad", ["image_shape", "image_range", "camera_size", "frames", "sampler", "steps"])
def test_bad_inputs_raise_value_error(image, bad):
    pipe = Diff4SplatPipeline(tiny_model())
    cams = pipe.default_cameras("orbit", FRAMES)
    kw = {"steps": 1}
    if bad == "image_shape":
        image = image[:32]
    elif bad == "image_range":
        image = image * 2
    elif bad == "camera_size":
        cams = cams.resized(32, 32)
    elif bad == "frames":
        cams = pipe.default_cameras("orbit", 8)
    elif bad == "sampler":
        kw["sampler"] = "rk4"
    else:
        kw["steps"] = 0
    with pytest.raises(ValueError):
        pipe(image, cams, "", **kw)
