"""Tests of diff4splat/io/viewer_data.py: keyframes are DynamicGaussians.at's, the byte layout round-trips, the
float16 error has its closed form, and the size budget's reductions (brute-force references, closed forms)."""
import math
from fractions import Fraction

import numpy as np
import pytest
import torch
from helpers import moving_patch_scene, windowed_patch_scene
from torch import Tensor

from diff4splat.cameras.path import CameraPath
from diff4splat.io import load_ply
from diff4splat.io.viewer_data import FLOAT16_MAX_PX, decode_keyframes, encode_keyframes, payload_bytes, viewer_payload
from diff4splat.render.keyframes import (
    _fits_float16,
    _keyframes_fit_float16,
    evenly_spaced,
    float16_error_px,
    held_keyframes,
    key_windows,
    keyframe_times,
    keyframes,
    most_covering,
    still_gaussians,
    time_range,
)
from diff4splat.scene.dynamic import DynamicGaussians
from diff4splat.scene.gaussians import Gaussians


def test_keyframes_are_the_scene_at_its_key_times():
    scene, cams = moving_patch_scene(n=50, frames=4, temporal=True)
    times = keyframe_times(scene)
    assert torch.equal(times, scene.times.double()) and time_range(scene, cams) == (0.0, 1.0)
    frames = keyframes(scene, times)
    assert set(frames) == {"means", "quats", "scales"}  # temporal opacity: evaluated by the page from μ_t, σ_t
    for k, t in enumerate(times.tolist()):
        g = scene.at(t, gate=0.0)
        torch.testing.assert_close(frames["means"][k], g.means)
        torch.testing.assert_close(frames["quats"][k], g.quats / g.quats.norm(dim=-1, keepdim=True))
        torch.testing.assert_close(frames["scales"][k], g.scales)
    assert float((frames["means"][-1, :, 0] - frames["means"][0, :, 0]).mean()) == pytest.approx(0.6)


def test_key_times_of_static_and_temporal_only_scenes():
    """A static scene has no time controls and no frame data; one with temporal support only has controls over
    the path's times and its μ_t, σ_t (float32) but no keyframes: its Gaussians do not move."""
    static, cams = moving_patch_scene(n=10, shift=0.0)
    assert keyframe_times(static) is None and time_range(static, cams) is None
    p = viewer_payload(static, cams)
    assert p.frames is None and p.config["dynamic"] is False and p.config["times"] == []
    temporal, cams = moving_patch_scene(n=10, shift=0.0, temporal=True)
    cams = CameraPath(cams.viewmats, cams.Ks, cams.width, cams.height, torch.linspace(0.2, 0.7, 5))
    assert keyframe_times(temporal) is None and time_range(temporal, cams) == pytest.approx((0.2, 0.7))
    p = viewer_payload(temporal, cams)
    assert p.config["dynamic"] is True and p.config["times"] == []
    assert p.config["timeRange"] == pytest.approx([0.2, 0.7])
    assert len(p.frames) == 8 * 10 and p.config["bytesPerHeldKey"] == 0
    back = decode_keyframes(p.frames, p.config)
    np.testing.assert_array_equal(back["t_means"], temporal.t_means.numpy())
    np.testing.assert_array_equal(back["t_scales"], temporal.t_scales.numpy())
    assert back["means"].shape == (0, 10, 3)


def _ragged(every: dict, first: Tensor, count: Tensor) -> Tensor:
    """Reference: the rows of held keyframes from every keyframe (F, N, ·) of every Gaussian, a loop per Gaussian."""
    dense = torch.cat([every["means"], every["quats"], every["scales"]], dim=-1)  # (F, N, 10)
    rows = [dense[int(f):int(f) + int(c), i] for i, (f, c) in enumerate(zip(first, count, strict=True))]
    return torch.cat(rows) if rows else dense.new_zeros(0, 10)


