"""The LDRM's motion network (models/motion.py) and the motion path (diff4splat/assembly/frame_motion.py)."""
from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F
from helpers import EXAMPLE_IMAGE, tiny_model

import diff4splat.pipeline as pipeline_module
from diff4splat.assembly.frame_motion import frame_motion, nearest_frames
from diff4splat.cameras import camera_rays, project_points, unproject_pixels
from diff4splat.io import load_image
from diff4splat.pipeline import Diff4SplatPipeline
from diff4splat.scene.dynamic import DynamicGaussians
from diff4splat.scene.gaussians import Gaussians
from models.ldrm import LDRMOutput
from models.motion import (
    MotionConfig,
    MotionNetwork,
    correlation,
    correlation_reference,
    motion_activations,
)


def _pyramid(x: torch.Tensor, levels: int) -> list[torch.Tensor]:
    out = [x]
    for _ in range(levels - 1):
        out.append(F.avg_pool2d(out[-1], 2))
    return out


def test_correlation_equals_the_per_pixel_bilinear_reference():
    g = torch.Generator().manual_seed(0)
    src = _pyramid(torch.randn(2, 3, 8, 8, generator=g), 2)
    tgt = _pyramid(torch.randn(2, 3, 8, 8, generator=g), 2)
    uv = torch.rand(2, 8, 8, 2, generator=g) * 10 - 1  # some look-ups fall outside the frame (zeros)
    torch.testing.assert_close(correlation(src, tgt, uv, 1), correlation_reference(src, tgt, uv, 1),
                               atol=1e-5, rtol=1e-5)


def test_correlation_at_an_integer_shift_is_the_cosine_of_the_matching_pixels():
    g = torch.Generator().manual_seed(1)
    f = torch.randn(1, 4, 10, 10, generator=g)
    ys, xs = torch.meshgrid(torch.arange(10.0), torch.arange(10.0), indexing="ij")
    uv = torch.stack([xs + 0.5, ys + 0.5], dim=-1)[None]  # each pixel's own centre
    corr = correlation([f], [f], uv, 1)  # (1, 9, 10, 10), offset (dx, dy) = channel (dy+1)·3 + dx+1
    torch.testing.assert_close(corr[:, 4], torch.ones(1, 10, 10))  # offset (0, 0): the pixel itself
    right = F.cosine_similarity(f[0, :, :, :-1], f[0, :, :, 1:], dim=0)
    torch.testing.assert_close(corr[0, 5, :, :-1], right)  # offset (1, 0): the right neighbour
    assert torch.all(corr[0, 5, :, -1] == 0)  # beyond the right border: zeros, similarity 0


def test_a_fresh_network_is_the_identity_and_a_static_scene_keeps_no_deformation():
    net = MotionNetwork(MotionConfig(features=4, hidden=8, levels=2, radius=1))
    T, H, W = 5, 16, 16
    g = torch.Generator().manual_seed(2)
    frames = torch.rand(T, 3, H, W, generator=g)
    K = torch.tensor([[20.0, 0, 8], [0, 20.0, 8], [0, 0, 1]]).expand(T, 3, 3)
    vm = torch.eye(4).repeat(T, 1, 1)
    vm[:, 0, 3] = torch.linspace(0, 0.3, T)  # a moving camera: its motion is the geometry's, not the scene's
    out = LDRMOutput(distance=torch.full((1, 2, H, W), 2.0), scales=None, quats=None, opacities=None, colors=None)
    times = torch.linspace(0, 1, T)
    moved = frame_motion(net, out, frames[None], times[None], vm[None], K[None], torch.tensor([0, 4]), times[None])
    assert torch.all(moved.d_means == 0) and torch.all(moved.d_scales == 0)
    assert torch.all(moved.d_quats == torch.tensor([1.0, 0, 0, 0]))
    g = Gaussians(torch.zeros(2 * H * W, 3), torch.ones(2 * H * W, 4) / 2, torch.full((2 * H * W, 3), 0.01),
                  torch.ones(2 * H * W), torch.zeros(2 * H * W, 1, 3))
    scene = DynamicGaussians(g, times, moved.d_means[0].flatten(1, 3), moved.d_quats[0].flatten(1, 3),
                             moved.d_scales[0].flatten(1, 3))
    assert scene.without_deformation(1e-6).is_static


def test_activations_threshold_exactly_and_pass_gradients_through_the_dead_zone():
    cfg = MotionConfig(min_flow=0.5)
    raw = torch.zeros(1, 4, 2, 2, requires_grad=True)
    match = torch.tensor([0.3, 0.0]).expand(1, 2, 2, 2)
    flow, log_depth = motion_activations(raw, match, cfg)
    assert torch.all(flow == 0) and torch.all(log_depth == 0)  # a closed gate: no motion
    (flow.sum() + log_depth.sum()).backward()
    assert raw.grad[:, 0].abs().sum() > 0  # the gate learns from the match…
    assert raw.grad[:, 1:].abs().sum() > 0  # …and the residual and the depth ratio get gradients at 0
    big = torch.zeros(1, 4, 1, 1)
    big[:, 1] = 2.0  # 2 px residual, gate closed
    flow, log_depth = motion_activations(big, torch.zeros(1, 1, 1, 2), cfg)
    expected = cfg.max_flow * math.tanh(2.0 / cfg.max_flow) - 0.5  # soft clamp, then shrunk by τ
    torch.testing.assert_close(flow[0, 0, 0], torch.tensor([expected, 0.0]))


