"""Tests of training/densify.py: 3DGS adaptive density control (clone, split, prune, opacity reset) and the
surgery on Adam's moments that goes with it, on each device and without tensors made on the default device."""
import math

import pytest
import torch
from torch import nn

from diff4splat.scene.quaternions import quat_to_rotmat
from training.densify import (
    DensifyConfig,
    DensityStats,
    densify_and_prune,
    prune,
    replace_params,
    reset_opacity,
)

EXTENT = 2.0
CFG = DensifyConfig(grad_threshold=1e-3, percent_dense=0.01, min_opacity=0.005, max_screen_size=20.0,
                    max_world_size=0.1)  # clone/split boundary 0.02 m, world-size prune above 0.2 m


pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


def _params(means, scales, quats=None, opacities=None, seed=0, device="cpu"):
    """Gaussian parameters as fit.py keeps them (log scales, logit opacities) and an Adam with one named
    group per parameter whose moments are non-zero and differ per row (one step taken, then the values
    put back); on ``device`` (drawn on the CPU)."""
    n = means.shape[0]
    g = torch.Generator().manual_seed(seed)
    params = {
        "means": means.float(),
        "scales": torch.log(torch.as_tensor(scales, dtype=torch.float32).expand(n, 3)).clone(),
        "quats": torch.tensor([1.0, 0.0, 0.0, 0.0]).repeat(n, 1) if quats is None else quats.float(),
        "opacities": torch.logit(torch.full((n,), 0.5) if opacities is None else opacities.float()),
        "sh0": torch.rand(n, 1, 3, generator=g),
        "shN": torch.rand(n, 3, 3, generator=g),
    }
    params = {k: nn.Parameter(v.contiguous().to(device)) for k, v in params.items()}
    opt = torch.optim.Adam([{"params": [p], "lr": 1e-3, "name": k} for k, p in params.items()], eps=1e-15)
    for p in params.values():
        p.grad = torch.randn(p.shape, generator=g).to(device)
    values = {k: v.detach().clone() for k, v in params.items()}
    opt.step()
    opt.zero_grad(set_to_none=True)
    with torch.no_grad():
        for k, v in params.items():
            v.copy_(values[k])
    return params, opt


def _stats(grads, radii=None) -> DensityStats:
    """Statistics with the given mean NDC gradient per Gaussian (one view)."""
    grads = torch.as_tensor(grads, dtype=torch.float32)
    s = DensityStats(grads.shape[0])
    s.grad_accum, s.denom = grads.clone(), torch.ones_like(grads)
    s.max_radii = torch.ones_like(grads) if radii is None else torch.as_tensor(radii, dtype=torch.float32)
    return s


def _moments(opt, name):
    p = next(g["params"][0] for g in opt.param_groups if g["name"] == name)
    return opt.state[p]


def test_density_stats_accumulate_ndc_gradient_norms_of_visible_gaussians():
    g = torch.Generator().manual_seed(0)
    W, H = 40, 20
    s = DensityStats(5)
    grads, radii = [], []
    for _ in range(3):
        grads.append(torch.randn(5, 2, generator=g))
        radii.append(torch.tensor([0, 3, 1, 0, 7]) * torch.randint(0, 2, (5,), generator=g))
        s.update(grads[-1], radii[-1], W, H)
    accum, denom, maxr = torch.zeros(5), torch.zeros(5), torch.zeros(5)
    for gr, r in zip(grads, radii, strict=True):
        for i in range(5):
            if r[i] > 0:
                accum[i] += math.hypot(float(gr[i, 0]) * W / 2, float(gr[i, 1]) * H / 2)
                denom[i] += 1
                maxr[i] = max(maxr[i], float(r[i]))
    torch.testing.assert_close(s.grad_accum, accum)
    assert torch.equal(s.denom, denom) and torch.equal(s.max_radii, maxr)
    assert float(denom[0]) == 0 and float(s.mean_grad()[0]) == 0  # never visible → 0, not NaN
    seen = denom > 0
    torch.testing.assert_close(s.mean_grad()[seen], accum[seen] / denom[seen])


def test_clone_copies_a_small_high_gradient_gaussian():
    means = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [0.0, 1.0, 1.0]])
    params, opt = _params(means, 0.01)  # all small (≤ 0.02 m)
    before = {k: v.detach().clone() for k, v in params.items()}
    stats = _stats([5e-3, 1e-4, 2e-3])  # 0 and 2 are hot
    out, counts = densify_and_prune(params, opt, stats, CFG, EXTENT, False, torch.Generator().manual_seed(0))
    assert counts == {"cloned": 2, "split": 0, "pruned": 0}
    for k, v in out.items():
        assert v.shape[0] == 5
        torch.testing.assert_close(v[:3].detach(), before[k], rtol=0, atol=0)  # originals kept as they were
        torch.testing.assert_close(v[3:].detach(), before[k][[0, 2]], rtol=0, atol=0)  # exact copies
    assert stats.grad_accum.shape == (5,) and float(stats.grad_accum.abs().sum()) == 0  # stats reset