@pytest.mark.parametrize("dtype", ["float16", "float32"])
def test_encode_decode_round_trip(dtype):
    scene, cams = moving_patch_scene(n=30, frames=3, temporal=True)
    times = keyframe_times(scene)
    frames = keyframes(scene, times)
    first, count = key_windows(scene, times)
    assert first.tolist() == [0] * 30 and count.tolist() == [3] * 30  # all move, unbounded support: every key
    held = held_keyframes(scene, times, first, count)
    torch.testing.assert_close(held, _ragged(frames, first, count), rtol=0, atol=0)
    data = encode_keyframes(held, (first, count), dtype, (scene.t_means, scene.t_scales))
    itemsize = 2 if dtype == "float16" else 4
    assert len(data) == 8 * 30 + 4 * 30 + 3 * 30 * 10 * itemsize
    assert len(data) == payload_bytes(30, 0, 90, 2, itemsize, True) - 30 * 17 * 4  # less the PLY
    back = decode_keyframes(data, {"numGaussians": 30, "times": [0, 0.5, 1], "temporal": True, "dtype": dtype})
    np.testing.assert_array_equal(back["t_means"], scene.t_means.numpy())  # float32 whatever the keyframes' dtype
    np.testing.assert_array_equal(back["t_scales"], scene.t_scales.numpy())
    for k, v in frames.items():
        ref = v.numpy().astype(np.float16).astype(np.float32) if dtype == "float16" else v.numpy()
        np.testing.assert_array_equal(back[k], ref)
    with pytest.raises(ValueError, match="dtype"):
        encode_keyframes(held, (first, count), "int8")
    with pytest.raises(ValueError, match="one row per held key"):
        encode_keyframes(held[1:], (first, count), dtype)


def _page_keys(times: list[float], t: float) -> tuple[int, int]:
    """The two keys the page (and DynamicGaussians.deformation_at) interpolates between at time t."""
    k = 0
    while k < len(times) - 2 and t > times[k + 1]:
        k += 1
    return k, min(k + 1, len(times) - 1)


def test_key_windows_hold_exactly_the_keys_the_page_reads_where_a_gaussian_is_seen():
    """Brute force over 4001 times and each window's edges: a Gaussian with bounded support holds the keys the page
    reads at every time it is seen (opacity > 0) and no other; a still one (Δ the identity) holds none, and its
    canonical pose is DynamicGaussians.at's at every time, exactly."""
    scene, cams = windowed_patch_scene()
    times = keyframe_times(scene)
    first, count = key_windows(scene, times)
    still = still_gaussians(scene)
    assert still.tolist() == [i < 20 for i in range(60)]
    ts = sorted(set(np.linspace(0, 1, 4001).tolist()) | {
        min(1.0, max(0.0, float(m + e))) for m, s in zip(scene.t_means, scene.t_scales, strict=True)
        for e in (-s + 1e-9, s - 1e-9)})
    needed = [set() for _ in range(60)]
    for t in ts:
        seen = scene.temporal_opacity(t) > 0
        for i in torch.nonzero(seen).squeeze(1).tolist():
            needed[i].update(_page_keys(times.tolist(), t))
    for i in range(20, 60):
        held = set(range(int(first[i]), int(first[i] + count[i])))
        assert needed[i] <= held, i
        if needed[i]:  # seen in [0, 1]: no key more than it needs
            assert held == set(range(min(needed[i]), max(needed[i]) + 1)), (i, needed[i], held)
    assert count[:20].tolist() == [0] * 20
    for t in (0.0, 0.37, 1.0):
        g = scene.at(t, gate=0.0, index=torch.arange(20))
        assert torch.equal(g.means, scene.canonical.means[:20]) and torch.equal(g.scales, scene.canonical.scales[:20])
        torch.testing.assert_close(g.quats, scene.canonical.quats[:20], rtol=0, atol=0)
    assert bool(still_gaussians(moving_patch_scene(n=10, shift=0.0)[0]).all())


def test_the_payload_holds_the_windows_and_decodes_to_the_scene_where_seen():
    """viewer_payload's frame data: each Gaussian's held keys are DynamicGaussians.at's there (NaN elsewhere), the
    size is payload_bytes' of the held count, and the held count is below N·F (still Gaussians and windows)."""
    scene, cams = windowed_patch_scene()
    p = viewer_payload(scene, cams, budget=None)
    c = p.config
    first, count = key_windows(scene, keyframe_times(scene))
    assert c["heldKeyframes"] == int(count.sum()) < 60 * 9 and c["dtype"] == "float16"
    assert len(p.frames) == payload_bytes(60, 0, c["heldKeyframes"], 3, 2, True) - 60 * 17 * 4
    back = decode_keyframes(p.frames, c)
    np.testing.assert_array_equal(back["key_first"], first.numpy())
    np.testing.assert_array_equal(back["key_count"], count.numpy())
    for f, t in enumerate(c["times"]):
        held = (first <= f) & (f < first + count)
        g = scene.at(t, gate=0.0)
        np.testing.assert_allclose(back["means"][f][held.numpy()], g.means[held].numpy(), atol=2e-3)
        assert np.isnan(back["means"][f][~held.numpy()]).all()


