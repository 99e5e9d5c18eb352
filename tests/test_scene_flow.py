"""Scene flow from optical flow and depth (diff4splat/geometry/scene_flow.py): DIS recovers a known translation, chained
tracking follows it and loses what leaves the image, lifting gives the closed-form 3D motion and keeps a static
scene still under a moving camera."""
from pathlib import Path

import pytest
import torch

from diff4splat.cameras import intrinsics_from_fov, look_at
from diff4splat.geometry.scene_flow import (
    chain_flows,
    consecutive_flows,
    lift_tracks,
    optical_flow,
    pixel_centres,
    sample_pixels,
    source_frame_motion,
    track_pixels,
)
from diff4splat.io import load_image

TEXTURE = Path(__file__).resolve().parent.parent / "data_prep" / "textures" / "coins.png"


def _window(image, top, left, size):  # (H, W, 3) → (3, size, size)
    return image[top:top + size, left:left + size].permute(2, 0, 1)


@pytest.fixture(scope="module")
def texture():
    return load_image(TEXTURE)


def test_dis_flow_recovers_a_translation(texture, device):
    # frame b is frame a's window moved by (−3, −2) in the texture: content moves (+3, +2) pixels
    a = _window(texture, 40, 40, 64)[None].to(device)
    b = _window(texture, 38, 37, 64)[None].to(device)
    for up in (1, 4):
        flow = optical_flow(a, b, upsample=up)
        assert flow.shape == (1, 64, 64, 2) and flow.device == a.device
        inner = flow[0, 8:-8, 8:-8].cpu()
        err = (inner - torch.tensor([3.0, 2.0])).norm(dim=-1)
        assert float(err.median()) < 0.25, (up, float(err.median()))


def test_sample_pixels_is_exact_at_centres_and_bilinear_between(device):
    maps = torch.arange(2 * 4 * 5 * 1, dtype=torch.float32, device=device).reshape(2, 4, 5, 1)
    uv = pixel_centres(4, 5, maps)[None].expand(2, 4, 5, 2)
    assert torch.equal(sample_pixels(maps, uv), maps)
    mid = torch.tensor([[[1.0, 0.5]]], device=device).expand(2, 1, 2)  # halfway between columns 0 and 1 of row 0
    assert torch.allclose(sample_pixels(maps, mid)[:, 0, 0], (maps[:, 0, 0, 0] + maps[:, 0, 1, 0]) / 2)


def test_tracking_chains_small_steps_and_loses_pixels_that_leave(texture, device):
    # content moves 2 pixels right per frame; a window-sized jump 0 → 4 (8 px) is chained from 2 px steps
    frames = torch.stack([_window(texture, 60, 60 - 2 * t, 48) for t in range(5)]).to(device)
    pos, ok = track_pixels(frames)
    assert pos.shape == (5, 48, 48, 2) and ok.shape == (5, 48, 48) and pos.device == frames.device
    centres = pixel_centres(48, 48, pos)
    inner = (slice(8, -16), slice(8, -8))  # stays inside the image through frame 4
    err = (pos[4][inner] - centres[inner] - torch.tensor([8.0, 0.0], device=device)).norm(dim=-1)
    assert float(err.median()) < 0.5
    assert bool(ok[4][inner].float().mean() > 0.9)
    # the last columns leave the image: lost, and their positions are held, never outside the image
    assert float(ok[4][:, -4:].float().mean()) < 0.2
    assert float(pos[..., 0].max()) <= 48



