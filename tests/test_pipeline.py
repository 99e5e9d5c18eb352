"""Tests of diff4splat/pipeline.py: generation, LDRM maps → Gaussians, defaults, validation."""
import math
from pathlib import Path

import pytest
import torch
from helpers import EXAMPLE_IMAGE, tiny_model

from diff4splat import pipeline as pipeline_module
from diff4splat.assembly.assemble import to_gaussians, video_colors
from diff4splat.assembly.photo import BACKDROP_CELLS, BACKDROP_EXTEND
from diff4splat.cameras import camera_rays, pack_plucker, plucker_rays
from diff4splat.generate import scene_slots
from diff4splat.io import load_image
from diff4splat.pipeline import Diff4SplatPipeline
from diff4splat.runtime import TorchRuntime
from diff4splat.scene.gaussians import sh0_to_rgb
from diff4splat.scene.quaternions import axis_angle_to_quat, quat_to_rotmat
from models import flow_matching
from models.flow_matching import euler_sample, sigma_schedule
from models.ldrm import LDRMOutput

FRAMES = 9


@pytest.fixture(scope="module")
def image():
    return load_image(EXAMPLE_IMAGE, size=(64, 64))


def _run(pipe, image, prompt="", frames=FRAMES, **kw):
    cams = pipe.default_cameras("orbit", frames)
    return pipe(image, cams, prompt, steps=kw.pop("steps", 2), **kw)


@pytest.mark.slow
def test_untrained_deformation_gives_a_static_scene_with_pixel_aligned_gaussians(image):
    pipe = Diff4SplatPipeline(tiny_model())
    res = _run(pipe, image)
    assert res.scene.is_static and res.scene.times is None  # zero-init deformation = identity → stored as static
    assert res.source_frames.tolist() == [0, 4, 8]  # FRAMES = 9 → 3 latent frames
    S = len(res.source_frames)
    assert res.photo_gaussians == 64 * 64 + 32 * 32  # the photo layer: front disks, backing disks per 2×2 pixels
    backdrop = (1 + 2 * BACKDROP_EXTEND) ** 2 * BACKDROP_CELLS**2  # 64 px: 4-pixel cells over 5 × 5 image sizes
    assert res.prune_stats["before"] == res.num_slots == res.photo_gaussians + backdrop + (S - 1) * 64 * 64
    assert scene_slots(pipe, 64, 64, FRAMES) == res.num_slots  # what generate's output-size check counts
    stats = res.prune_stats
    assert stats["after"] == (stats["before"] - stats["duplicates"] - stats["occluders"] - stats["low_opacity"]
                              - stats["unseen"])
    assert res.gaussian_index.shape == (res.scene.num_gaussians,) and bool((res.gaussian_index.diff() > 0).all())
    g = res.scene.canonical
    assert torch.isfinite(g.means).all() and (g.scales > 0).all()
    # the reference camera (identity) sees each front disk of the photo layer at its own pixel centre
    ref = res.gaussian_index < 64 * 64
    if int(ref.sum()) == 64 * 64:
        uv = (res.cameras.Ks[0] @ g.means[ref].T).T
        uv = uv[:, :2] / uv[:, 2:]
        _, d = camera_rays(res.cameras.viewmats[:1], res.cameras.Ks[:1], 64, 64)
        jj, ii = torch.meshgrid(torch.arange(64) + 0.5, torch.arange(64) + 0.5, indexing="xy")
        torch.testing.assert_close(uv, torch.stack([jj, ii], -1).reshape(-1, 2), atol=1e-3, rtol=0)