def test_split_replaces_a_large_gaussian_by_two_sampled_from_it():
    n = 3000
    q = torch.nn.functional.normalize(torch.tensor([0.9, 0.3, -0.2, 0.25]), dim=0)
    mu = torch.tensor([0.5, -1.0, 3.0])
    s = torch.tensor([0.3, 0.1, 0.05])  # large: 0.3 > 0.02 m
    params, opt = _params(mu.repeat(n, 1), s.repeat(n, 1), quats=q.repeat(n, 1))
    before = {k: v.detach().clone() for k, v in params.items()}
    stats = _stats(torch.full((n,), 1.0))
    cfg = DensifyConfig(grad_threshold=1e-3, max_gaussians=10 * n)
    out, counts = densify_and_prune(params, opt, stats, cfg, EXTENT, False, torch.Generator().manual_seed(0))
    assert counts == {"cloned": 0, "split": n, "pruned": 0}
    assert out["means"].shape == (2 * n, 3)  # the originals are gone, two children each
    torch.testing.assert_close(out["scales"].detach().exp(), (s / 1.6).expand(2 * n, 3))
    for k in ("quats", "opacities", "sh0", "shN"):
        torch.testing.assert_close(out[k].detach(), before[k].repeat(2, *([1] * (before[k].dim() - 1))))
    x = out["means"].detach().double()
    torch.testing.assert_close(x.mean(0), mu.double(), atol=4 * float(s.max()) / math.sqrt(2 * n), rtol=0)
    R = quat_to_rotmat(q[None].double())[0]
    cov = R @ torch.diag(s.double() ** 2) @ R.T  # position ~ N(μ, R S² Rᵀ)
    torch.testing.assert_close(torch.cov(x.T), cov, atol=0.1 * float(s.max()) ** 2, rtol=0)


def test_split_n_three_and_mixed_clone_split():
    means = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [0.0, 1.0, 1.0], [2.0, 0.0, 1.0]])
    scales = torch.tensor([[0.01] * 3, [0.5] * 3, [0.01] * 3, [0.5] * 3])
    params, opt = _params(means, scales)
    before = {k: v.detach().clone() for k, v in params.items()}
    cfg = DensifyConfig(grad_threshold=1e-3, split_n=3)
    out, counts = densify_and_prune(params, opt, _stats([1.0, 1.0, 0.0, 0.0]), cfg, EXTENT, False,
                                    torch.Generator().manual_seed(0))
    assert counts == {"cloned": 1, "split": 1, "pruned": 0}
    # kept: 0, 2, 3 (1 was split), then the clone of 0, then 3 children of 1 with scales / (0.8·3)
    assert out["means"].shape[0] == 3 + 1 + 3
    torch.testing.assert_close(out["means"][:4].detach(), before["means"][[0, 2, 3, 0]])
    torch.testing.assert_close(out["scales"][4:].detach().exp(), torch.full((3, 3), 0.5 / 2.4))


def test_prune_by_opacity_and_by_size_after_reset():
    means = torch.rand(5, 3, generator=torch.Generator().manual_seed(0))
    scales = torch.tensor([[0.01] * 3, [0.01] * 3, [0.3] * 3, [0.01] * 3, [0.01] * 3])
    opac = torch.tensor([0.5, 0.001, 0.5, 0.5, 0.5])
    radii = [1.0, 1.0, 1.0, 25.0, 1.0]  # 3 is too large on screen, 2 in the world (0.3 > 0.1·2)
    for prune_large, kept in ((False, [0, 2, 3, 4]), (True, [0, 4])):
        params, opt = _params(means, scales, opacities=opac)
        before = params["means"].detach().clone()
        out, counts = densify_and_prune(params, opt, _stats(torch.zeros(5), radii), CFG, EXTENT, prune_large,
                                        torch.Generator())
        assert counts == {"cloned": 0, "split": 0, "pruned": 5 - len(kept)}
        torch.testing.assert_close(out["means"].detach(), before[kept])


