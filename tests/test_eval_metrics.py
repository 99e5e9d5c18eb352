"""Tests of training/eval_metrics.py: closed forms of every metric, on each device, and without tensors made on
torch's default device."""
import math

import pytest
import torch

from diff4splat.cameras import intrinsics_from_fov, make_trajectory
from diff4splat.scene.quaternions import axis_angle_to_quat, quat_to_rotmat
from training.eval_metrics import (
    ANGLE_BINS,
    PSNR_CAP,
    ablation_noise,
    angle_bin,
    binned_psnr,
    blockiness,
    covisible_mask,
    depth_errors,
    frame_mse,
    gap_intervals,
    image_psnr,
    image_ssim,
    kept_index_map,
    masked_psnr,
    motion_errors,
    pearson,
    psnr_from_mse,
    repeat_baselines,
    thumbnail,
    view_angles,
)


def test_depth_errors_see_the_scale_that_pearson_does_not():
    true = torch.tensor([1.0, 2.0, 4.0, 8.0])
    assert pearson(0.5 * true, true) == pytest.approx(1.0)  # blind to a scene placed at half the distance
    assert depth_errors(0.5 * true, true) == pytest.approx({"depth_abs_rel": 0.5, "depth_scale": 0.5})
    pred = torch.tensor([1.0, 3.0, 4.0, 4.0])  # relative errors 0, 0.5, 0, 0.5; ratios 1, 1.5, 1, 0.5
    assert depth_errors(pred, true)["depth_abs_rel"] == pytest.approx(0.25)
    assert depth_errors(pred, true)["depth_scale"] == 1.0  # torch's median: the lower of the two middle values
    assert all(math.isnan(v) for v in depth_errors(torch.ones(0), torch.ones(0)).values())


def test_pearson_and_psnr_closed_forms():
    a = torch.arange(10.0)
    assert pearson(a, 2 * a + 1) == pytest.approx(1.0)
    assert pearson(a, -a) == pytest.approx(-1.0)
    assert pearson(a, torch.ones(10)) == 0.0  # constant: no correlation, not NaN
    img = torch.rand(1, 3, 8, 8)
    assert image_psnr(img, img) == PSNR_CAP
    assert image_psnr(torch.zeros(1, 3, 8, 8), torch.full((1, 3, 8, 8), 0.1)) == pytest.approx(20.0, abs=1e-4)
    assert math.isnan(psnr_from_mse(float("nan")))


def test_psnr_of_a_corrupted_prediction_drops_by_the_expected_amount():
    """Adding uniform error e to a perfect prediction gives MSE e², i.e. −20·log10(e) dB; doubling e costs
    20·log10(2) ≈ 6.02 dB. Predictions are clamped to [0, 1] before scoring."""
    gt = 0.25 + 0.5 * torch.rand(2, 3, 16, 16, generator=torch.Generator().manual_seed(0))
    assert image_psnr(gt, gt) == PSNR_CAP
    a, b = image_psnr(gt + 0.05, gt), image_psnr(gt - 0.1, gt)
    assert a == pytest.approx(-20 * math.log10(0.05), abs=1e-3)
    assert a - b == pytest.approx(20 * math.log10(2), abs=1e-3)
    assert image_psnr(gt.clamp(max=0.5) + 10.0, gt) == pytest.approx(image_psnr(torch.ones_like(gt), gt), abs=1e-6)