@pytest.mark.slow
@pytest.mark.parametrize("trajectory", ["arc", "orbit"])
def test_no_prompt_and_no_drag_give_a_static_scene_on_any_path(image, trajectory):
    """Motion only where asked for (issue 78): a model whose deformation head moves every pixel makes a static scene
    (no deformation, so no deformation.npz) without a prompt, a blank one included; with one it moves."""
    pipe = Diff4SplatPipeline(tiny_model(dynamic=True))
    cams = pipe.default_cameras(trajectory, FRAMES)
    for prompt in ("", "   "):
        res = pipe(image, cams, prompt, steps=1)
        assert res.scene.is_static and res.scene.times is None, prompt
    assert not pipe(image, cams, "a cat turns its head", steps=1).scene.is_static


def test_dynamic_head_gives_deformation_at_every_frame_time(image):
    pipe = Diff4SplatPipeline(tiny_model(dynamic=True))
    res = _run(pipe, image, prompt="a cat turns its head")  # motion is asked for
    scene = res.scene
    assert not scene.is_static
    torch.testing.assert_close(scene.times, res.cameras.times)
    assert scene.d_means.shape == (FRAMES, scene.num_gaussians, 3)
    assert scene.d_means.abs().max() > 0
    assert not torch.equal(scene.at(0.0).means, scene.at(1.0).means)


@pytest.mark.slow
def test_empty_prompt_never_calls_the_text_encoder(image, monkeypatch):
    model = tiny_model()
    calls = []
    def refuse(*a, **k):
        calls.append(1)
        raise AssertionError("the text encoder was called")

    monkeypatch.setattr(model.text_encoder, "forward", refuse)
    pipe = Diff4SplatPipeline(model)
    _run(pipe, image, prompt="")
    _run(pipe, image, prompt="   ")
    assert calls == []


@pytest.mark.slow
def test_prompt_conditions_the_sample_once_cross_attention_is_trained(image):
    model = _trained_cross_attention(tiny_model())
    pipe = Diff4SplatPipeline(model)
    calls = []
    model.text_encoder.register_forward_hook(lambda *a: calls.append(1))
    a = _run(pipe, image, prompt="a cat turns its head")
    b = _run(pipe, image, prompt="the camera flies over a city")
    c = _run(pipe, image, prompt="")
    assert len(calls) == 2
    assert not torch.allclose(a.latents, b.latents) and not torch.allclose(a.latents, c.latents)


def _trained_cross_attention(model):
    with torch.no_grad():  # un-zero the cross-attention output projections (zero-init at construction)
        for name, p in model.dit.named_parameters():
            if "cross" in name and p.dim() == 2 and p.abs().sum() == 0:
                p.normal_(0, 0.2)
        for p in model.dit.parameters():  # and the final layer, so v ≠ 0
            if p.abs().sum() == 0:
                p.normal_(0, 0.05)
    return model


@pytest.mark.slow
def test_a_mask_of_only_real_tokens_is_dropped_and_padding_stays_masked(image, monkeypatch):
    """One prompt has no padding: its all-True mask reaches the DiT as None (unmasked cross-attention); a mask
    with padding is kept, and padded junk changes nothing."""
    pipe = Diff4SplatPipeline(_trained_cross_attention(tiny_model()))
    runtime = pipe.runtime
    seen, velocity, encode = [], runtime.velocity, runtime.encode_text
    monkeypatch.setattr(runtime, "velocity", lambda *a, **k: seen.append(k["text_mask"]) or velocity(*a, **k))
    plain = _run(pipe, image, prompt="a cat turns its head")
    assert seen and all(m is None for m in seen)

    def padded(prompt):  # the same tokens and three junk tokens marked as padding
        text, mask = encode(prompt)
        junk = torch.randn(1, 3, text.shape[-1], generator=torch.Generator().manual_seed(0))
        return torch.cat([text, junk], 1), torch.cat([mask, torch.zeros(1, 3, dtype=torch.bool)], 1)

    monkeypatch.setattr(runtime, "encode_text", padded)
    seen.clear()
    masked = _run(pipe, image, prompt="a cat turns its head")
    L = len("a cat turns its head") + 2  # the byte tokenizer: bos, one token per byte, eos
    assert seen and all(m is not None and m.shape == (1, L + 3) and int(m.sum()) == L for m in seen)
    torch.testing.assert_close(masked.latents, plain.latents, atol=1e-5, rtol=1e-5)


