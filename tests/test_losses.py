import math

import kornia
import pytest
import torch
import torch.nn.functional as F

from diff4splat.cameras import camera_rays
from training.losses import (
    depth_correlation_loss,
    depth_smoothness_loss,
    displacement_loss,
    flow_matching_loss,
    gather_track_predictions,
    head_distillation_loss,
    log_depth_loss,
    motion_loss,
    moving_cells,
    photometric_loss,
    sample_training_sigmas,
    warp_loss,
)


def test_flow_matching_loss_is_zero_for_the_exact_velocity_and_closed_form_otherwise():
    g = torch.Generator().manual_seed(0)
    x0, eps = torch.randn(2, 4, 3, 8, 8, generator=g), torch.randn(2, 4, 3, 8, 8, generator=g)
    sigma = torch.tensor([0.3, 0.8])
    exact = lambda x, s: eps - x0  # noqa: E731  the conditional target
    assert flow_matching_loss(exact, x0, eps, sigma) == 0
    zero = lambda x, s: torch.zeros_like(x)  # noqa: E731
    torch.testing.assert_close(flow_matching_loss(zero, x0, eps, sigma), ((eps - x0) ** 2).mean())
    seen = []
    flow_matching_loss(lambda x, s: seen.append((x, s)) or x, x0, eps, sigma)
    torch.testing.assert_close(seen[0][0], (1 - sigma.view(2, 1, 1, 1, 1)) * x0 + sigma.view(2, 1, 1, 1, 1) * eps)