def test_adam_moments_follow_the_rows():
    means = torch.rand(4, 3, generator=torch.Generator().manual_seed(0))
    opac = torch.tensor([0.5, 0.001, 0.5, 0.5])  # 1 is pruned
    params, opt = _params(means, 0.01, opacities=opac)
    old = {k: {m: _moments(opt, k)[m].clone() for m in ("exp_avg", "exp_avg_sq")} for k in params}
    steps = {k: _moments(opt, k)["step"].clone() for k in params}
    out, _ = densify_and_prune(params, opt, _stats([0.0, 0.0, 0.0, 1.0]), CFG, EXTENT, False, torch.Generator())
    # rows now: 0, 2, 3, clone of 3
    assert {g["name"]: g["params"][0] for g in opt.param_groups} == out  # the groups hold the new tensors
    assert all(p not in opt.state for p in params.values())  # no state left on the old tensors
    for k, p in out.items():
        st = opt.state[p]
        assert torch.equal(st["step"], steps[k])
        for m in ("exp_avg", "exp_avg_sq"):
            assert st[m].shape == p.shape
            assert torch.equal(st[m][:3], old[k][m][[0, 2, 3]])
            assert float(st[m][3:].abs().sum()) == 0  # new rows start with zero moments
    # an optimizer step on the new parameters works (shapes agree)
    for p in out.values():
        p.grad = torch.ones_like(p)
    opt.step()


def test_max_gaussians_cap_takes_the_largest_gradients():
    means = torch.rand(10, 3, generator=torch.Generator().manual_seed(0))
    grads = torch.tensor([0.5, 0.9, 0.1, 0.7, 0.3, 0.8, 0.2, 0.6, 0.4, 0.0]) * 1e-2
    params, opt = _params(means, 0.01)
    before = params["means"].detach().clone()
    cfg = DensifyConfig(grad_threshold=1e-3, max_gaussians=13)
    out, counts = densify_and_prune(params, opt, _stats(grads), cfg, EXTENT, False, torch.Generator())
    assert counts["cloned"] == 3 and out["means"].shape[0] == 13
    torch.testing.assert_close(out["means"][10:].detach(), before[[1, 3, 5]])  # 0.9, 0.7, 0.8 in row order
    # splits cost split_n − 1 each: room 2 with split_n = 3 takes exactly the hottest one
    scales = torch.full((10, 3), 0.5)
    params, opt = _params(means, scales)
    cfg = DensifyConfig(grad_threshold=1e-3, max_gaussians=12, split_n=3)
    out, counts = densify_and_prune(params, opt, _stats(grads), cfg, EXTENT, False, torch.Generator())
    assert counts == {"cloned": 0, "split": 1, "pruned": 0} and out["means"].shape[0] == 12
    # already at the cap: nothing is added
    params, opt = _params(means, 0.01)
    out, counts = densify_and_prune(params, opt, _stats(grads), DensifyConfig(grad_threshold=1e-3, max_gaussians=8),
                                    EXTENT, False, torch.Generator())
    assert counts["cloned"] == 0 and out["means"].shape[0] == 10


def test_reset_opacity_clamps_to_0_01_and_zeroes_its_moments():
    opac = torch.tensor([0.9, 0.005, 0.5])
    params, opt = _params(torch.zeros(3, 3), 0.01, opacities=opac)
    scale_moments = _moments(opt, "scales")["exp_avg"].clone()
    out = reset_opacity(params, opt)
    torch.testing.assert_close(torch.sigmoid(out["opacities"].detach()), torch.tensor([0.01, 0.005, 0.01]))
    st = opt.state[out["opacities"]]
    assert float(st["exp_avg"].abs().sum()) == 0 and float(st["exp_avg_sq"].abs().sum()) == 0
    assert torch.equal(_moments(opt, "scales")["exp_avg"], scale_moments)  # other groups untouched
    assert out["means"] is params["means"]
    with pytest.raises(ValueError, match="opacities"):
        reset_opacity({}, torch.optim.Adam([{"params": [nn.Parameter(torch.zeros(1))], "name": "x"}]))


def test_prune_and_replace_params():
    params, opt = _params(torch.rand(4, 3), 0.01)
    stats = _stats([1.0, 2.0, 3.0, 4.0], [5.0, 6.0, 7.0, 8.0])
    out = prune(params, opt, torch.tensor([True, False, True, False]), stats)
    assert out["means"].shape == (2, 3) and stats.grad_accum.tolist() == [2.0, 4.0]
    assert stats.max_radii.tolist() == [6.0, 8.0] and stats.denom.tolist() == [1.0, 1.0]
    with pytest.raises(ValueError, match="without an Adam group"):
        replace_params({**out, "extra": nn.Parameter(torch.zeros(2))}, opt,
                       {k: v.detach()[:0] for k, v in out.items()}, None)


def test_active_schedule():
    d = DensifyConfig(start=5, until=20, interval=5)
    assert [i for i in range(30) if d.active(i)] == [10, 15, 20]