def test_an_unchecked_link_is_followed_and_the_check_resumes_after_it(device):
    """Forward flows of +1 px then +2 px, the backward flows of the first link wrong by 3 px (over the 1.5 px
    tolerance): checked, every track is lost at once and held at its start; with ``unchecked=1`` the first link is
    followed (tracked), and the next link goes on from the last position that passed the check, the start."""
    H = W = 8
    fw = torch.zeros(2, H, W, 2, device=device)
    fw[0, ..., 0], fw[1, ..., 0] = 1.0, 2.0
    bw = -fw.clone()
    bw[0, ..., 0] += 3.0
    centres = pixel_centres(H, W, fw)
    pos, ok = chain_flows(fw, bw)
    assert not bool(ok[1:].any()) and torch.equal(pos[2], centres)
    pos, ok = chain_flows(fw, bw, unchecked=1)
    inner = (slice(None), slice(0, W - 3))  # a step of 1 px stays inside
    assert bool(ok[1][inner].all()) and torch.allclose(pos[1][inner], centres[inner] + torch.tensor([1.0, 0.0],
                                                                                                   device=device))
    assert not bool(ok[2].any()) and torch.equal(pos[2], centres)
    bw[0, ..., 0] -= 3.0  # consistent flows: unchecked changes nothing
    assert all(torch.equal(a, b) for a, b in zip(chain_flows(fw, bw), chain_flows(fw, bw, unchecked=1), strict=True))
    with pytest.raises(ValueError, match="unchecked"):
        chain_flows(fw, bw, unchecked=-1)

def _plane_setup(device, T=3):
    K = intrinsics_from_fov(32, 32, fov_x_deg=60.0, dtype=torch.float64)
    Ks = K[None].expand(T, 3, 3).to(device)
    # cameras translating sideways and forward, looking down +z (frame 0 the identity)
    eyes = torch.stack([torch.tensor([0.1 * t, 0.0, 0.05 * t], dtype=torch.float64) for t in range(T)])
    viewmats = look_at(eyes, eyes + torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)).to(device)
    return Ks, viewmats


def _project(points, K, viewmat):  # (N, 3) world → (N, 2) pixels, (N,) z
    cam = points @ viewmat[:3, :3].T + viewmat[:3, 3]
    uv = cam[:, :2] / cam[:, 2:] * K.diagonal()[:2] + K[:2, 2]
    return uv, cam[:, 2]


@pytest.mark.parametrize("motion", [(0.0, 0.0, 0.0), (0.4, -0.2, 0.0)])  # 0.4 m at 3 m: 3.7 px, above the gate
def test_lifting_gives_the_closed_form_motion_and_keeps_static_points_still(device, motion):
    """A fronto-parallel plane at z = 3 m seen by a moving camera; ``motion`` moves the whole plane per frame.
    Positions and depths are exact (the plane's own projections), so lifting must return the true points."""
    T, H, W = 3, 32, 32
    Ks, viewmats = _plane_setup(device, T)
    uv0 = pixel_centres(H, W, Ks).reshape(-1, 2)
    z0 = torch.full((H * W,), 3.0, dtype=torch.float64, device=device)
    first = torch.cat([(uv0 - Ks[0, :2, 2]) / Ks[0].diagonal()[:2] * z0[:, None], z0[:, None]], dim=1)  # camera 0 = I
    step = torch.tensor(motion, dtype=torch.float64, device=device)
    positions, depths = [uv0.reshape(H, W, 2)], [z0.reshape(H, W)]
    for t in range(1, T):
        uv, z = _project(first + t * step, Ks[t], viewmats[t])
        positions.append(uv.reshape(H, W, 2))
        depths.append(torch.full((H, W), float(z[0]), dtype=torch.float64, device=device))  # fronto-parallel plane
    tracked = torch.ones(T, H, W, dtype=torch.bool, device=device)
    points, moving = lift_tracks(torch.stack(positions), tracked, torch.stack(depths), Ks, viewmats)
    assert points.device == Ks.device
    truth = torch.stack([first + t * step for t in range(T)]).reshape(T, H, W, 3)
    assert torch.allclose(points, truth, atol=1e-6)
    assert bool(moving[1:].all()) == bool(step.abs().sum() > 0) and not bool(moving[0].any())
    # a lost track holds its last position
    lost = tracked.clone()
    lost[2] = False
    held, _ = lift_tracks(torch.stack(positions), lost, torch.stack(depths), Ks, viewmats)
    assert torch.allclose(held[2], held[1])
    # depth at frames 0 and 2 only: frame 1's camera-space depth is interpolated, exact for this linear motion
    sparse, _ = lift_tracks(torch.stack(positions), tracked, torch.stack(depths)[[0, 2]], Ks, viewmats,
                            depth_frames=[0, 2])
    assert torch.allclose(sparse, truth, atol=1e-6)