@pytest.mark.slow
def test_same_seed_same_scene_other_seed_other_latents(image):
    pipe = Diff4SplatPipeline(tiny_model(active_dit=True))
    a, b, c = _run(pipe, image, seed=1), _run(pipe, image, seed=1), _run(pipe, image, seed=2)
    assert torch.equal(a.latents, b.latents) and torch.equal(a.scene.canonical.means, b.scene.canonical.means)
    assert not torch.equal(a.latents, c.latents)
    # the photograph's own latent replaces the sampled first latent frame
    assert torch.equal(a.latents[:, :, 0], c.latents[:, :, 0])


@pytest.mark.slow
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


@pytest.mark.parametrize("bad", ["image_shape", "image_range", "image_numpy", "camera_size", "frames", "sampler",
                                 "steps"])
def test_bad_inputs_raise_value_error(image, bad):
    """Each bad input raises a ValueError naming the offending parameter."""
    pipe = Diff4SplatPipeline(tiny_model())
    cams = pipe.default_cameras("orbit", FRAMES)
    kw = {"steps": 1}
    if bad == "image_shape":
        image = image[:32]
    elif bad == "image_range":
        image = image * 2
    elif bad == "image_numpy":  # an AttributeError ('numpy.ndarray' object has no attribute 'dim') before
        image = image.numpy()
    elif bad == "camera_size":
        cams = cams.resized(32, 32)
    elif bad == "frames":
        cams = pipe.default_cameras("orbit", 8)
    elif bad == "sampler":
        kw["sampler"] = "rk4"
    else:
        kw["steps"] = 0
    with pytest.raises(ValueError, match={"image_shape": "image", "image_range": "image",
                                          "image_numpy": "image must be a torch.Tensor", "camera_size": "cameras",
                                          "frames": "T=8", "sampler": "sampler", "steps": "steps"}[bad]):
        pipe(image, cams, "", **kw)


def _maps(B=1, K=3, S=2, H=12, W=16, seed=0) -> LDRMOutput:
    """Random activated LDRM maps of S source frames in their documented ranges (no network needed)."""
    g = torch.Generator().manual_seed(seed)
    quats = torch.randn(B, S, H, W, 4, generator=g)
    d_quats = torch.randn(B, K, S, H, W, 4, generator=g)
    return LDRMOutput(distance=0.5 + 3 * torch.rand(B, S, H, W, generator=g),
                      scales=0.01 + 0.05 * torch.rand(B, S, H, W, 3, generator=g),
                      quats=quats / quats.norm(dim=-1, keepdim=True),
                      opacities=torch.rand(B, S, H, W, generator=g),
                      colors=torch.rand(B, S, H, W, 3, generator=g),
                      d_means=0.1 * torch.randn(B, K, S, H, W, 3, generator=g),
                      d_quats=d_quats / d_quats.norm(dim=-1, keepdim=True),
                      d_scales=0.1 * torch.randn(B, K, S, H, W, 3, generator=g))


def _viewmat(axis, degrees, t):
    viewmat = torch.eye(4)
    viewmat[:3, :3] = quat_to_rotmat(axis_angle_to_quat(torch.tensor(axis), torch.tensor(math.radians(degrees))))
    viewmat[:3, 3] = torch.tensor(t)
    return viewmat