def _viewmat(R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    vm = torch.eye(4, dtype=torch.float64)
    vm[:3, :3], vm[:3, 3] = R, t
    return vm


def test_view_angle_of_a_known_rotation_is_its_angle():
    """Camera i = a rotation by θ about an arbitrary axis composed with an arbitrary first camera (R_i = R(θ)·R_0)
    and arbitrary translations: the view angle is θ, from 0 through tiny angles to exactly 180°."""
    g = torch.Generator().manual_seed(0)
    R0 = quat_to_rotmat(torch.randn(4, generator=g, dtype=torch.float64))
    axis = torch.tensor([0.3, -0.8, 0.5], dtype=torch.float64)
    thetas = [0.0, 1e-4, 0.5, 15.0, 44.9, 90.0, 135.0, 179.99, 180.0]
    vms = [_viewmat(quat_to_rotmat(axis_angle_to_quat(axis, torch.tensor(math.radians(th), dtype=torch.float64)))
                    @ R0, torch.randn(3, generator=g, dtype=torch.float64)) for th in thetas]
    angles = view_angles(torch.stack(vms))
    assert angles.tolist() == pytest.approx(thetas, abs=1e-7)
    # a pure translation does not change where the camera looks
    assert float(view_angles(torch.stack([vms[0], _viewmat(R0, torch.ones(3, dtype=torch.float64))]))[1]) < 1e-7
    with pytest.raises(ValueError, match="viewmats"):
        view_angles(torch.eye(4))


def test_view_angle_of_an_arc_is_its_sweep():
    """The arc preset orbits the scene centre by a·t: its view angles are the sweep a·t (degrees)."""
    K = intrinsics_from_fov(32, 32, fov_y_deg=50.0)
    path = make_trajectory("arc", 9, K.double(), 32, 32, scene_depth=2.0, amplitude=1.2)
    expected = [math.degrees(1.2 * i / 8) for i in range(9)]
    assert view_angles(path.viewmats).tolist() == pytest.approx(expected, abs=1e-6)


def test_angle_bins_partition_the_frames():
    """Every angle in [0, 180] falls in exactly one bin (boundaries go to the upper bin, 180° to the last),
    the counts add up to the frame count, and each bin's PSNR is that of its frames' mean MSE."""
    g = torch.Generator().manual_seed(1)
    edges = [0.0, 15.0, 45.0, 90.0, 180.0, 14.999, 45.001, 89.999]
    uniform = 180 * torch.rand(40, generator=g, dtype=torch.float64)
    angles = torch.cat([torch.tensor(edges, dtype=torch.float64), uniform])
    idx = angle_bin(angles)
    assert idx[:8].tolist() == [0, 1, 2, 3, 3, 0, 2, 2]
    for a, i in zip(angles.tolist(), idx.tolist(), strict=True):  # brute force against the bins' definition
        inside = [lo <= a < hi or (hi == 180.0 and a == 180.0) for _, lo, hi in ANGLE_BINS]
        assert inside.count(True) == 1 and inside.index(True) == i
    mse = 0.01 + 0.1 * torch.rand(len(angles), generator=g, dtype=torch.float64)
    bins = binned_psnr(mse, angles)
    assert list(bins) == [name for name, _, _ in ANGLE_BINS]
    assert sum(n for _, n in bins.values()) == len(angles)
    for i, (name, _, _) in enumerate(ANGLE_BINS):
        assert bins[name][0] == pytest.approx(-10 * math.log10(float(mse[idx == i].mean())), abs=1e-9)
    empty = binned_psnr(mse[:1], torch.zeros(1, dtype=torch.float64))
    assert empty["0_15"][1] == 1 and math.isnan(empty["45_90"][0]) and empty["45_90"][1] == 0


def test_gap_intervals_pool_frames_and_resample_whole_clips():
    """The gap is binned_psnr's PSNR difference; the interval resamples clips, not frames: one clip gives a point,
    and two clips give exactly the gaps of (clip 0 twice) and (clip 1 twice) as the 5 % and 95 % quantiles
    (each of those two resamplings has probability 1/4), where a bootstrap of frames would spread between them."""
    g = torch.Generator().manual_seed(7)
    angles = [torch.tensor([3.0, 20.0, 50.0]), torch.tensor([10.0, 30.0]), torch.tensor([5.0, 60.0, 70.0, 100.0])]
    model = [0.01 + 0.05 * torch.rand(len(a), generator=g, dtype=torch.float64) for a in angles]
    other = [0.01 + 0.05 * torch.rand(len(a), generator=g, dtype=torch.float64) for a in angles]
    gaps = gap_intervals(model, other, angles)
    assert list(gaps) == ["all"] + [name for name, _, _ in ANGLE_BINS]
    bm, bo = binned_psnr(torch.cat(model), torch.cat(angles)), binned_psnr(torch.cat(other), torch.cat(angles))
    for name, _, _ in ANGLE_BINS:
        assert gaps[name][0] == pytest.approx(bm[name][0] - bo[name][0], abs=1e-9)
    assert gaps["all"][0] == pytest.approx(10 * math.log10(float(torch.cat(other).sum() / torch.cat(model).sum())))
    assert [gaps[n][3] for n in gaps] == [3, 3, 2, 2, 1]  # clips with frames in each bin
    assert gap_intervals(model, other, angles) == gaps  # seeded

    one = gap_intervals(model[:1], other[:1], angles[:1])
    assert all(lo == pytest.approx(p) and hi == pytest.approx(p) for p, lo, hi, n in one.values() if n)
    assert math.isnan(one["90_180"][0]) and math.isnan(one["90_180"][1]) and one["90_180"][3] == 0

    a2 = [torch.full((4,), 5.0), torch.full((2,), 5.0)]
    m2 = [torch.tensor([0.01, 0.02, 0.01, 0.03], dtype=torch.float64), torch.tensor([0.02, 0.04], dtype=torch.float64)]
    o2 = [torch.tensor([0.04, 0.02, 0.05, 0.03], dtype=torch.float64), torch.tensor([0.03, 0.05], dtype=torch.float64)]
    same = [10 * math.log10(float(o.sum() / m.sum())) for m, o in zip(m2, o2, strict=True)]  # 3.80, 1.25 dB
    point, lo, hi, n = gap_intervals(m2, o2, a2)["0_15"]
    assert n == 2 and lo == pytest.approx(min(same)) and hi == pytest.approx(max(same))

    # a clip the model predicts exactly (zero MSE): its draws' gaps are +inf; the interval takes the draws at its
    # ends (no interpolation between infinite draws, which gave NaN)
    m3 = [torch.zeros(4, dtype=torch.float64), m2[1]]
    p3, lo3, hi3, _ = gap_intervals(m3, o2, a2)["0_15"]
    assert p3 == pytest.approx(10 * math.log10(float((o2[0].sum() + o2[1].sum()) / m2[1].sum())))
    assert lo3 == pytest.approx(same[1]) and hi3 == math.inf
    assert point == pytest.approx(10 * math.log10(float((o2[0].sum() + o2[1].sum()) / (m2[0].sum() + m2[1].sum()))))
    for bad in [([], [], []), (model, other[:2], angles), (model, other, [angles[0], angles[1], angles[1]])]:
        with pytest.raises(ValueError):
            gap_intervals(*bad)
    with pytest.raises(ValueError, match="draws"):
        gap_intervals(model, other, angles, draws=0)


def test_gap_intervals_take_inputs_on_any_device(device, no_implicit_device):
    """Frame MSEs on ``device``: the statistics are made on the CPU, never on torch's default device."""
    with torch.device("cpu"):
        angles = [torch.tensor([3.0, 50.0]), torch.tensor([20.0])]
        model = [torch.tensor([0.01, 0.02], dtype=torch.float64), torch.tensor([0.03], dtype=torch.float64)]
        other = [torch.tensor([0.02, 0.05], dtype=torch.float64), torch.tensor([0.04], dtype=torch.float64)]
        ref = gap_intervals(model, other, angles, draws=50)
    moved = [[t.to(device) for t in x] for x in (model, other, angles)]
    got = gap_intervals(*moved, draws=50)
    assert list(got) == list(ref) and ref["all"][1] < ref["all"][2]
    for name in ref:
        assert got[name] == pytest.approx(ref[name], nan_ok=True)


def test_repeat_baselines_on_a_static_clip_and_a_shifted_one():
    """Identical frames: repeating frame 0 is exact (PSNR_CAP), and so is its blur when the frames are one
    colour; frames that brighten by δ per frame have repeat MSE (k·δ)² at frame k."""
    g = torch.Generator().manual_seed(2)
    frame = torch.rand(3, 1, 32, 32, generator=g)
    same = repeat_baselines(frame.expand(3, 5, 32, 32))
    assert psnr_from_mse(float(same["repeat"].mean())) == PSNR_CAP
    assert float(same["repeat_blur"].min()) > 0  # blurring a textured frame changes it
    flat = repeat_baselines(torch.full((3, 5, 32, 32), 0.4))
    assert psnr_from_mse(float(flat["repeat_blur"].mean())) == PSNR_CAP
    video = (0.2 + 0.05 * torch.arange(5.0)).reshape(1, 5, 1, 1).expand(3, 5, 16, 16)
    assert repeat_baselines(video)["repeat"].tolist() == pytest.approx([(0.05 * k) ** 2 for k in range(1, 5)])
    with pytest.raises(ValueError, match="video"):
        repeat_baselines(frame)


def test_frame_mse_clamps_predictions():
    gt = torch.full((2, 3, 4, 4), 0.5)
    assert frame_mse(gt + 2.0, gt).tolist() == pytest.approx([0.25, 0.25])
    with pytest.raises(ValueError, match="shape"):
        frame_mse(gt, gt[:1])


def test_motion_errors_on_hand_computed_tracks():
    """Two tracks, three frames. Track 0 moves +x by 1 per frame; the prediction sits 0.5 m too deep (z) and
    moves +x by 0.5 per frame. Track 1 is visible at frames 0 and 2 only. Track 2 is invisible at frame 0,
    so it counts for the absolute EPE but not for the displacement metrics."""
    x, z = torch.tensor([1.0, 0, 0]), torch.tensor([0, 0, 1.0])
    tracks = torch.stack([torch.stack([z + k * x for k in range(3)]),
                          torch.stack([z, z + 2 * x, z + 2 * x]),
                          torch.stack([z, z, z])])
    pred = torch.stack([torch.stack([1.5 * z + 0.5 * k * x for k in range(3)]),
                        torch.stack([z, z, z + 3 * x]),
                        torch.stack([z, z + x, z])])
    mask = torch.tensor([[True, True, True], [True, False, True], [False, True, True]])
    m = motion_errors(pred, tracks, mask)
    # displacement pairs (t ≥ 1, visible at 0 and t): (0,1), (0,2), (1,2)
    assert m["motion_disp_epe"] == pytest.approx((0.5 + 1.0 + 1.0) / 3)
    assert m["motion_disp_hold"] == pytest.approx((1.0 + 2.0 + 2.0) / 3)
    assert m["motion_disp_d5"] == m["motion_disp_d10"] == 0.0  # errors 0.5, 1, 1 m
    assert m["motion_disp_hold_d10"] == 0.0
    exact = motion_errors(tracks + 0.07 * z, tracks, mask)  # right displacements, a wrong depth: every pair within 5 cm
    assert exact["motion_disp_d5"] == exact["motion_disp_d10"] == 1.0 and exact["motion_disp_epe"] < 1e-6
    off = tracks.clone()
    off[1:, 1:] += 0.07 * z  # track 0's pairs exact; tracks 1 and 2 are 0.07 m off at t ≥ 1: within 10 cm, not 5
    near = motion_errors(off, tracks, torch.ones(3, 3, dtype=torch.bool))
    assert near["motion_disp_d5"] == pytest.approx(2 / 6) and near["motion_disp_d10"] == 1.0
    assert near["motion_disp_hold_d5"] == pytest.approx(2 / 6)  # track 2 never moves
    # absolute EPE over the 7 masked pairs: track 0: √(0.25+0.25), √(0.25+1), track 1: 0, 1; track 2: 1, 0
    t0 = [0.5, math.sqrt(0.25 + 0.25), math.sqrt(0.25 + 1.0)]
    assert m["motion_epe"] == pytest.approx((sum(t0) + 0 + 1 + 1 + 0) / 7)
    assert m["motion_epe_t0"] == pytest.approx((0.5 + 0) / 2)
    hold = [0.5, math.sqrt(0.25 + 1), math.sqrt(0.25 + 4), 0, 2, 0, 0]  # ‖p̂_0 − p_t‖
    assert m["motion_epe_hold"] == pytest.approx(sum(hold) / 7)
    none = motion_errors(pred, tracks, torch.zeros(3, 3, dtype=torch.bool))
    assert all(math.isnan(v) for v in none.values())


def test_kept_index_map_inverts_the_pruning_index():
    g = torch.Generator().manual_seed(3)
    total = 3 * 8 * 8
    index = torch.randperm(total, generator=g)[:70].sort().values
    kept = kept_index_map(index, total)
    brute = [next((j for j, p in enumerate(index.tolist()) if p == slot), -1) for slot in range(total)]
    assert kept.tolist() == brute
    assert (kept >= 0).sum() == 70
    with pytest.raises(ValueError, match="gaussian_index"):
        kept_index_map(torch.tensor([0, total]), total)
    with pytest.raises(ValueError, match="repeated"):
        kept_index_map(torch.tensor([1, 1]), total)


def _translated(x: float) -> torch.Tensor:
    """World-to-camera of a camera at (x, 0, 0) looking down +z (identity rotation)."""
    v = torch.eye(4)
    v[0, 3] = -x
    return v


def test_covisible_mask_of_a_plane_seen_by_a_shifted_camera():
    """Plane z = 5, evaluated camera at the origin, training camera 1 m to the right: a pixel's point
    projects f·1/5 = 6.4 px further left in the training view, so columns with centre u + 0.5 < 6.4 (the
    first 6) fall outside it, all others are seen."""
    H, W, f = 8, 64, 32.0
    K = torch.tensor([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1.0]])
    depth = torch.full((H, W), 5.0)
    m = covisible_mask(depth, torch.eye(4), K, depth[None], _translated(1.0)[None], K[None])
    expected = torch.zeros(H, W, dtype=torch.bool)
    expected[:, 6:] = True
    assert torch.equal(m, expected)
    # an occluder at 2 m covering the training view's right half hides the points that land there:
    # column u lands at u − 6.4 ≥ 32 for centres ≥ 38.4, i.e. columns 38 …
    occluded = depth.clone()
    occluded[:, W // 2:] = 2.0
    m = covisible_mask(depth, torch.eye(4), K, occluded[None], _translated(1.0)[None], K[None])
    expected[:, 38:] = False
    assert torch.equal(m, expected)
    # a second training camera 1 m to the left sees columns 0 … 57 (centre + 6.4 < 64): the union
    m = covisible_mask(depth, torch.eye(4), K, torch.stack([occluded, depth]),
                       torch.stack([_translated(1.0), _translated(-1.0)]), torch.stack([K, K]))
    assert bool(m[:, :58].all()) and not bool(m[:, 58:].any())
    # unknown depth is never dropped; a training camera facing away sees nothing
    depth[0, 0] = math.inf
    back = torch.diag(torch.tensor([-1.0, 1.0, -1.0, 1.0]))  # rotated 180° about y
    m = covisible_mask(depth, torch.eye(4), K, depth[None], back[None], K[None])
    assert bool(m[0, 0]) and int(m.sum()) == 1


def test_covisible_mask_tolerance_and_errors():
    """A point 2 % behind the training view's surface counts as seen (rel_tol 3 %), 4 % behind does not."""
    K = torch.tensor([[4.0, 0, 2], [0, 4.0, 2], [0, 0, 1.0]])
    depth = torch.full((4, 4), 1.02)
    assert bool(covisible_mask(depth, torch.eye(4), K, torch.ones(1, 4, 4), torch.eye(4)[None], K[None]).all())
    depth = torch.full((4, 4), 1.04)
    assert not bool(covisible_mask(depth, torch.eye(4), K, torch.ones(1, 4, 4), torch.eye(4)[None], K[None]).any())
    with pytest.raises(ValueError, match="train_depths"):
        covisible_mask(depth, torch.eye(4), K, torch.ones(4, 4), torch.eye(4)[None], K[None])


def test_masked_psnr_closed_form():
    gt = torch.full((2, 4, 4, 3), 0.5)
    pred = gt.clone()
    mask = torch.zeros(2, 4, 4, dtype=torch.bool)
    mask[:, :2] = True
    pred[mask] += 0.1  # error 0.1 where masked (20 dB) ...
    pred[~mask] += 0.4  # ... and a large error elsewhere, which the masked PSNR ignores
    assert masked_psnr(pred, gt, mask) == pytest.approx(20.0, abs=1e-5)
    assert math.isnan(masked_psnr(pred, gt, torch.zeros_like(mask)))
    with pytest.raises(ValueError, match="mask"):
        masked_psnr(pred, gt, mask[0])


def _metric_inputs(device):
    """Inputs of every metric function, drawn on the CPU and moved to ``device``."""
    g = torch.Generator().manual_seed(7)
    K = torch.tensor([[16.0, 0, 8], [0, 16.0, 6], [0, 0, 1.0]])
    depth = 2.0 + torch.rand(12, 16, generator=g)
    depth[0, :3] = math.inf
    x = dict(pred=torch.rand(3, 3, 12, 16, generator=g), gt=torch.rand(3, 3, 12, 16, generator=g),
             video=torch.rand(3, 5, 12, 16, generator=g), a=torch.rand(50, generator=g), b=torch.rand(50, generator=g),
             viewmats=torch.stack([torch.eye(4), _translated(0.3), _translated(-0.2)]), K=K, depth=depth,
             tracks=torch.rand(6, 3, 3, generator=g), track_pred=torch.rand(6, 3, 3, generator=g),
             track_mask=torch.rand(6, 3, generator=g) < 0.7, index=torch.tensor([3, 0, 7, 5]),
             mask=torch.rand(3, 12, 16, generator=g) < 0.5, angles=torch.tensor([0.0, 10.0, 50.0, 120.0, 180.0]))
    return {k: v.to(device) for k, v in x.items()}


def _all_metrics(x):
    """Every metric function of the module on the inputs of :func:`_metric_inputs`, as CPU tensors and floats."""
    binned = binned_psnr(frame_mse(x["pred"], x["gt"]), x["angles"][:3].double())
    out = {"psnr": image_psnr(x["pred"], x["gt"]), "ssim": image_ssim(x["pred"], x["gt"]),
           "pearson": pearson(x["a"], x["b"]), "frame_mse": frame_mse(x["pred"], x["gt"]),
           "angles": view_angles(x["viewmats"]), "bins": angle_bin(x["angles"]),
           **{f"binned_{k}": v for k, v in binned.items()},
           "kept": kept_index_map(x["index"], 9), "noise": ablation_noise((2, 3), 4, x["a"].device),
           "covisible": covisible_mask(x["depth"], x["viewmats"][0], x["K"], x["depth"][None].expand(2, 12, 16),
                                       x["viewmats"][1:], x["K"][None].expand(2, 3, 3)),
           "masked": masked_psnr(x["pred"].permute(0, 2, 3, 1), x["gt"].permute(0, 2, 3, 1), x["mask"]),
           **{f"repeat_{k}": v for k, v in repeat_baselines(x["video"]).items()},
           **{f"motion_{k}": v for k, v in motion_errors(x["track_pred"], x["tracks"], x["track_mask"]).items()}}
    return out


def test_metrics_on_each_device(device):
    """Every metric is computed on its inputs' device and equals the CPU value (the noise: the same draws)."""
    got, ref = _all_metrics(_metric_inputs(device)), _all_metrics(_metric_inputs("cpu"))
    for k, v in got.items():
        if isinstance(v, torch.Tensor):
            assert v.device.type == device.type, k
            torch.testing.assert_close(v.cpu(), ref[k], rtol=1e-5, atol=1e-6, msg=k)
        else:
            assert v == pytest.approx(ref[k], rel=1e-5, abs=1e-6, nan_ok=True), k


def test_metrics_make_nothing_on_the_default_device(no_implicit_device):
    """With torch's default device "meta" (tests/conftest.py) every metric of CPU inputs is computed on the CPU."""
    with torch.device("cpu"):
        x = _metric_inputs("cpu")
    out = _all_metrics(x)
    for k, v in out.items():
        if isinstance(v, torch.Tensor):
            assert v.device.type == "cpu", k
    assert math.isfinite(out["psnr"]) and 0 < out["ssim"] < 1 and out["kept"].tolist()[:4] == [1, -1, -1, 0]


def test_thumbnail_keeps_constants_and_interior_ramps_and_nothing_finer():
    """Area average to 8×8 then bilinear back: a constant image exactly; a linear ramp exactly away from the
    borders (cell means are the ramp at the cell centres, which bilinear interpolation joins linearly); detail
    finer than a cell (a one-pixel checkerboard) is averaged away to its mean."""
    const = torch.full((1, 3, 64, 48), 0.3)
    torch.testing.assert_close(thumbnail(const), const)
    x = torch.arange(64, dtype=torch.float32)
    ramp = (x / 64).expand(1, 3, 64, 64).contiguous()
    inner = slice(8, 56)
    torch.testing.assert_close(thumbnail(ramp)[..., inner, inner], ramp[..., inner, inner])
    checker = ((x[:, None] + x[None, :]) % 2).expand(1, 3, 64, 64)
    torch.testing.assert_close(thumbnail(checker), torch.full_like(checker, 0.5))



def test_blockiness_closed_forms():
    """On a 32×32 grid with 8-pixel blocks (3 border and 28 inside differences per row and column): a ramp (a
    difference of 1 everywhere along x) scores 1; constant 8×8 blocks have differences on the borders only; a step
    after every 4th column puts 3 steps on the 3 border columns and 4 on the 28 inside ones: (3/6) / (4/56) = 7."""
    ramp = torch.arange(32.0).repeat(32, 1)
    assert blockiness(ramp, 8) == pytest.approx(1.0)
    blocks = torch.randn(3, 4, 4, generator=torch.Generator().manual_seed(0))
    blocks = blocks.repeat_interleave(8, 1).repeat_interleave(8, 2)  # (3, 32, 32)
    assert blockiness(blocks, 8) > 1e15
    steps = (torch.arange(32) // 4).float().repeat(32, 1)
    assert blockiness(steps, 8) == pytest.approx(7.0)