def test_a_static_world_stays_still_under_a_wrong_depth_and_a_moving_camera(device):
    """The plane's true projections under the moving camera, but depth maps at a third of the truth: every pixel
    lies on its epipolar segment, so nothing moves (the camera-only position at the given depth is 1.9-3.7 px off);
    a point moved off that segment (up, across the sideways motion) does."""
    T, H, W = 3, 32, 32
    Ks, viewmats = _plane_setup(device, T)
    uv0 = pixel_centres(H, W, Ks).reshape(-1, 2)
    z0 = torch.full((H * W,), 3.0, dtype=torch.float64, device=device)
    first = torch.cat([(uv0 - Ks[0, :2, 2]) / Ks[0].diagonal()[:2] * z0[:, None], z0[:, None]], dim=1)
    positions = torch.stack([_project(first, Ks[t], viewmats[t])[0].reshape(H, W, 2) for t in range(T)])
    positions[2, 5, 5, 1] -= 4.0  # one point rises 4 px at frame 2
    wrong = torch.full((T, H, W), 1.0, dtype=torch.float64, device=device)  # a third of the true 3 m
    tracked = torch.ones(T, H, W, dtype=torch.bool, device=device)
    points, moving = lift_tracks(positions, tracked, wrong, Ks, viewmats)
    assert int(moving.sum()) == 1 and bool(moving[2, 5, 5])
    assert torch.equal(points[1], points[0]) and float((points[2] - points[0]).norm(dim=-1).max()) > 0


def test_lifting_picks_the_neighbour_depth_consistent_with_the_point(device):
    """A tracked pixel on an object's edge: its own pixel holds the wall's depth, a neighbour the object's. The point
    (static, gate passed by a 3-pixel motion) is lifted at the object's depth, not 10 m away."""
    T, H, W = 2, 16, 16
    Ks, viewmats = _plane_setup(device, T)
    viewmats = viewmats[:1].expand(T, 4, 4).contiguous()  # a still camera
    positions = pixel_centres(H, W, Ks)[None].expand(T, H, W, 2).clone()
    positions[1, 8, 8, 0] += 3.0
    depths = torch.full((T, H, W), 2.0, dtype=torch.float64, device=device)
    depths[1, 8, 11] = 10.0  # the wall shows at the pixel the point moved to; its left neighbour is the object
    tracked = torch.ones(T, H, W, dtype=torch.bool, device=device)
    points, moving = lift_tracks(positions, tracked, depths, Ks, viewmats)
    assert bool(moving[1, 8, 8]) and int(moving[1].sum()) == 1
    assert abs(float(points[1, 8, 8, 2]) - 2.0) < 1e-9


def test_source_frames_move_with_the_video(texture, device):
    """Content moving 2 px right per frame before a still camera, on a plane 2 m away: every source frame's pixels
    move (t − f)·2 px·z/f_x metres along x, before and after their own frame f, and not at all along z."""
    T, size = 5, 48
    frames = torch.stack([_window(texture, 60, 60 - 2 * t, size) for t in range(T)]).to(device)
    K = intrinsics_from_fov(size, size, fov_x_deg=60.0, dtype=torch.float64).to(device)
    Ks, viewmats = K[None].expand(T, 3, 3), torch.eye(4, dtype=torch.float64, device=device)[None].expand(T, 4, 4)
    depths = torch.full((2, size, size), 2.0, dtype=torch.float64, device=device)
    d = source_frame_motion(frames, depths, [0, 4], Ks, viewmats)
    assert d.shape == (T, 2, size, size, 3) and d.device == frames.device
    inner = (slice(12, -12), slice(12, -12))
    metres_per_px = 2.0 / float(K[0, 0])
    for s, f in enumerate([0, 4]):
        assert float(d[f, s].abs().max()) == 0.0
        for t in range(T):
            if abs(t - f) < 2:  # within the gate of 2 px: held still
                continue
            dx = d[t, s][inner][..., 0]
            assert abs(float(dx.median()) - (t - f) * 2 * metres_per_px) < 0.25 * metres_per_px, (s, t)
            assert float(d[t, s][inner][..., 2].abs().median()) < 1e-6