def test_to_gaussians_puts_each_pixel_on_its_source_camera_ray():
    H, W, S = 12, 16, 2
    out = _maps(B=2, S=S, H=H, W=W)
    viewmats = torch.stack([_viewmat([0.3, 1.0, 0.2], 20.0, [0.2, -0.1, 0.5]),
                            _viewmat([0.0, 1.0, 0.0], -35.0, [-0.4, 0.0, 0.1])])  # non-identity world-to-camera
    Ks = torch.stack([torch.tensor([[14.0, 0.0, 8.5], [0.0, 13.0, 5.5], [0.0, 0.0, 1.0]]),
                      torch.tensor([[11.0, 0.0, 7.5], [0.0, 12.0, 6.0], [0.0, 0.0, 1.0]])])
    g, dm, dq, ds = to_gaussians(out, viewmats, Ks, batch_index=1)
    g.validate()
    M = S * H * W
    assert g.num_gaussians == M and g.sh.shape == (M, 1, 3)
    assert dm.shape == (3, M, 3) and dq.shape == (3, M, 4) and ds.shape == (3, M, 3)
    for s in range(S):
        R, t, K = viewmats[s, :3, :3], viewmats[s, :3, 3], Ks[s]
        centre = -R.T @ t
        for i, j in [(0, 0), (5, 11), (11, 15), (7, 2)]:
            idx = s * H * W + i * W + j  # source-frame-major, then row-major pixels
            d_cam = torch.linalg.solve(K, torch.tensor([j + 0.5, i + 0.5, 1.0]))  # explicit K⁻¹ (u, v, 1)
            d_world = R.T @ d_cam
            torch.testing.assert_close(g.means[idx], centre + out.distance[1, s, i, j] * d_world / d_world.norm(),
                                       atol=1e-5, rtol=1e-5)
            torch.testing.assert_close(dm[:, idx], out.d_means[1, :, s, i, j])
            torch.testing.assert_close(g.quats[idx], out.quats[1, s, i, j])
        # projecting source s's means into camera s lands on the pixel centres; the ray distance is recovered
        part = slice(s * H * W, (s + 1) * H * W)
        cam = g.means[part] @ R.T + t
        uv = (cam @ K.T)[:, :2] / cam[:, 2:3]
        v, u = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")
        torch.testing.assert_close(uv, torch.stack([u, v], -1).reshape(H * W, 2), atol=2e-4, rtol=0)
        torch.testing.assert_close(cam.norm(dim=-1), out.distance[1, s].reshape(H * W), atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(g.opacities, out.opacities[1].reshape(M))
    torch.testing.assert_close(g.scales, out.scales[1].reshape(M, 3))
    # colours survive the SH-0 encoding (clamped to [1e-4, 1 − 1e-4])
    torch.testing.assert_close(sh0_to_rgb(g.sh[:, 0]), out.colors[1].reshape(M, 3).clamp(1e-4, 1 - 1e-4))


def test_to_gaussians_static_maps_and_errors():
    out = _maps(S=1)
    out.d_means = out.d_quats = out.d_scales = None
    K = torch.tensor([[14.0, 0.0, 8.0], [0.0, 14.0, 6.0], [0.0, 0.0, 1.0]])[None]
    g, dm, dq, ds = to_gaussians(out, torch.eye(4)[None], K)
    assert dm is None and dq is None and ds is None and g.num_gaussians == 12 * 16
    with pytest.raises(ValueError, match="batch_index"):
        to_gaussians(out, torch.eye(4)[None], K, batch_index=1)
    with pytest.raises(ValueError, match="viewmats"):
        to_gaussians(out, torch.eye(4), K)  # no source axis
    with pytest.raises(ValueError, match="viewmats"):
        to_gaussians(out, torch.eye(4).repeat(2, 1, 1), K.repeat(2, 1, 1))  # 2 cameras for 1 source frame
    with pytest.raises(ValueError, match="Ks"):
        to_gaussians(out, torch.eye(4)[None], torch.eye(4)[None])


@pytest.mark.slow
def test_video_latents_replace_the_sampler_and_reach_the_ldrm(image, monkeypatch):
    """``video_latents`` skips the DiT; the LDRM receives them with frame 0 replaced by the photo's latent."""
    model = tiny_model()
    pipe = Diff4SplatPipeline(model)
    calls, seen = [], []
    model.dit.register_forward_hook(lambda *a: calls.append(1))
    real = pipe.runtime.reconstruct
    monkeypatch.setattr(pipe.runtime, "reconstruct", lambda lat, *a: seen.append(lat) or real(lat, *a))
    sampled = _run(pipe, image)
    assert calls
    calls.clear()
    noise = torch.randn(sampled.latents.shape, generator=torch.Generator().manual_seed(5))
    res = _run(pipe, image, video_latents=noise)
    assert calls == []
    assert torch.equal(seen[-1][:, :, 1:], noise[:, :, 1:]) and torch.equal(seen[-1][:, :, 0], sampled.latents[:, :, 0])
    assert torch.equal(res.latents, seen[-1])
    with pytest.raises(ValueError, match="video_latents"):
        _run(pipe, image, video_latents=noise[:, :, :2])


@pytest.mark.slow
def test_every_source_frame_contributes_and_duplicates_are_pruned(image):
    """A trained-like LDRM (opaque Gaussians on a plane seen by every frame of a small arc): later source
    frames re-describe what frame 0 placed, so duplicate pruning drops most of them; with gaussian_frames
    "reference" only frame 0's grid exists."""
    model = tiny_model()
    with torch.no_grad():
        model.ldrm.head.out.weight.zero_()  # every pixel at the default distance, default scale
        model.ldrm.head.out.bias.zero_()
        model.ldrm.head.out.bias[8] = 6.0  # opacity σ(6) ≈ 1 (raw channels: distance, scales 3, quaternion 4, opacity)
    pipe = Diff4SplatPipeline(model)
    cams = pipe.default_cameras("forward", FRAMES, amplitude=0.02)  # 4 cm: within 5 % of the 2 m distance
    res = pipe(image, cams, "", steps=1)
    stats = res.prune_stats
    backdrop = (1 + 2 * BACKDROP_EXTEND) ** 2 * BACKDROP_CELLS**2
    assert stats["before"] == 64 * 64 + 32 * 32 + backdrop + 2 * 64 * 64  # photo layer, backdrop, frames 4 and 8
    assert stats["duplicates"] > 0.5 * 2 * 64 * 64, stats
    model.ldrm.config.gaussian_frames = "reference"
    ref = pipe(image, cams, "", steps=1)
    assert ref.prune_stats["before"] == 64 * 64 + 32 * 32 + backdrop and ref.prune_stats["duplicates"] == 0


@pytest.mark.slow
def test_result_reports_the_steps_and_sampler_actually_used(image, monkeypatch):
    """Defaults are resolved once, by the pipeline: the result carries what ran (config defaults included)."""
    pipe = Diff4SplatPipeline(tiny_model())
    assert isinstance(pipe.runtime, TorchRuntime) and pipe.runtime.name == "torch"
    seen = []
    real = flow_matching.ODESteps  # the sampler loop the pipeline drives
    monkeypatch.setattr(pipeline_module, "ODESteps", lambda name, sigmas, noise:
                        seen.append((len(sigmas) - 1, name)) or real(name, sigmas, noise))
    cams = pipe.default_cameras("orbit", 5)
    pipe.config.sampling.steps, pipe.config.sampling.sampler = 3, "heun"
    res = pipe(image, cams, "")
    assert (res.steps, res.sampler, res.shift) == (3, "heun", pipe.config.sampling.shift) and seen[-1] == (3, "heun")
    res = pipe(image, cams, "", steps=2, sampler="euler")
    assert (res.steps, res.sampler) == (2, "euler") and seen[-1] == (2, "euler")


def test_pipeline_rejects_a_model_that_is_no_runtime():
    with pytest.raises(TypeError, match="NetworkRuntime"):
        Diff4SplatPipeline(object())


def test_library_value_errors_name_parameters_not_cli_flags(image):
    """Messages raised to library callers name the parameter (``steps``), never a command-line flag."""
    pipe = Diff4SplatPipeline(tiny_model())
    cams = pipe.default_cameras("orbit", 5)
    for kw in ({"steps": 0}, {"sampler": "rk4"}):
        with pytest.raises(ValueError) as info:
            pipe(image, cams, "", **kw)
        assert "--" not in str(info.value) and next(iter(kw)) in str(info.value)


@pytest.mark.slow
def test_guidance_integrates_the_guided_velocity(image, monkeypatch):
    """Classifier-free guidance (Ho & Salimans 2022) with our networks: with a prompt and g ≠ 1 each step calls the
    DiT with the prompt's tokens and without text, and the sampler integrates v_u + g·(v_p − v_u); g = 1 and an empty
    prompt run one call per step, and g = 1 is the default (the result is the unguided one, bit for bit)."""
    pipe = Diff4SplatPipeline(tiny_model(active_dit=True))
    cams = pipe.default_cameras("orbit", 5)
    calls = []
    real, dit = pipe.runtime.velocity, pipe.runtime.velocity_model
    monkeypatch.setattr(pipe.runtime, "velocity_model", lambda x, s, il, pl, t, m: calls.append(t is not None)
                        or dit(x, s, il, pl, t, m))
    base = pipe(image, cams, "a cat turns", steps=3)
    assert base.guidance == 1.0 and calls == [True] * 3
    calls.clear()
    guided = pipe(image, cams, "a cat turns", steps=3, guidance=3.0)
    assert guided.guidance == 3.0 and calls == [True, False] * 3
    assert (guided.latents - base.latents).abs().max() > 1e-4
    # the same integration by hand from the runtime's two velocities
    text, mask = pipe.runtime.encode_text("a cat turns")
    n, (h, w) = base.latents.shape[2], base.latents.shape[-2:]
    noise = torch.randn((1, base.latents.shape[1], n, h, w), generator=torch.Generator().manual_seed(0))
    image_latent = guided.latents[:, :, :1]
    plucker = _packed_plucker(pipe, cams)
    manual = euler_sample(lambda x, s: real(x, s.reshape(1), image_latent, plucker, None, None)
                          + 3.0 * (real(x, s.reshape(1), image_latent, plucker, text, mask)
                                   - real(x, s.reshape(1), image_latent, plucker, None, None)),
                          noise, sigma_schedule(3, pipe.config.sampling.shift, dtype=torch.float64))
    torch.testing.assert_close(guided.latents[:, :, 1:], manual[:, :, 1:], atol=1e-5, rtol=1e-5)
    calls.clear()
    assert pipe(image, cams, "", steps=3, guidance=3.0).guidance == 1.0 and calls == [False] * 3
    with pytest.raises(ValueError, match="guidance"):
        pipe(image, cams, "a cat", guidance=float("nan"))


def _packed_plucker(pipe, cams):
    c, lat = pipe.config, pipe.runtime.latent
    model_cams = cams.relative_to_first().resized(c.width, c.height)
    return pack_plucker(plucker_rays(model_cams.viewmats, model_cams.Ks, c.width, c.height)[None],
                        lat.temporal_factor, lat.spatial_factor)


def test_video_colors_replace_the_later_frames_colours_only():
    """Source frames 1… take the video's pixels at their own video frame, mapped from [−1, 1] to [0, 1] and clamped;
    frame 0's colours and every other map stay; a video at another grid or too short is refused."""
    g = torch.Generator().manual_seed(0)
    S, h, w, T = 3, 4, 5, 9
    out = LDRMOutput(distance=torch.rand(1, S, h, w, generator=g), scales=torch.rand(1, S, h, w, 3, generator=g),
                     quats=torch.rand(1, S, h, w, 4, generator=g), opacities=torch.rand(1, S, h, w, generator=g),
                     colors=torch.rand(1, S, h, w, 3, generator=g))
    video = torch.rand(1, 3, T, h, w, generator=g) * 2.4 - 1.2  # beyond [−1, 1]: the clamp
    sources = torch.tensor([0, 4, 8])
    got = video_colors(out, video, sources)
    assert torch.equal(got.colors[:, 0], out.colors[:, 0]) and got.distance is out.distance
    for j, t in enumerate(sources.tolist()[1:], start=1):
        for y, x in ((0, 0), (3, 4), (2, 1)):
            want = ((video[0, :, t, y, x] + 1) / 2).clamp(0, 1)
            torch.testing.assert_close(got.colors[0, j, y, x], want, atol=0, rtol=0)
    with pytest.raises(ValueError, match="video must have shape"):
        video_colors(out, video[..., :4], sources)
    with pytest.raises(ValueError, match="sources"):
        video_colors(out, video[:, :, :8], sources)


@pytest.mark.slow
def test_generated_colors_video_colours_the_generated_gaussians_with_the_decoded_video(image, monkeypatch):
    """Config ``generated_colors: video``: every kept Gaussian of source frame j ≥ 1 carries the decoded generated
    video's pixel of its own grid cell at video frame sources[j]; with "ldrm" the decoder never runs and they carry
    the LDRM's colours (which differ, so the check can fail)."""
    pipe = Diff4SplatPipeline(tiny_model())
    decoded, maps = [], []
    real_decode, real_reconstruct = pipe.runtime.decode_latents, pipe.runtime.reconstruct
    monkeypatch.setattr(pipe.runtime, "decode_latents", lambda lat: decoded.append(real_decode(lat)) or decoded[-1])
    monkeypatch.setattr(pipe.runtime, "reconstruct", lambda *a: maps.append(real_reconstruct(*a)) or maps[-1])

    def generated_colours(res):
        hw = 64 * 64
        offset = res.num_slots - (len(res.source_frames) - 1) * hw
        gen = res.gaussian_index >= offset
        k = res.gaussian_index[gen] - offset
        assert int(gen.sum()) > 100
        return sh0_to_rgb(res.scene.canonical.sh[gen, 0]), k // hw + 1, k % hw

    res = _run(pipe, image)
    assert decoded == []
    got, j, pix = generated_colours(res)
    ldrm = maps[-1].colors[0].reshape(len(res.source_frames), -1, 3)[j, pix].clamp(1e-4, 1 - 1e-4)
    torch.testing.assert_close(got, ldrm, atol=1e-5, rtol=0)
    monkeypatch.setattr(pipe.config, "generated_colors", "video")
    res = _run(pipe, image)
    assert len(decoded) == 1 and decoded[0].shape == (1, 3, FRAMES, 64, 64)
    got, j, pix = generated_colours(res)
    frames = decoded[0][0].permute(1, 2, 3, 0).reshape(FRAMES, -1, 3)
    want = ((frames[res.source_frames[j], pix] + 1) / 2).clamp(1e-4, 1 - 1e-4)
    torch.testing.assert_close(got, want, atol=1e-5, rtol=0)
    ldrm = maps[-1].colors[0].reshape(len(res.source_frames), -1, 3)[j, pix].clamp(1e-4, 1 - 1e-4)
    assert float((want - ldrm).abs().max()) > 0.05  # the LDRM's own colours are not the video's


@pytest.mark.slow
def test_the_readmes_python_example_runs_and_keeps_the_photo(monkeypatch):
    """The README's Python block, run as written from the repository root: frame 0 of its render is the photograph
    (≥ 60 dB: 77.4 measured; with the renderer's defaults instead of the scene's eps2d and background, as the
    example once rendered, 33.4 dB)."""
    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    (block,) = [b.split("```", 1)[0] for b in readme.split("```python\n")[1:] if "render_path(scene" in b]
    monkeypatch.chdir(Path(__file__).resolve().parents[1])
    names: dict = {}
    exec(compile(block, "README.md", "exec"), names)  # noqa: S102 (the repository's own documentation)
    mse = float(((names["colors"][0] - names["image"]) ** 2).mean())
    assert -10 * math.log10(mse) >= 60.0