def test_most_covering_ranks_opacity_times_area_and_spreads_ties():
    """The kept Gaussians are the top m of o·(s₁s₂s₃)^⅔ by a brute-force ranking (a 2× larger Gaussian at half
    the opacity covers more), and among equal scores (ten alike layers of 100) every layer keeps about its share
    instead of the first five whole."""
    g = torch.Generator().manual_seed(3)
    opac, scales = torch.rand(300, generator=g), 0.01 + torch.rand(300, 3, generator=g)
    score = [float(opac[i]) * float(scales[i].prod()) ** (2 / 3) for i in range(300)]
    want = sorted(sorted(range(300), key=lambda i: -score[i])[:40])
    assert most_covering(opac, scales, 40).tolist() == want
    assert most_covering(torch.tensor([0.9, 0.5]), torch.tensor([[1.0] * 3, [2.0] * 3]), 1).tolist() == [1]
    kept = most_covering(torch.full((1000,), 0.995), torch.full((1000, 3), 0.01), 500)
    per_layer = torch.bincount(kept // 100, minlength=10)
    assert kept.numel() == 500 and int(per_layer.min()) >= 35 and int(per_layer.max()) <= 65, per_layer.tolist()
    assert torch.equal(kept, most_covering(torch.full((1000,), 0.995), torch.full((1000, 3), 0.01), 500))


def test_ramps_travel_after_the_time_scales():
    """A trapezoid's ramps (DynamicGaussians.t_ramps) follow μ_t and σ_t as float32, the config says so, and the
    payload's size counts three arrays."""
    scene, cams = moving_patch_scene(n=30, frames=3, temporal=True)
    scene = DynamicGaussians(scene.canonical, scene.times, scene.d_means, scene.d_quats, scene.d_scales,
                             scene.t_means, scene.t_scales, scene.t_scales * 0.5)
    p = viewer_payload(scene, cams)
    assert p.config["temporal"] and p.config["temporalRamps"]
    held = p.config["heldKeyframes"]
    itemsize = p.config["bytesPerHeldKey"] // 10
    assert len(p.frames) == payload_bytes(30, 0, held, 3, itemsize, True) - 30 * 17 * 4
    back = decode_keyframes(p.frames, p.config)
    np.testing.assert_array_equal(back["t_ramps"], scene.t_ramps.numpy())
    np.testing.assert_array_equal(back["t_scales"], scene.t_scales.numpy())
    np.testing.assert_allclose(back["means"][1], scene.at(0.5, gate=0.0).means.numpy(), atol=2e-3)
    assert not viewer_payload(DynamicGaussians(scene.canonical, t_means=scene.t_means, t_scales=scene.t_scales),
                              cams).config["temporalRamps"]


@pytest.mark.parametrize("shared_means", [False, True])
def test_rows_shared_by_every_gaussian_give_what_their_dense_copies_give(shared_means):
    """``reconstruct`` gives every Gaussian one identity rotation and scale row (stride 0); still_gaussians,
    without_deformation and the payload's float16 check read only that row (distinct_rows) and answer as on dense
    copies: a Gaussian moved by Δμ alone is not still, a scale row off the identity moves every Gaussian, and a scale
    bound past float16 forces float32."""
    g = Gaussians(torch.randn(5, 3), torch.tensor([1.0, 0, 0, 0]).expand(5, 4).clone(), torch.full((5, 3), 0.1),
                  torch.full((5,), 0.9), torch.rand(5, 1, 3))
    times = torch.tensor([0.0, 0.5, 1.0])
    d_means = torch.zeros(3, 1, 3).expand(3, 5, 3) if shared_means else torch.zeros(3, 5, 3)
    if not shared_means:
        d_means[2, 3, 0] = 0.01
    for row, still in ((0.0, [True] * 5 if shared_means else [True, True, True, False, True]), (0.2, [False] * 5),
                       (14.0, [False] * 5)):  # 0.1 m·e¹⁴ ≈ 1.2e5 > 65504
        d_scales = torch.tensor([0.0, 0.0, row]).expand(3, 3)[:, None].expand(3, 5, 3)
        d_quats = torch.tensor([1.0, 0, 0, 0]).expand(3, 5, 4)
        shared = DynamicGaussians(g, times, d_means, d_quats, d_scales)
        dense = DynamicGaussians(g, times, d_means.clone(), d_quats.clone(), d_scales.clone())
        assert shared.d_scales.stride(1) == 0 and shared.d_quats.stride(1) == 0
        assert still_gaussians(shared).tolist() == still_gaussians(dense).tolist() == still
        assert shared.without_deformation().is_static == dense.without_deformation().is_static == all(still)
        assert _keyframes_fit_float16(shared, times) == _keyframes_fit_float16(dense, times) == (row < 14)


def test_float16_error_closed_form():
    """x = 1.0004 m rounds to 1.0 in float16 (spacing 2⁻¹⁰ near 1); at z = 1 m with f = 1000 px the point moves
    1000 · 0.0004 = 0.4 px. Points behind the camera do not count."""
    K = torch.tensor([[1000.0, 0, 500], [0, 1000.0, 500], [0, 0, 1]])
    means = torch.tensor([[[1.0004, 0.0, 1.0], [5.0, 0.0, -1.0]]], dtype=torch.float64)
    assert float16_error_px(means, torch.eye(4)[None], K[None]) == pytest.approx(0.4, rel=1e-3)
    assert float16_error_px(means[:, 1:], torch.eye(4)[None], K[None]) == 0.0


def test_evenly_spaced_is_exact_integer_rounding_past_float32s_integers():
    """round(i · (n − 1) / (k − 1)) exactly (Fractions), first 0 and last n − 1, also above 2²⁴ items, where a
    float32 linspace ends at n (16,777,220 of 16,777,220: an index past the end, the paper-size viewer's 10⁸
    keyframe points)."""
    for n, k in ((10, 4), (7, 7), (5, 9), (1, 3), (2**24 + 4, 200_000), (10**8 + 7, 9)):
        got = evenly_spaced(n, k).tolist()
        want = [int(Fraction(2 * i * (n - 1) + (k - 1), 2 * (k - 1))) for i in range(k)]
        assert got == want and got[0] == 0 and got[-1] == n - 1, (n, k)
    assert evenly_spaced(5, 1).tolist() == [0]
    float32 = torch.linspace(0, 2**24 + 3, 200_000).round().long()
    assert int(float32[-1]) == 2**24 + 4  # the bug this replaces
    # the float16 check over 2²⁴ + 4 points (a stride-0 view: no memory) takes the subset without an IndexError
    means = torch.tensor([1.0004, 0.0, 1.0], dtype=torch.float64).expand(1, 2**24 + 4, 3)
    K = torch.tensor([[1000.0, 0, 500], [0, 1000.0, 500], [0, 0, 1]])
    assert float16_error_px(means, torch.eye(4)[None], K[None]) == pytest.approx(0.4, rel=1e-3)


def test_float32_where_float16_would_move_points_by_more_than_half_a_pixel():
    scene, cams = moving_patch_scene(n=20)
    assert viewer_payload(scene, cams).config["dtype"] == "float16"
    # the same scene 1 km away, seen through a long lens: float16 spacing there is 0.5 m
    far = torch.eye(4)
    far[2, 3] = -1000.0
    s = scene.canonical
    moved = type(scene)(type(s)(s.means + torch.tensor([0, 0, 1000.0]), s.quats, s.scales, s.opacities, s.sh),
                        scene.times, scene.d_means, scene.d_quats, scene.d_scales)
    tele = CameraPath(far.repeat(len(cams), 1, 1), cams.Ks * torch.tensor([1000.0, 1000.0, 1.0])[:, None],
                      cams.width, cams.height)
    p = viewer_payload(moved, tele)
    assert p.config["float16ErrorPx"] > FLOAT16_MAX_PX and p.config["dtype"] == "float32"
    # one Gaussian beyond float16's range (|x| > 65504 m, out of every view) also needs float32
    huge = type(scene)(type(s)(s.means.clone().index_put_((torch.tensor([0]), torch.tensor([2])), torch.tensor(7e4)),
                               s.quats, s.scales, s.opacities, s.sh),
                       scene.times, scene.d_means, scene.d_quats, scene.d_scales)
    p = viewer_payload(huge, cams)
    assert p.config["float16ErrorPx"] <= FLOAT16_MAX_PX and p.config["dtype"] == "float32"


def test_ply_is_the_canonical_scene(tmp_path):
    scene, cams = moving_patch_scene(n=25, sh_degree=2)
    p = viewer_payload(scene, cams)
    (tmp_path / "v.ply").write_bytes(p.ply)
    g = load_ply(tmp_path / "v.ply")
    torch.testing.assert_close(g.means, scene.canonical.means)
    torch.testing.assert_close(g.sh, scene.canonical.sh)
    assert p.config["shDegree"] == 2 and p.config["numGaussians"] == 25 and p.config["note"] == ""
    assert p.config["reductions"] == []
    assert p.config["bytesPerHeldKey"] == 20  # 10 float16 values
    assert len(p.ply) - p.ply.index(b"end_header\n") - 11 + len(p.frames) == payload_bytes(25, 2, 125, 0, 2, True)


def test_budget_reductions_in_order():
    scene, cams = moving_patch_scene(n=200, frames=9, sh_degree=3)
    full = payload_bytes(200, 3, 9 * 200, 0, 2, True)
    assert viewer_payload(scene, cams, budget=full).reductions == []
    # just under: SH 3 → 0 is enough
    p = viewer_payload(scene, cams, budget=full - 1)
    assert p.reductions == ["SH degree 3 → 0"] and p.config["shDegree"] == 0 and "reduced" in p.config["note"]
    assert p.config["reductions"] == p.reductions
    # a budget for the PLY at SH 0 plus 3 keyframes: 9 → 3 keyframes, the first and the last kept
    budget = payload_bytes(200, 0, 3 * 200, 0, 2, True)
    p = viewer_payload(scene, cams, budget=budget)
    assert p.reductions == ["SH degree 3 → 0", "9 → 3 keyframes"]
    assert p.config["times"] == pytest.approx([0.0, 0.5, 1.0])
    assert len(p.frames) == 200 * 4 + 3 * 200 * 10 * 2
    # room for 50 Gaussians at 2 keyframes: keyframes go only while they are the larger part of the payload (at 3,
    # 60 bytes a Gaussian against the PLY's 68 and the window's 4), then the most opaque at 3 keyframes fill it (all
    # of one size: most_covering)
    opac = torch.linspace(0.1, 0.9, 200)
    c = scene.canonical
    scene = type(scene)(type(c)(c.means, c.quats, c.scales, opac, c.sh), scene.times, scene.d_means,
                        scene.d_quats, scene.d_scales)
    budget = payload_bytes(50, 0, 2 * 50, 0, 2, True)
    p = viewer_payload(scene, cams, budget=budget)
    m = budget // (17 * 4 + 4 + 3 * 20)
    assert p.reductions[1] == "9 → 3 keyframes" and p.config["numGaussians"] == m == 42 and len(p.reductions) == 3
    assert budget >= len(p.frames) + m * 17 * 4 > budget - (17 * 4 + 4 + 3 * 20)
    decoded = decode_keyframes(p.frames, p.config)
    kept = torch.arange(200 - m, 200)
    np.testing.assert_allclose(decoded["means"][0], scene.at(0.0).means[kept].numpy(), atol=2e-3)


def test_a_scene_of_short_lived_layers_keeps_every_keyframe_and_fewer_gaussians():
    """Gaussians that each hold a few keys (windows) and still ones (none) make keyframes the smaller part of the
    payload: over budget, every key time stays (no motion smeared between far keys) and the Gaussians covering most
    are kept, each counted at its own size, the payload filling the budget to within one Gaussian."""
    scene, cams = windowed_patch_scene(n=600)
    full = viewer_payload(scene, cams, budget=None)
    held = full.config["heldKeyframes"]
    assert held < 600 * 9 * 0.6
    budget = (len(full.ply) - full.ply.index(b"end_header\n") - 11 + len(full.frames)) // 2
    p = viewer_payload(scene, cams, budget=budget)
    assert p.reductions == [f"600 → {p.config['numGaussians']} Gaussians (those covering most)"]
    assert len(p.config["times"]) == 9
    used = len(p.ply) - p.ply.index(b"end_header\n") - 11 + len(p.frames)
    assert budget - (17 * 4 + 12 + 4 + 9 * 20) < used <= budget


def test_config_cameras_and_errors():
    scene, cams = moving_patch_scene(n=10)
    p = viewer_payload(scene, cams, fps=4.0, background=(0.1, 0.2, 0.3))
    c = p.config
    assert len(c["cameras"]) == 5 and c["cameras"][0]["viewmat"] == torch.eye(4).reshape(-1).tolist()
    assert c["cameras"][0]["K"] == cams.Ks[0].reshape(-1).tolist() and c["background"] == pytest.approx([0.1, 0.2, 0.3])
    assert c["duration"] == 1.0 and c["targetDistance"] == pytest.approx(3.0, abs=0.1)  # 4 steps at 4 fps; z ≈ 3 m
    assert math.isfinite(c["far"]) and c["far"] >= 100
    with pytest.raises(ValueError, match="fps"):
        viewer_payload(scene, cams, fps=0)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_fits_float16_is_a_finite_float16_cast_without_the_copy(dtype):
    """One min/max pass decides what `isfinite(x.half()).all()` would (the float16 keyframes' range check)."""
    edge = [65504.0, 65519.0, 65519.99, 65520.0, 70000.0, math.nan, math.inf, 1e-8, 0.0]
    for v in edge + [-x for x in edge]:
        x = torch.tensor([[1.0, v], [0.5, -2.0]], dtype=dtype)
        assert _fits_float16(x) == bool(torch.isfinite(x.half()).all()), v


@pytest.mark.parametrize("far", [False, True])
@pytest.mark.slow
def test_the_payload_equals_the_one_built_from_every_keyframe(far):
    """``viewer_payload`` deforms only the kept Gaussians at the kept key times, and decides the dtype from the
    means ``float16_error_px`` would pick out of all F·N (more than it measures) and from a range bound (``far``:
    means beyond float16's range, so the exact per-time check runs): the same bytes as the reference that holds
    every keyframe of every Gaussian, then reduces."""
    n, F = 30_000, 9  # F·N above FLOAT16_CHECK_POINTS: the evenly spaced subset is used
    scene, cams = moving_patch_scene(n=n, frames=F, temporal=True)
    if far:
        c = scene.canonical
        means = c.means.clone()
        means[7] += 70_000.0  # one far Gaussian: float16 overflows there
        scene = type(scene)(type(c)(means, c.quats, c.scales, torch.linspace(0.1, 0.9, n), c.sh), scene.times,
                            scene.d_means, scene.d_quats, scene.d_scales, scene.t_means, scene.t_scales)
    times = keyframe_times(scene)
    every = keyframes(scene, times)  # the reference: F × N keyframes held at once
    err = float16_error_px(every["means"], cams.viewmats, cams.Ks)
    dtype = "float16" if err <= FLOAT16_MAX_PX and all(_fits_float16(v) for v in every.values()) else "float32"
    assert dtype == ("float32" if far else "float16")
    itemsize = 2 if dtype == "float16" else 4
    # a third of the Gaussians at 3 keyframes: fewer keyframes, then fewer Gaussians
    budget = payload_bytes(n // 3, 0, 3 * (n // 3), 2, itemsize, True)
    p = viewer_payload(scene, cams, budget=budget)
    assert p.config["dtype"] == dtype and p.config["float16ErrorPx"] == err
    m = p.config["numGaussians"]
    assert len(p.reductions) == 2 and 0 < m < n and len(p.config["times"]) < F  # both reductions taken
    kept_t = torch.tensor([times.tolist().index(t) for t in p.config["times"]])
    kept = most_covering(scene.canonical.opacities, scene.canonical.scales, m)  # its own test: brute force
    first, count = torch.zeros(m, dtype=torch.int64), torch.full((m,), len(kept_t))  # every Gaussian moves
    held = _ragged({k: v[kept_t][:, kept] for k, v in every.items()}, first, count)
    want = encode_keyframes(held, (first, count), dtype, (scene.t_means[kept], scene.t_scales[kept]))
    assert p.frames == want