def test_a_span_gives_the_whole_clips_motion_within_it_and_zero_outside(texture, device):
    """Tracking is causal and a span ends on source frames, so each source's motion within its span is the whole
    clip's to the bit (content that accelerates, with varied depth so the depth interpolation matters), and zero
    outside."""
    T, size = 7, 40
    frames = torch.stack([_window(texture, 60, 60 - t * t // 2, size) for t in range(T)]).to(device)
    K = intrinsics_from_fov(size, size, fov_x_deg=60.0, dtype=torch.float64).to(device)
    Ks, viewmats = K[None].expand(T, 3, 3), torch.eye(4, dtype=torch.float64, device=device)[None].expand(T, 4, 4)
    sources = [0, 2, 3, 6]
    depths = (2.0 + torch.rand(len(sources), size, size, dtype=torch.float64,
                               generator=torch.Generator().manual_seed(0))).to(device)
    flows = consecutive_flows(frames)
    whole = source_frame_motion(frames, depths, sources, Ks, viewmats, flows=flows, gate_px=0.5)
    spans = [(0, 6), (0, 3), (2, 6), (3, 6)]
    part = source_frame_motion(frames, depths, sources, Ks, viewmats, flows=flows, gate_px=0.5, spans=spans)
    assert all(float(whole[f, s].abs().max()) == 0.0 for s, f in enumerate(sources))  # each source at home
    for s, (lo, hi) in enumerate(spans):
        assert torch.equal(part[lo:hi + 1, s], whole[lo:hi + 1, s]), s
        assert float(part[:lo, s].abs().sum() + part[hi + 1:, s].abs().sum()) == 0.0
        assert float(whole[lo:hi + 1, s].abs().max()) > 0 or s == 3
    assert float(whole[[0, 1, 6], 1].abs().max()) > 0  # what the span of source 1 leaves out was motion


def test_bad_spans_are_refused(device):
    frames = torch.rand(5, 3, 8, 8, device=device)
    Ks, viewmats = _plane_setup(device, 5)
    depths = torch.ones(2, 8, 8, device=device)
    for spans in ([(0, 4)], [(1, 4), (0, 4)], [(0, 5), (0, 4)], [(0, 3), (2, 4)], [(0, 2.0), (0, 4)]):
        with pytest.raises(ValueError, match="spans"):
            source_frame_motion(frames, depths, [0, 2], Ks, viewmats, spans=spans)


def test_bad_inputs_are_refused(device):
    frames = torch.rand(2, 3, 8, 8, device=device)
    with pytest.raises(ValueError, match="preset"):
        optical_flow(frames, frames, preset="slow")
    with pytest.raises(ValueError, match="src and dst"):
        optical_flow(frames, frames[:1])
    with pytest.raises(ValueError, match="fb_tolerance"):
        track_pixels(frames, fb_tolerance=0)
    Ks, viewmats = _plane_setup(device, 2)
    pos, ok = track_pixels(frames)
    with pytest.raises(ValueError, match="finite and > 0"):
        lift_tracks(pos, ok, torch.zeros(2, 8, 8, device=device), Ks, viewmats)
    with pytest.raises(ValueError, match="depth_frames"):
        lift_tracks(pos, ok, torch.ones(1, 8, 8, device=device), Ks, viewmats, depth_frames=[1])
    with pytest.raises(ValueError, match="sources"):
        source_frame_motion(frames, torch.ones(2, 8, 8, device=device), [1, 0], Ks, viewmats)
