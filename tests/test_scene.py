import math

import pytest
import torch

import diff4splat.scene.dynamic as scene_module
from diff4splat.scene.dynamic import DynamicGaussians
from diff4splat.scene.gaussians import Gaussians
from diff4splat.scene.quaternions import axis_angle_to_quat, quat_to_rotmat


def _gaussians(m=5, seed=0, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    return Gaussians(
        means=torch.randn(m, 3, generator=g, dtype=dtype),
        quats=torch.randn(m, 4, generator=g, dtype=dtype),
        scales=torch.rand(m, 3, generator=g, dtype=dtype) + 0.1,
        opacities=torch.rand(m, generator=g, dtype=dtype),
        sh=torch.randn(m, 1, 3, generator=g, dtype=dtype),
    )


def _identity_quats(t, m, dtype=torch.float64):
    q = torch.zeros(t, m, 4, dtype=dtype)
    q[..., 0] = 1
    return q


def test_static_scene_returns_canonical_and_stores_nothing():
    g = _gaussians()
    scene = DynamicGaussians(g)
    assert scene.is_static and scene.times is None
    assert scene.at(0.3) is g


def test_key_times_are_exact_and_midpoints_interpolate_linearly():
    g = _gaussians()
    times = torch.tensor([0.0, 0.5, 1.0], dtype=torch.float64)
    d_means = torch.randn(3, 5, 3, dtype=torch.float64)
    d_scales = torch.randn(3, 5, 3, dtype=torch.float64) * 0.1
    scene = DynamicGaussians(g, times, d_means, _identity_quats(3, 5), d_scales)
    for k, t in enumerate(times.tolist()):
        gt = scene.at(t)
        torch.testing.assert_close(gt.means, g.means + d_means[k])
        torch.testing.assert_close(gt.scales, g.scales * torch.exp(d_scales[k]))
    gt = scene.at(0.25)
    torch.testing.assert_close(gt.means, g.means + 0.5 * (d_means[0] + d_means[1]))
    torch.testing.assert_close(gt.scales, g.scales * torch.exp(0.5 * (d_scales[0] + d_scales[1])))
    torch.testing.assert_close(gt.opacities, g.opacities)


def test_rotation_offset_is_applied_on_the_left():
    # canonical rotation about x, offset rotation about z: R_t = R_z R_x (Δq ⊗ q)
    m = 1
    q = axis_angle_to_quat(torch.tensor([1.0, 0, 0], dtype=torch.float64), torch.tensor(0.4, dtype=torch.float64))
    g = Gaussians(torch.zeros(m, 3, dtype=torch.float64), q[None], torch.ones(m, 3, dtype=torch.float64),
                  torch.full((m,), 0.5, dtype=torch.float64), torch.zeros(m, 1, 3, dtype=torch.float64))
    dq = axis_angle_to_quat(torch.tensor([0.0, 0, 1], dtype=torch.float64), torch.tensor(0.9, dtype=torch.float64))
    times = torch.tensor([0.0, 1.0], dtype=torch.float64)
    d_quats = torch.stack([torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64), dq[None]])
    scene = DynamicGaussians(g, times, torch.zeros(2, m, 3, dtype=torch.float64), d_quats,
                             torch.zeros(2, m, 3, dtype=torch.float64))
    R = quat_to_rotmat(scene.at(1.0).quats[0])
    torch.testing.assert_close(R, quat_to_rotmat(dq) @ quat_to_rotmat(q))
    # halfway: half the angle (nlerp of two rotations about one axis is exact at the midpoint)
    half = axis_angle_to_quat(torch.tensor([0.0, 0, 1], dtype=torch.float64), torch.tensor(0.45, dtype=torch.float64))
    torch.testing.assert_close(quat_to_rotmat(scene.at(0.5).quats[0]), quat_to_rotmat(half) @ quat_to_rotmat(q))


def test_times_outside_key_range_clamp_and_single_key_time():
    g = _gaussians(3)
    d = torch.randn(1, 3, 3, dtype=torch.float64)
    scene = DynamicGaussians(g, torch.tensor([0.5], dtype=torch.float64), d, _identity_quats(1, 3),
                             torch.zeros(1, 3, 3, dtype=torch.float64))
    torch.testing.assert_close(scene.at(0.0).means, g.means + d[0])
    torch.testing.assert_close(scene.at(1.0).means, g.means + d[0])


def test_select_keeps_deformation_aligned():
    g = _gaussians(6)
    times = torch.tensor([0.0, 1.0], dtype=torch.float64)
    d_means = torch.randn(2, 6, 3, dtype=torch.float64)
    scene = DynamicGaussians(g, times, d_means, _identity_quats(2, 6), torch.zeros(2, 6, 3, dtype=torch.float64))
    mask = torch.tensor([True, False, True, False, False, True])
    sub = scene.select(mask)
    torch.testing.assert_close(sub.at(1.0).means, scene.at(1.0).means[mask])