@pytest.mark.parametrize("field, value", [
    ("start", -1), ("until", 1.5), ("interval", 0), ("interval", True), ("split_n", 1), ("max_gaussians", 0),
    ("opacity_reset_interval", -3), ("grad_threshold", -1e-4), ("percent_dense", math.nan),
    ("min_opacity", "0.1"), ("max_screen_size", -1.0), ("max_world_size", None),
])
def test_densify_config_rejects_bad_fields(field, value):
    with pytest.raises(ValueError, match=field):
        DensifyConfig(**{field: value})


def _densify_inputs(device):
    """(params, optimizer, means2d gradients (6, 2), per-axis radii (6, 2)) on ``device``, for :func:`_densify`."""
    g = torch.Generator().manual_seed(1)
    means = torch.rand(6, 3, generator=g)
    scales = torch.tensor([[0.01] * 3, [0.3] * 3, [0.01] * 3, [0.05] * 3, [0.01] * 3, [0.01] * 3])
    opac = torch.tensor([0.5, 0.5, 0.5, 0.5, 0.001, 0.5])
    params, opt = _params(means, scales, opacities=opac, device=device)
    grads = torch.tensor([[1e-3, 0.0], [1e-3, 1e-3], [0.0, 0.0], [2e-3, 0.0], [0.0, 0.0], [0.0, 1e-5]])
    radii = torch.tensor([[2, 3], [4, 1], [0, 0], [5, 5], [1, 1], [30, 2]])  # per-axis (gsplat ≥ 1.5); 5 too large
    return params, opt, grads.to(device), radii.to(device)


def _densify(params, opt, grads, radii):
    """Statistics from one view, then clone (0), split (1, 3), prune by opacity (4) and screen size (5), an
    opacity reset: (params, counts, stats, optimizer)."""
    stats = DensityStats(6, grads.device)
    stats.update(grads, radii, 40, 20)
    out, counts = densify_and_prune(params, opt, stats, CFG, EXTENT, True, torch.Generator().manual_seed(5))
    return reset_opacity(out, opt), counts, stats, opt


def test_densify_on_each_device(device):
    """The same statistics, clones, split draws (a CPU generator) and prunes on every device."""
    out, counts, stats, opt = _densify(*_densify_inputs(device))
    ref, ref_counts, _, _ = _densify(*_densify_inputs("cpu"))
    assert counts == ref_counts == {"cloned": 1, "split": 2, "pruned": 2}
    assert stats.device.type == device.type and stats.grad_accum.shape == (out["means"].shape[0],)
    for k, p in out.items():
        assert p.device.type == device.type
        assert all(m.device.type == device.type for key, m in opt.state[p].items() if key != "step")
        torch.testing.assert_close(p.detach().cpu(), ref[k].detach(), rtol=1e-6, atol=1e-6)


def test_density_stats_take_the_larger_of_per_axis_radii():
    a, b = DensityStats(3), DensityStats(3)
    grads = torch.tensor([[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]])
    a.update(grads, torch.tensor([[0, 0], [2, 5], [0, 1]]), 10, 10)
    b.update(grads, torch.tensor([0, 5, 1]), 10, 10)
    for x, y in ((a.grad_accum, b.grad_accum), (a.denom, b.denom), (a.max_radii, b.max_radii)):
        assert torch.equal(x, y)
    assert a.denom.tolist() == [0.0, 1.0, 1.0]


def test_densify_makes_nothing_on_the_default_device(no_implicit_device):
    """With torch's default device "meta" (tests/conftest.py) density control on CPU tensors stays on the CPU:
    statistics, clone, split, prune (opacity and size), the cap, an opacity reset and a plain prune."""
    with torch.device("cpu"):
        means = torch.rand(6, 3, generator=torch.Generator().manual_seed(2))
        capped, capped_opt = _params(means, 0.5)
        remove = torch.tensor([True, False, False, False, False, True])
        inputs = _densify_inputs("cpu")
    out, counts, stats, opt = _densify(*inputs)
    assert counts["split"] == 2 and {p.device.type for p in out.values()} == {"cpu"}
    assert {stats.grad_accum.device.type, stats.max_radii.device.type} == {"cpu"}
    cap_stats = DensityStats(6)
    cap_stats.grad_accum, cap_stats.denom = cap_stats.grad_accum + 1.0, cap_stats.denom + 1.0
    cfg = DensifyConfig(grad_threshold=1e-3, max_gaussians=8)
    capped, capped_counts = densify_and_prune(capped, capped_opt, cap_stats, cfg, EXTENT, False, torch.Generator())
    assert capped_counts["split"] == 2 and capped["means"].device.type == "cpu"
    pruned = prune(capped, capped_opt, torch.cat([remove, remove[:2]]), cap_stats)
    assert pruned["means"].shape[0] == 8 - 3 and cap_stats.denom.device.type == "cpu"