def test_matching_recovers_an_integer_shift_beyond_one_levels_window():
    net = MotionNetwork(MotionConfig(features=8, hidden=8, levels=3, radius=2))
    g = torch.Generator().manual_seed(3)
    # features that stay distinct when pooled 4× (the coarse levels): noise with a 2-pixel correlation length
    base = F.interpolate(torch.randn(1, 8, 24, 24, generator=g), size=(48, 48), mode="bilinear")
    shift = (5, -3)  # pixels (dx, dy): beyond level 0's ±2 window, inside level 2's ±8
    target = torch.roll(base, shifts=(shift[1], shift[0]), dims=(2, 3))
    ys, xs = torch.meshgrid(torch.arange(48.0), torch.arange(48.0), indexing="ij")
    uv = torch.stack([xs + 0.5, ys + 0.5], dim=-1)[None]
    with torch.no_grad():
        net.log_sharpness.fill_(math.log(100.0))
        flow, _ = net.match(_pyramid(base, 3), _pyramid(target, 3), uv)
    inner = flow[0, 12:-12, 12:-12]  # away from the wrapped borders
    err = (inner - torch.tensor(shift, dtype=torch.float32)).norm(dim=-1)
    assert err.median() < 0.25, err.median()


def test_frame_motion_lifts_a_flow_to_its_closed_form_3d_displacement(monkeypatch):
    net = MotionNetwork(MotionConfig(features=4, hidden=8, levels=2, radius=1))
    T, H, W, f, z = 3, 8, 8, 10.0, 2.0
    step = torch.tensor([1.5, -1.0])  # pixels per key time

    def constant_flow(source, target, uv):
        return step.expand(uv.shape), torch.zeros(uv.shape[:-1])
    monkeypatch.setattr(net, "forward", constant_flow)
    K = torch.tensor([[f, 0, 4], [0, f, 4], [0, 0, 1]]).expand(T, 3, 3)
    vm = torch.eye(4).repeat(T, 1, 1)
    times = torch.linspace(0, 1, T)
    out = LDRMOutput(distance=torch.full((1, 1, H, W), z), scales=None, quats=None, opacities=None, colors=None)
    # distance along each ray = z-depth / cos: place every pixel at z-depth 2 m
    _, dirs = camera_rays(vm[:1], K[:1], W, H)
    out.distance = (z / dirs[..., 2])[None]
    moved = frame_motion(net, out, torch.rand(1, T, 3, H, W), times[None], vm[None], K[None], torch.tensor([0]),
                         times[None])
    for k in range(T):  # the window follows the point: k steps of the flow, at constant depth
        expected = torch.cat([step * k * z / f, torch.zeros(1)])
        torch.testing.assert_close(moved.d_means[0, k, 0], expected.expand(H, W, 3), atol=1e-5, rtol=0)


def test_project_and_unproject_are_inverse_and_use_pixel_centres():
    g = torch.Generator().manual_seed(4)
    vm = torch.eye(4)
    vm[:3, 3] = torch.tensor([0.1, -0.2, 0.3])
    K = torch.tensor([[30.0, 0, 16], [0, 32.0, 12], [0, 0, 1]])
    uv = torch.rand(5, 2, generator=g) * 20
    z = torch.rand(5, generator=g) + 1
    points = unproject_pixels(uv, z, vm, K)
    uv2, z2 = project_points(points, vm, K)
    torch.testing.assert_close(uv2, uv)
    torch.testing.assert_close(z2, z)
    o, d = camera_rays(vm[None], K[None], 4, 3)  # pixel (i, j) = (1, 2): centre (2.5, 1.5)
    uv3, _ = project_points(o[0, 1, 2] + 2.0 * d[0, 1, 2], vm, K)
    torch.testing.assert_close(uv3, torch.tensor([2.5, 1.5]))