def test_select_keeps_a_row_shared_by_every_gaussian_a_view():
    g = _gaussians(6)
    times = torch.tensor([0.0, 0.5, 1.0], dtype=torch.float64)
    per_key = torch.randn(3, 1, 3, dtype=torch.float64)  # one log-scale row per key, shared by every Gaussian
    shared = DynamicGaussians(g, times, torch.randn(3, 6, 3, dtype=torch.float64),
                              torch.tensor([1.0, 0, 0, 0], dtype=torch.float64).expand(3, 6, 4),
                              per_key.expand(3, 6, 3))
    dense = DynamicGaussians(g, times, shared.d_means, shared.d_quats.clone(), shared.d_scales.clone())
    mask = torch.tensor([True, False, True, False, False, True])
    for index in (mask, torch.tensor([4, 1, 1]), torch.tensor([], dtype=torch.long)):
        sub, ref = shared.select(index), dense.select(index)
        assert sub.d_quats.stride()[:2] == (0, 0) and sub.d_scales.stride(1) == 0  # still views
        for key in ("d_means", "d_quats", "d_scales"):
            assert torch.equal(getattr(sub, key), getattr(ref, key)), key
        for t in (0.0, 0.3, 1.0):
            torch.testing.assert_close(sub.at(t).scales, ref.at(t).scales)


def test_a_shared_row_is_checked_once_and_deforms_as_its_dense_copy():
    """Rows shared by every Gaussian (stride 0) are validated on their one row (a zero rotation or a NaN scale
    still fails, naming the array) and the numba kernel reads them in place: at() equals the dense copy's."""
    g = _gaussians(7)
    times = torch.tensor([0.0, 1.0], dtype=torch.float64)
    d_means = torch.randn(2, 7, 3, dtype=torch.float64)
    quat = torch.tensor([[0.9, 0.1, -0.2, 0.3], [1.0, 0.0, 0.0, 0.0]], dtype=torch.float64)[:, None].expand(2, 7, 4)
    log_scale = torch.tensor([[0.1, -0.2, 0.0], [0.0, 0.3, 0.0]], dtype=torch.float64)[:, None].expand(2, 7, 3)
    shared = DynamicGaussians(g, times, d_means, quat, log_scale)
    dense = DynamicGaussians(g, times, d_means, quat.clone(), log_scale.clone())
    for t in (0.0, 0.4, 1.0):
        a, b = shared.at(t), dense.at(t)
        for key in ("means", "quats", "scales"):
            torch.testing.assert_close(getattr(a, key), getattr(b, key), rtol=0, atol=0)
    with pytest.raises(ValueError, match="d_quats"):
        DynamicGaussians(g, times, d_means, torch.zeros(2, 1, 4, dtype=torch.float64).expand(2, 7, 4), log_scale)
    with pytest.raises(ValueError, match="d_scales"):
        DynamicGaussians(g, times, d_means, quat, torch.full((2, 1, 3), math.nan, dtype=torch.float64).expand(2, 7, 3))


@pytest.mark.parametrize("temporal", [False, True])
@pytest.mark.parametrize("gate", [0.0, 0.2])
@pytest.mark.parametrize("static", [False, True])
def test_at_of_an_index_is_the_selection_of_at(temporal, gate, static):
    """``at(t, gate, index)`` evaluates only the Gaussians of ``index`` (indices or mask): the same values as the
    subset's own ``at`` (select first, then evaluate), gated the same way."""
    m, k = 40, 5
    g = _gaussians(m, seed=3)
    gen = torch.Generator().manual_seed(4)
    times = torch.linspace(0, 1, k, dtype=torch.float64)
    d = {} if static else {"times": times, "d_means": torch.randn(k, m, 3, generator=gen, dtype=torch.float64),
                           "d_quats": torch.randn(k, m, 4, generator=gen, dtype=torch.float64),
                           "d_scales": 0.1 * torch.randn(k, m, 3, generator=gen, dtype=torch.float64)}
    if temporal:
        d.update(t_means=torch.rand(m, generator=gen, dtype=torch.float64),
                 t_scales=0.05 + 0.3 * torch.rand(m, generator=gen, dtype=torch.float64))
    scene = DynamicGaussians(g, **d)
    mask = torch.rand(m, generator=gen) < 0.5
    for t in (0.0, 0.37, 0.5, 1.0):
        want = scene.select(mask).at(t, gate)
        for index in (mask, torch.nonzero(mask).squeeze(1)):
            got = scene.at(t, gate, index=index)
            for name in ("means", "quats", "scales", "opacities", "sh"):
                torch.testing.assert_close(getattr(got, name), getattr(want, name))
        if temporal and gate > 0:
            assert 0 < want.num_gaussians < int(mask.sum())  # the gate dropped some of the selection, not all
    with pytest.raises(ValueError, match="gate must be >= 0"):
        scene.at(0.5, -1.0, index=mask)