def test_moving_cells_match_a_per_point_loop_and_leave_still_scenes_empty():
    """Every moving pixel's point, projected at each frame, marks its latent cell (brute force: one point at a time);
    still points and points behind the camera mark none; latent frame 0 stays empty."""
    g = torch.Generator().manual_seed(3)
    B, T, H, W, n, h, w, tf = 2, 9, 16, 24, 3, 4, 6, 4
    K = torch.tensor([[20.0, 0, 12], [0, 20.0, 8], [0, 0, 1]])
    Ks = K.expand(B, T, 3, 3)
    viewmats = torch.eye(4).repeat(B, T, 1, 1)
    viewmats[..., 0, 3] = torch.linspace(0, 0.3, T)  # a camera sliding along x
    base = torch.cat([torch.rand(B, 1, H, W, 2, generator=g) * 2 - 1, 2 + torch.rand(B, 1, H, W, 1, generator=g)], -1)
    tracks = base.repeat(1, T, 1, 1, 1)
    movers = torch.rand(B, H, W, generator=g) < 0.2
    step = torch.linspace(0, 1, T)[None, :, None, None, None] * torch.tensor([0.6, -0.4, 0.0])
    tracks = torch.where(movers[:, None, ..., None], tracks + step, tracks)
    tracks[0, :, 0, 0, 2] = -1.0  # behind the camera throughout (and moving: its x changes)
    movers[0, 0, 0] = True
    valid = torch.ones(B, H, W, dtype=torch.bool)
    cells = moving_cells(tracks, valid, viewmats, Ks, (n, h, w), tf)
    expected = torch.zeros(B, n, h, w, dtype=torch.bool)
    for b, y, x in movers.nonzero().tolist():
        for t in range(1, T):
            p = viewmats[b, t, :3, :3] @ tracks[b, t, y, x] + viewmats[b, t, :3, 3]
            if p[2] <= 0:
                continue
            u, v = float(K[0, 0] * p[0] / p[2] + K[0, 2]), float(K[1, 1] * p[1] / p[2] + K[1, 2])
            if 0 <= u < W and 0 <= v < H:
                expected[b, 1 + (t - 1) // tf, int(v // (H // h)), int(u // (W // w))] = True
    assert expected.any() and not expected[:, 0].any()
    assert torch.equal(cells, expected)
    # a point 0.01 px left of a cell's edge (u = 7.99, cells 4 px wide) stays in its cell under bf16 autocast, as a
    # bf16 training step calls it (bfloat16 rounds u to 8.0)
    edge = torch.tensor([-0.401, 0.0, 2.0]).expand(1, 5, H, W, 3).clone()
    edge[:, 0, ..., 0] = 0.3  # frame 0 elsewhere: the point moves
    one = torch.zeros(1, H, W, dtype=torch.bool)
    one[0, 0, 0] = True
    with torch.autocast("cpu", dtype=torch.bfloat16):
        got = moving_cells(edge, one, torch.eye(4).expand(1, 5, 4, 4), K.expand(1, 5, 3, 3), (2, h, w), 4)
    assert got[0, 1].nonzero().tolist() == [[2, 1]]  # row v = 8 // 4, column 7.99 // 4
    still = moving_cells(base.repeat(1, T, 1, 1, 1), valid, viewmats, Ks, (n, h, w), tf)
    assert not still.any()
    with pytest.raises(ValueError, match="latent grid"):
        moving_cells(tracks, valid, viewmats, Ks, (2, h, w), tf)


def test_training_sigmas_are_logit_normal_and_shifted():
    g = torch.Generator().manual_seed(0)
    s = sample_training_sigmas(200_000, generator=g)
    assert 0 < s.min() and s.max() < 1
    logits = torch.log(s / (1 - s))
    assert abs(float(logits.mean())) < 0.01 and abs(float(logits.std()) - 1) < 0.01
    g = torch.Generator().manual_seed(0)
    shifted = sample_training_sigmas(200_000, shift=3.0, generator=g)
    torch.testing.assert_close(shifted, 3 * s / (1 + 2 * s))


def test_photometric_loss_closed_forms():
    img = torch.rand(2, 3, 32, 32, generator=torch.Generator().manual_seed(1))
    assert float(photometric_loss(img, img)) == pytest.approx(0.0, abs=1e-6)
    # a constant offset c: L1 = c; SSIM of x and x + c is the luminance term only
    c = 0.1
    l1_only = photometric_loss(img, img + c, ssim_weight=0.0)
    assert float(l1_only) == pytest.approx(c, rel=1e-5)
    # pure SSIM term equals 1 − kornia's mean SSIM

    torch.testing.assert_close(photometric_loss(img, img * 0.5, ssim_weight=1.0),
                               1 - kornia.metrics.ssim(img, img * 0.5, 11).mean())
    with pytest.raises(ValueError):
        photometric_loss(img, img[:, :, :16])


def test_depth_correlation_is_invariant_to_scale_and_shift_and_finite_when_constant():
    g = torch.Generator().manual_seed(2)
    ref = torch.rand(2, 16, 16, generator=g) + 1
    # eps = 1e-6 in the variances moves ρ by ~eps/var ≈ 1e-5 for var ≈ 1/12
    assert float(depth_correlation_loss(3.0 * ref + 2.0, ref)) == pytest.approx(0.0, abs=1e-4)
    assert float(depth_correlation_loss(-ref, ref)) == pytest.approx(2.0, abs=1e-4)  # ρ = −1
    const = torch.ones(2, 16, 16)
    loss = depth_correlation_loss(const, ref)
    assert torch.isfinite(loss) and float(loss) == pytest.approx(1.0, abs=1e-4)
    pred = const.clone().requires_grad_()
    depth_correlation_loss(pred, ref).backward()
    assert torch.isfinite(pred.grad).all()


def test_depth_correlation_ignores_invalid_pixels():
    g = torch.Generator().manual_seed(3)
    ref = torch.rand(1, 8, 8, generator=g) + 1
    pred = 2 * ref
    valid = torch.ones_like(ref, dtype=torch.bool)
    valid[0, :2] = False
    pred_bad = pred.clone()
    pred_bad[0, :2] = 1000.0  # garbage where invalid
    ref_bad = ref.clone()
    ref_bad[0, 0, 0] = math.inf
    assert float(depth_correlation_loss(pred_bad, ref_bad, valid)) == pytest.approx(0.0, abs=1e-5)


def test_log_depth_loss_weighs_the_scale_error_by_one_minus_lambda():
    g = torch.Generator().manual_seed(0)
    ref = torch.rand(2, 8, 8, generator=g) * 5 + 0.5
    for lam in (0.0, 0.5, 1.0):  # a pure scale error c: g = log c everywhere, L = (1 − λ)·log²c
        assert float(log_depth_loss(1.3 * ref, ref, lam=lam)) == pytest.approx((1 - lam) * math.log(1.3) ** 2,
                                                                              abs=1e-6)
    pred = ref * torch.exp(torch.randn(2, 8, 8, generator=g) * 0.3)
    valid = torch.rand(2, 8, 8, generator=g) > 0.3
    valid[1] = False  # an image with no valid pixel contributes 0 to the mean over images
    pred[0, 0, 0] = float("nan")  # left out: not finite
    valid[0, 0, 0] = True
    d = (pred[0].log() - ref[0].log())[valid[0] & torch.isfinite(pred[0])].double()
    expected = ((d ** 2).mean() - 0.5 * d.mean() ** 2) / 2  # brute force, one loop-free line per image
    assert float(log_depth_loss(pred, ref, valid, lam=0.5)) == pytest.approx(float(expected), rel=1e-5)


def test_log_depth_loss_gradient_is_finite_at_invalid_pixels_and_rejects_bad_input():
    pred = torch.tensor([[[1.0, 0.0], [-2.0, 3.0]]], requires_grad=True)
    ref = torch.tensor([[[2.0, 1.0], [1.0, 0.0]]])
    log_depth_loss(pred, ref).backward()
    assert torch.isfinite(pred.grad).all() and float(pred.grad[0, 0, 1]) == 0.0
    with pytest.raises(ValueError, match="lam"):
        log_depth_loss(pred, ref, lam=1.5)
    with pytest.raises(ValueError, match="B, H, W"):
        log_depth_loss(pred[0], ref[0])


def test_smoothness_zero_for_constant_depth_and_down_weighted_at_image_edges():
    img = torch.zeros(1, 3, 16, 16)
    assert float(depth_smoothness_loss(torch.full((1, 16, 16), 2.0), img)) == 0.0
    depth = torch.ones(1, 16, 16)
    depth[..., 8:] = 2.0  # a vertical depth edge
    flat = depth_smoothness_loss(depth, img)
    img_edge = img.clone()
    img_edge[..., 8:] = 1.0  # the same edge in the image
    aligned = depth_smoothness_loss(depth, img_edge)
    torch.testing.assert_close(aligned, flat * math.exp(-1.0))


def test_motion_loss_is_masked_mean_end_point_error():
    pred = torch.zeros(1, 2, 3, 3)
    target = torch.zeros(1, 2, 3, 3)
    target[0, 0, :, 0] = 3.0  # track 0 is 3 m off at every time
    target[0, 1, :, 1] = 100.0  # track 1 is far off but invisible
    vis = torch.zeros(1, 2, 3, dtype=torch.bool)
    vis[0, 0] = True
    assert float(motion_loss(pred, target, vis)) == pytest.approx(3.0)
    assert float(motion_loss(pred, target, torch.zeros_like(vis))) == 0.0
    p = pred.clone().requires_grad_()
    motion_loss(p, pred, vis).backward()  # distance 0: gradient must stay finite
    assert torch.isfinite(p.grad).all()


def test_gather_track_predictions_follows_pixel_aligned_gaussians():
    B, T, M = 1, 4, 6
    means = torch.arange(M * 3, dtype=torch.float32).reshape(1, M, 3)
    d = torch.randn(B, T, M, 3)
    idx = torch.tensor([[5, 0, 2]])
    out = gather_track_predictions(means, d, idx)
    assert out.shape == (1, 3, T, 3)
    for p, m in enumerate(idx[0].tolist()):
        torch.testing.assert_close(out[0, p], means[0, m] + d[0, :, m])


def test_displacement_loss_ignores_frame_0_offsets_and_matches_a_loop():
    """A prediction off by a constant (wrong depth, right motion) has zero displacement loss; otherwise the
    loss is the mean over (p, t ≥ 1) visible at 0 and at t of ‖(x̂_t − x̂_0) − (x_t − x_0)‖."""
    g = torch.Generator().manual_seed(0)
    target = torch.randn(1, 5, 4, 3, generator=g)
    vis = torch.rand(1, 5, 4, generator=g) > 0.3
    assert float(displacement_loss(target + torch.tensor([0.3, -1.0, 2.0]), target, vis)) < 1e-5
    pred = torch.randn(1, 5, 4, 3, generator=g)
    terms = [float(((pred[0, p, t] - pred[0, p, 0]) - (target[0, p, t] - target[0, p, 0])).norm())
             for p in range(5) for t in range(1, 4) if vis[0, p, 0] and vis[0, p, t]]
    assert terms
    assert float(displacement_loss(pred, target, vis)) == pytest.approx(sum(terms) / len(terms), rel=1e-5)


def test_photometric_loss_is_float32_inside_a_bfloat16_autocast_region(monkeypatch):
    """SSIM's variances (E[x²] − μ², ~1e-3 here) would drown in bfloat16 rounding under the trainer's autocast:
    the loss runs SSIM with autocast off (on every device type) on float32 images, and so returns the float32
    value."""
    seen = []
    real = kornia.metrics.ssim

    def spy(x, y, *a, **k):
        seen.append((torch.is_autocast_enabled("cpu"), torch.is_autocast_enabled("cuda"), x.dtype, y.dtype))
        return real(x, y, *a, **k)

    monkeypatch.setattr(kornia.metrics, "ssim", spy)
    g = torch.Generator().manual_seed(0)
    a = torch.rand(2, 3, 24, 24, generator=g)
    b = (a + 0.05 * torch.randn(2, 3, 24, 24, generator=g)).clamp(0, 1)
    ref = photometric_loss(a, b)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        got = photometric_loss(a.bfloat16(), b)
    assert seen[-1] == (False, False, torch.float32, torch.float32)
    assert got.dtype == torch.float32
    torch.testing.assert_close(got, ref, atol=1e-3, rtol=0)  # only a's bfloat16 rounding remains


def _blur_by_hand(x: torch.Tensor, sigma: float) -> torch.Tensor:
    """(N, C, H, W) blurred by a normalised Gaussian of radius ⌈3σ⌉, borders replicated, as two 1-D passes."""
    r = math.ceil(3 * sigma)
    k = torch.exp(-torch.arange(-r, r + 1, dtype=x.dtype) ** 2 / (2 * sigma**2))
    k = k / k.sum()
    C = x.shape[1]
    x = F.conv2d(F.pad(x, (r, r, 0, 0), mode="replicate"), k.view(1, 1, 1, -1).expand(C, 1, 1, -1), groups=C)
    return F.conv2d(F.pad(x, (0, 0, r, r), mode="replicate"), k.view(1, 1, -1, 1).expand(C, 1, -1, 1), groups=C)


def test_head_distillation_loss_closed_form_and_blur():
    g = torch.Generator().manual_seed(0)
    student, teacher = torch.randn(2, 12, 3, 16, 16, generator=g), torch.randn(2, 12, 3, 16, 16, generator=g)
    torch.testing.assert_close(head_distillation_loss(student, teacher, 0.0), ((student - teacher) ** 2).mean())
    assert head_distillation_loss(teacher, teacher, 0.0) == 0
    sigma = 1.3
    blurred = _blur_by_hand(teacher.transpose(1, 2).reshape(6, 12, 16, 16), sigma).reshape(2, 3, 12, 16, 16)
    blurred = blurred.transpose(1, 2)
    torch.testing.assert_close(head_distillation_loss(student, teacher, sigma), ((student - blurred) ** 2).mean())
    assert head_distillation_loss(blurred, teacher, sigma) < 1e-10
    # an 8×8 block pattern: the blurred target has a smaller jump across a block border than the teacher
    blocks = torch.randn(1, 12, 1, 2, 2, generator=g).repeat_interleave(8, -1).repeat_interleave(8, -2)
    target = _blur_by_hand(blocks[:, :, 0], sigma)
    assert (target[..., 8] - target[..., 7]).abs().mean() < 0.5 * (blocks[..., 8] - blocks[..., 7]).abs().mean()
    student.requires_grad_(True)
    head_distillation_loss(student, teacher.requires_grad_(True), sigma).backward()
    assert teacher.grad is None and student.grad.abs().sum() > 0, "the teacher's maps are a target, not trained"


@pytest.mark.parametrize("sigma", [-0.5, float("nan"), float("inf")])
def test_head_distillation_loss_rejects_bad_sigma(sigma):
    x = torch.zeros(1, 12, 1, 8, 8)
    with pytest.raises(ValueError, match="sigma"):
        head_distillation_loss(x, x, sigma)


def test_head_distillation_loss_rejects_mismatched_maps():
    with pytest.raises(ValueError, match="one shape"):
        head_distillation_loss(torch.zeros(1, 12, 1, 8, 8), torch.zeros(1, 12, 2, 8, 8), 1.0)


def test_smoothness_counts_only_valid_pixels():
    """An uncovered pixel renders depth 0: it swamped the per-image normaliser and its edges scored a constant
    covered depth 0.257 instead of 0."""
    img = torch.rand(1, 3, 16, 16, generator=torch.Generator().manual_seed(0))
    depth = torch.full((1, 16, 16), 2.0, requires_grad=True)
    hole = torch.zeros(1, 16, 16, dtype=torch.bool)
    hole[..., 4:8] = True
    rendered = torch.where(hole, torch.zeros_like(depth), depth)  # the renderer's depth of uncovered pixels
    loss = depth_smoothness_loss(rendered, img, ~hole)
    loss.backward()
    assert float(loss.detach()) == 0.0 and float(depth.grad.abs().max()) == 0.0
    assert float(depth_smoothness_loss(rendered.detach(), img)) == 0.0  # depth 0 is never valid
    # on the valid pixels it is the loss of the valid region alone: a crop of the right half
    ramp = 1.0 + torch.arange(16.0).expand(1, 16, 16) / 4
    right = torch.zeros(1, 16, 16, dtype=torch.bool)
    right[..., 8:] = True
    torch.testing.assert_close(depth_smoothness_loss(torch.where(right, ramp, 0.0), img, right),
                               depth_smoothness_loss(ramp[..., 8:], img[..., 8:]))


def test_warp_loss_is_zero_when_points_follow_the_content_and_not_when_held_still():
    T, H, W, f, z = 3, 16, 16, 20.0, 2.0
    g = torch.Generator().manual_seed(0)
    tex = F.interpolate(torch.rand(1, 3, 8, 24, generator=g), size=(H, W + 8), mode="bilinear")[0]
    frames = torch.stack([tex[:, :, 2 * t:2 * t + W] for t in range(T)])  # content moves 2 px left per frame
    K = torch.tensor([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1]]).expand(T, 3, 3)
    vm = torch.eye(4).repeat(T, 1, 1)
    o, d = camera_rays(vm[:1], K[:1], W, H)
    still = (o + d * (z / d[..., 2:]))[0].expand(T, H, W, 3)  # frame 0's pixels at z-depth 2 m
    step = torch.tensor([-2.0 * z / f, 0.0, 0.0])
    moving = still + torch.arange(T, dtype=torch.float32)[:, None, None, None] * step
    assert float(warp_loss(frames, moving, vm, K)) < 1e-6  # integer shifts: exact bilinear look-ups
    assert float(warp_loss(frames, still, vm, K)) > 0.01
    assert float(warp_loss(frames[:1].expand(T, 3, H, W), still, vm, K)) < 1e-6  # a still video, still points