def test_a_batch_of_scenes_moves_as_each_scene_alone():
    """frame_motion on B = 3 scenes at once (different frames, cameras, depths and key times) equals three calls of
    one scene each, with a network whose output is not zero (its gate open), so pixels move."""
    torch.manual_seed(0)
    net = MotionNetwork(MotionConfig(features=4, hidden=8, levels=2, radius=1, min_flow=0.1))
    torch.nn.init.normal_(net.out.weight, std=0.5)
    torch.nn.init.normal_(net.out.bias, std=0.5)
    B, T, S, H, W = 3, 5, 2, 12, 12
    g = torch.Generator().manual_seed(1)
    frames = torch.rand(B, T, 3, H, W, generator=g)
    vm = torch.eye(4).repeat(B, T, 1, 1)
    vm[..., :3, 3] = torch.rand(B, T, 3, generator=g) * 0.2
    K = torch.tensor([[15.0, 0, 6], [0, 15.0, 6], [0, 0, 1]]).repeat(B, T, 1, 1)
    K[:, :, 0, 0] += torch.arange(B)[:, None]
    frame_times = torch.linspace(0, 1, T).repeat(B, 1)
    times = torch.stack([torch.linspace(0, 1, 4), torch.tensor([0.0, 0.2, 0.6, 1.0]), torch.linspace(0.1, 0.9, 4)])
    out = LDRMOutput(distance=1 + torch.rand(B, S, H, W, generator=g), scales=None, quats=None, opacities=None,
                     colors=None, d_quats=torch.randn(B, 4, S, H, W, 4, generator=g),
                     d_scales=torch.randn(B, 4, S, H, W, 3, generator=g))
    sources = torch.tensor([0, 3])
    with torch.no_grad():
        batched = frame_motion(net, out, frames, frame_times, vm, K, sources, times)
        assert batched.d_means.shape == (B, 4, S, H, W, 3) and batched.d_means.abs().amax() > 0.01
        for b in range(B):
            one = LDRMOutput(**{k: None if v is None else v[b:b + 1] for k, v in vars(out).items()})
            alone = frame_motion(net, one, frames[b:b + 1], frame_times[b:b + 1], vm[b:b + 1], K[b:b + 1], sources,
                                 times[b:b + 1])
            for name in ("d_means", "d_quats", "d_scales"):
                torch.testing.assert_close(getattr(batched, name)[b:b + 1], getattr(alone, name))


def test_nearest_frames_picks_the_closest_time():
    frames = torch.tensor([0.0, 0.25, 0.5, 0.75, 1.0])
    assert nearest_frames(torch.tensor([0.0, 0.3, 0.74, 1.0]), frames).tolist() == [0, 1, 3, 4]


def test_frame_motion_refuses_frames_that_do_not_match_the_maps():
    net = MotionNetwork(MotionConfig(features=4, hidden=8, levels=2, radius=1))
    out = LDRMOutput(distance=torch.full((1, 1, 8, 8), 2.0), scales=None, quats=None, opacities=None, colors=None)
    T = 3
    with pytest.raises(ValueError, match="must agree"):
        frame_motion(net, out, torch.rand(1, T, 3, 16, 16), torch.linspace(0, 1, T)[None],
                     torch.eye(4).repeat(1, T, 1, 1), torch.eye(3).repeat(1, T, 1, 1), torch.tensor([0]),
                     torch.linspace(0, 1, T)[None])


@pytest.fixture(scope="module")
def image():
    return load_image(EXAMPLE_IMAGE, size=(64, 64))


@pytest.mark.slow
def test_generate_reads_motion_from_the_decoded_frames(image, monkeypatch):
    model = tiny_model(seed=0, dynamic=True, motion=True)
    pipe = Diff4SplatPipeline(model)
    assert pipe.runtime.has_motion
    seen = {}

    def spy(net, out, frames, *args):
        seen["frames"] = frames
        return frame_motion(net, out, frames, *args)
    monkeypatch.setattr(pipeline_module, "frame_motion", spy)
    cams = pipe.default_cameras("orbit", 9)
    res = pipe(image, cams, "it moves", steps=1)
    frames = seen["frames"]
    assert frames.shape == (1, 9, 3, 64, 64) and frames.min() >= 0 and frames.max() <= 1
    decoded = ((pipe.runtime.decode_latents(res.latents)[0].transpose(0, 1) + 1) / 2).clamp(0, 1)
    torch.testing.assert_close(frames[0], decoded)
    assert not res.scene.is_static and res.scene.d_means.abs().max() > 0


@pytest.mark.slow
def test_a_still_motion_network_makes_the_scene_static_whatever_the_token_network_says(image):
    model = tiny_model(seed=0, dynamic=True, motion=True)  # the token network's maps are not the identity
    with torch.no_grad():
        model.ldrm.motion.out.weight.zero_()
        model.ldrm.motion.out.bias.zero_()
    pipe = Diff4SplatPipeline(model)
    res = pipe(image, pipe.default_cameras("orbit", 9), "it moves", steps=1)
    assert res.scene.is_static and res.scene.times is None  # no deformation file


def test_the_runtime_lends_its_motion_network_only_where_there_is_one():
    """``motion_network()`` yields the LDRM's own motion network (the one ``frame_motion`` calls); a model without one
    refuses with a ValueError naming ``has_motion``."""
    model = tiny_model(seed=0, dynamic=True, motion=True)
    with Diff4SplatPipeline(model).runtime.motion_network() as net:
        assert net is model.ldrm.motion
    runtime = Diff4SplatPipeline(tiny_model(seed=0, dynamic=True)).runtime
    assert not runtime.has_motion
    with pytest.raises(ValueError, match="has_motion is False"), runtime.motion_network():
        pass