def test_identity_deformation_is_dropped():
    g = _gaussians(4)
    times = torch.tensor([0.0, 1.0], dtype=torch.float64)
    z = torch.zeros(2, 4, 3, dtype=torch.float64)
    assert DynamicGaussians(g, times, z, _identity_quats(2, 4), z).without_deformation().is_static
    moving = DynamicGaussians(g, times, z + 1e-3, _identity_quats(2, 4), z)
    assert not moving.without_deformation().is_static
    assert moving.without_deformation(atol=1e-2).is_static


@pytest.mark.parametrize("bad", ["partial", "shape", "nan", "times_range", "times_order", "zero_quat", "times_0d"])
def test_invalid_deformation_raises(bad):
    g = _gaussians(2)
    times = torch.tensor([0.0, 1.0], dtype=torch.float64)
    dm, dq, ds = torch.zeros(2, 2, 3, dtype=torch.float64), _identity_quats(2, 2), torch.zeros(2, 2, 3,
                                                                                               dtype=torch.float64)
    if bad == "partial":
        args = (times, dm, None, ds)
    elif bad == "shape":
        args = (times, dm[:, :1], dq, ds)
    elif bad == "nan":
        dm[0, 0, 0] = math.nan
        args = (times, dm, dq, ds)
    elif bad == "times_range":
        args = (times + 0.5, dm, dq, ds)
    elif bad == "times_order":
        args = (times.flip(0), dm, dq, ds)
    elif bad == "times_0d":  # an IndexError before the shape check
        args = (times[0], dm[:1], dq[:1], ds[:1])
    else:
        dq[1, 1] = 0
        args = (times, dm, dq, ds)
    with pytest.raises(ValueError):
        DynamicGaussians(g, *args)


def test_time_outside_unit_interval_raises():
    with pytest.raises(ValueError, match="time t"):
        DynamicGaussians(_gaussians()).at(1.5)


def _dynamic_scene(m, k, dtype, seed=0, temporal=True):
    gen = torch.Generator().manual_seed(seed)
    d = {"times": torch.linspace(0, 1, k, dtype=dtype), "d_means": torch.randn(k, m, 3, generator=gen, dtype=dtype),
         "d_quats": torch.randn(k, m, 4, generator=gen, dtype=dtype),
         "d_scales": 0.3 * torch.randn(k, m, 3, generator=gen, dtype=dtype)}
    if temporal:
        d.update(t_means=torch.rand(m, generator=gen, dtype=dtype),
                 t_scales=0.05 + 0.3 * torch.rand(m, generator=gen, dtype=dtype))
    return DynamicGaussians(_gaussians(m, seed=seed + 1, dtype=dtype), **d)


@pytest.mark.parametrize("dtype, tol", [(torch.float32, 2e-6), (torch.float64, 1e-13)])
def test_the_fused_cpu_kernel_of_at_matches_the_reference(monkeypatch, dtype, tol):
    """On the CPU without gradients ``at`` runs the numba kernel (:mod:`diff4splat.scene.kernels`); the reference
    is ``deformation_at`` then ``compose_deformation`` of the same Gaussians. Times at, between and beyond the keys;
    a gate that drops some Gaussians; antipodal key quaternions (the shorter-arc sign)."""
    calls = []
    kernel = scene_module._deform_kernel()
    assert kernel is not None  # numba is a dependency
    monkeypatch.setattr(scene_module, "_deform_kernel", lambda: lambda *a: calls.append(1) or kernel(*a))
    scene = _dynamic_scene(300, 4, dtype)
    scene.d_quats[2, :50] = -scene.d_quats[1, :50]  # the same rotations, opposite signs
    for t in (0.0, 1 / 3, 0.5, 0.9, 1.0):
        got = scene.at(t)
        idx = scene.active_indices(t)
        assert 0 < idx.numel() < 300
        c = scene.canonical.select(idx)
        means, quats, scales = scene_module.compose_deformation(c.means, c.quats, c.scales,
                                                                *scene.deformation_at(t, idx))
        for a, b in ((got.means, means), (got.quats, quats), (got.scales, scales)):
            assert a.dtype == dtype
            torch.testing.assert_close(a, b, rtol=tol, atol=tol)
        torch.testing.assert_close(got.opacities, c.opacities * scene.temporal_opacity(t)[idx])
    assert len(calls) == 5


def test_at_with_gradients_or_an_overflowing_scale_runs_the_reference():
    """Gradients need the PyTorch reference (the kernel has no backward); a scale that overflows is reported by the
    reference's error, as without the kernel."""
    scene = _dynamic_scene(20, 3, torch.float64, temporal=False)
    scene.canonical.means.requires_grad_(True)
    scene.at(0.4).means.sum().backward()
    torch.testing.assert_close(scene.canonical.means.grad, torch.ones_like(scene.canonical.means))
    scene = _dynamic_scene(20, 3, torch.float64, temporal=False)
    scene.d_scales[1, 7, 0] = 1e4  # exp overflows
    with pytest.raises(ValueError, match="scales"):
        scene.at(0.5)
