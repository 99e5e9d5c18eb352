"""Tests of models/hexplane.py: the 4DGS HexPlane deformation field, its regularisers and its file, on each device
and without tensors made on torch's default device."""
import math

import pytest
import torch
from safetensors.torch import save_file

from diff4splat.scene.dynamic import DynamicGaussians, compose_deformation
from diff4splat.scene.gaussians import Gaussians
from diff4splat.scene.quaternions import quat_normalize
from models.hexplane import (
    MIN_EXTENT,
    PLANE_AXES,
    HexPlaneConfig,
    HexPlaneField,
    load_field,
    plane_tv,
    sample_plane,
    save_field,
    time_l1,
    time_smoothness,
)

BOX = torch.tensor([[-1.0, -2.0, 0.0], [1.0, 2.0, 4.0]])
TINY = dict(feature_dim=2, resolution=(3, 4, 3, 5), multires=(1, 2), net_width=5, trunk_depth=1)


def _perturbed(config: HexPlaneConfig, bounds=BOX, seed: int = 0, dtype=torch.float32) -> HexPlaneField:
    """A field whose zero-initialised head outputs and constant time planes are randomised (seeded)."""
    torch.manual_seed(seed)
    field = HexPlaneField(config, bounds).to(dtype)
    with torch.no_grad():
        for head in (field.d_means_head, field.d_quats_head, field.d_scales_head):
            head[-1].weight.normal_(0.0, 0.5)
            head[-1].bias.normal_(0.0, 0.1)
        for planes in field.grids:
            for i in (2, 4, 5):
                planes[i].add_(0.3 * torch.randn_like(planes[i]))
    return field


def _points(n: int, seed: int = 1, dtype=torch.float32) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    u = torch.rand(n, 3, generator=g, dtype=torch.float64)
    return (BOX[0].double() + u * (BOX[1] - BOX[0]).double()).to(dtype)


def test_default_config_matches_reference_and_parameter_count():
    cfg = HexPlaneConfig()
    assert (cfg.feature_dim, cfg.resolution, cfg.multires, cfg.net_width, cfg.trunk_depth) == (
        32, (64, 64, 64, 25), (1, 2), 64, 0)
    assert (cfg.plane_tv_weight, cfg.time_smoothness_weight, cfg.l1_time_planes) == (1e-4, 1e-2, 1e-4)
    field = HexPlaneField(cfg, BOX)
    assert sum(p.numel() for p in field.parameters()) == cfg.num_parameters == 2_444_170  # the docstring's figure
    tiny = HexPlaneConfig(**TINY)
    assert sum(p.numel() for p in HexPlaneField(tiny, BOX).parameters()) == tiny.num_parameters
    # plane (a, b) has shape (1, F, res_b, res_a); spatial resolution × multires, time resolution unchanged
    assert PLANE_AXES == ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))
    assert tuple(field.grids[1][2].shape) == (1, 32, 25, 128)  # xt at scale 2
    assert tuple(field.grids[0][0].shape) == (1, 32, 64, 64)
    for planes in field.grids:
        for (_, b), p in zip(PLANE_AXES, planes, strict=True):
            if b == 3:
                assert bool((p == 1).all())
            else:
                assert 0.1 <= float(p.detach().min()) < float(p.detach().max()) <= 0.5


def test_identity_at_init():
    field = HexPlaneField(HexPlaneConfig(**TINY), BOX)
    means = torch.cat([_points(50), torch.tensor([[9.0, -9.0, 100.0]])])
    for t in (0.0, 0.37, 1.0, torch.linspace(0, 1, 51)):
        d_means, d_quats, d_scales = field(means, t)
        assert torch.equal(d_means, torch.zeros(51, 3))
        assert torch.equal(d_quats, torch.tensor([[1.0, 0.0, 0.0, 0.0]]).expand(51, 4))
        assert torch.equal(d_scales, torch.zeros(51, 3))
    quats, scales = torch.randn(51, 4), torch.rand(51, 3) + 0.1
    m, q, s = compose_deformation(means, quats, scales, *field(means, 0.5))
    assert torch.equal(m, means) and torch.equal(s, scales)
    torch.testing.assert_close(q, quat_normalize(quats))
    # the features do reach the trunk: only the heads' last layers are zero
    assert float(field.trunk(field.features(means, 0.5)).detach().abs().sum()) > 0


def _bilinear(plane: torch.Tensor, u: float, v: float) -> torch.Tensor:
    """Hand-written bilinear interpolation, align_corners=True, clamped to the border. → (C,)."""
    H, W = plane.shape[-2:]
    x = (min(max(u, -1.0), 1.0) + 1) / 2 * (W - 1)
    y = (min(max(v, -1.0), 1.0) + 1) / 2 * (H - 1)
    x0, y0 = min(int(math.floor(x)), W - 2), min(int(math.floor(y)), H - 2)
    fx, fy = x - x0, y - y0
    p = plane[0]
    return ((1 - fx) * (1 - fy) * p[:, y0, x0] + fx * (1 - fy) * p[:, y0, x0 + 1]
            + (1 - fx) * fy * p[:, y0 + 1, x0] + fx * fy * p[:, y0 + 1, x0 + 1])


def test_sample_plane_is_bilinear_with_border_clamp():
    plane = torch.arange(24, dtype=torch.float64).reshape(1, 2, 3, 4) ** 1.5  # not bilinear itself
    coords = [(-1.0, -1.0), (1.0, 1.0), (0.2, -0.4), (-0.7, 0.9), (3.0, -5.0), (-1e9, 1e9)]
    got = sample_plane(plane, torch.tensor(coords, dtype=torch.float64))
    for (u, v), row in zip(coords, got, strict=True):
        torch.testing.assert_close(row, _bilinear(plane, u, v))
    # corners: u indexes W (columns), v indexes H (rows)
    torch.testing.assert_close(got[0], plane[0, :, 0, 0])
    torch.testing.assert_close(got[1], plane[0, :, 2, 3])
    torch.testing.assert_close(got[4], plane[0, :, 0, 3])  # outside: clamped to the top-right corner
    torch.testing.assert_close(got[5], plane[0, :, 2, 0])


def test_features_axes_box_and_time_mapping():
    """The xy plane varies along x, the zt plane along t: checks which coordinate drives which plane axis,
    the box normalisation (min → −1, max → +1) and the time mapping t → 2t − 1 over the whole axis."""
    cfg = HexPlaneConfig(feature_dim=1, resolution=(3, 4, 5, 6), multires=(1,), net_width=2)
    field = HexPlaneField(cfg, BOX).double()
    with torch.no_grad():
        for p in field.grids[0]:
            p.fill_(1.0)
        field.grids[0][0].copy_(torch.arange(3.0).view(1, 1, 1, 3).expand(1, 1, 4, 3))  # xy: x index
        field.grids[0][5].copy_(10.0 ** torch.arange(6.0).view(1, 1, 6, 1).expand(1, 1, 6, 5))  # zt: 10^t row
    means = torch.tensor([[-1.0, 0, 0], [0.0, 0, 0], [1.0, 0, 0], [0.5, 0, 0], [50.0, -9, 99]], dtype=torch.float64)
    x_index = torch.tensor([0.0, 1.0, 2.0, 1.5, 2.0], dtype=torch.float64)
    for t, row in ((0.0, 1.0), (1.0, 1e5), (0.2, 10.0), (0.3, 0.5 * 10 + 0.5 * 100)):
        torch.testing.assert_close(field.features(means, t)[:, 0], x_index * row)
    # the time tensor form is the per-point float form
    ts = torch.tensor([0.0, 1.0, 0.2, 0.3, 1.0], dtype=torch.float64)
    torch.testing.assert_close(field.features(means, ts)[:, 0], x_index * torch.tensor([1.0, 1e5, 10, 55, 1e5],
                                                                                     dtype=torch.float64))


def test_regularisers_closed_forms():
    h = torch.arange(5.0, dtype=torch.float64).view(1, 1, 5, 1)
    w = torch.arange(4.0, dtype=torch.float64).view(1, 1, 1, 4)
    linear_in_h = (3 * h + w**2).expand(1, 2, 5, 4)
    assert float(time_smoothness(linear_in_h)) == 0.0  # second difference along h vanishes
    assert float(time_smoothness((h**2).expand(1, 2, 5, 4))) == pytest.approx(4.0)  # Δ² h² = 2
    assert float(time_smoothness((w**2).expand(1, 2, 5, 4))) == 0.0  # only the h (time) axis counts
    checker = ((-1.0) ** (h + w)).expand(1, 3, 5, 4)
    assert float(plane_tv(checker)) == pytest.approx(2 * (4 + 4))  # every neighbour differs by 2
    assert float(plane_tv((0.5 * w).expand(1, 1, 5, 4))) == pytest.approx(2 * 0.25)  # h part 0, w part 0.5²
    assert float(plane_tv((h**2).expand(1, 1, 5, 4))) == pytest.approx(2 * (1 + 9 + 25 + 49) / 4)
    assert float(time_l1(torch.ones(1, 2, 3, 4))) == 0.0
    assert float(time_l1(torch.full((1, 2, 3, 4), 0.5))) == 0.5
    assert float(time_l1(torch.full((1, 2, 3, 4), 1.5))) == 0.5
    with pytest.raises(ValueError, match="H >= 3"):
        time_smoothness(torch.ones(1, 1, 2, 4))


@pytest.mark.parametrize("plane_reg", ["smoothness", "tv"])
def test_field_regularization_is_the_reference_weighted_sum(plane_reg):
    cfg = HexPlaneConfig(feature_dim=2, resolution=(4, 4, 4, 5), multires=(1, 2), net_width=4,
                         plane_tv_weight=0.3, time_smoothness_weight=0.05, l1_time_planes=0.7, plane_reg=plane_reg)
    field = HexPlaneField(cfg, BOX).double()
    with torch.no_grad():
        for planes in field.grids:
            for (_, b), p in zip(PLANE_AXES, planes, strict=True):
                rows = torch.arange(p.shape[2], dtype=torch.float64).view(1, 1, -1, 1)
                # spatial planes: h²; time planes: 0.5·h² (second difference 1, |1 − p| known)
                p.copy_((rows**2 if b != 3 else 0.5 * rows**2).expand_as(p))
    total = 0.0
    for planes in field.grids:
        H = planes[0].shape[2]
        spatial = 4.0 if plane_reg == "smoothness" else 2 * sum((2 * k + 1) ** 2 for k in range(H - 1)) / (H - 1)
        l1 = sum(abs(1 - 0.5 * k**2) for k in range(5)) / 5
        total += 0.3 * 3 * spatial + 0.05 * 3 * 1.0 + 0.7 * 3 * l1
    assert float(field.regularization().detach()) == pytest.approx(total, rel=1e-12)
    field.regularization().backward()
    assert all(p.grad is not None for planes in field.grids for p in planes)


@pytest.mark.slow
def test_gradients_match_finite_differences():
    field = _perturbed(HexPlaneConfig(**TINY), dtype=torch.float64)
    names = ["grids.0.0", "grids.1.2", "grids.1.5", "trunk.0.weight", "trunk.2.bias"]
    params = dict(field.named_parameters())
    means = _points(6, seed=3, dtype=torch.float64).requires_grad_(True)
    times = torch.tensor([0.1, 0.33, 0.5, 0.71, 0.9, 0.05], dtype=torch.float64)

    def f(*inputs):
        *ps, m = inputs
        out = torch.func.functional_call(field, dict(zip(names, ps, strict=True)), (m, times))
        return torch.cat([o.reshape(-1) for o in out])

    inputs = tuple(params[n].detach().clone().requires_grad_(True) for n in names) + (means,)
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-6, rtol=1e-5)

    holder = _Holder(field)

    def reg(plane_xy, plane_xt):
        return torch.func.functional_call(holder, {"field.grids.0.0": plane_xy, "field.grids.0.2": plane_xt}, ())

    planes = (params["grids.0.0"].detach().clone().requires_grad_(True),
              params["grids.0.2"].detach().clone().requires_grad_(True))
    assert torch.autograd.gradcheck(reg, planes, eps=1e-6, atol=1e-6, rtol=1e-5)
    # x outside the box is clamped: zero gradient along x, but y, z inside still get one
    far = torch.tensor([[50.0, 0.3, 1.7]], dtype=torch.float64, requires_grad=True)
    sum(o.sum() for o in field(far, 0.5)).backward()
    assert float(far.grad[0, 0]) == 0.0 and float(far.grad[0, 1:].abs().sum()) > 0


class _Holder(torch.nn.Module):
    """Wraps a field so ``functional_call`` can reach ``regularization`` through ``forward``."""

    def __init__(self, field: HexPlaneField):
        super().__init__()
        self.field = field

    def forward(self):
        return self.field.regularization()


def test_save_load_round_trip(tmp_path):
    field = _perturbed(HexPlaneConfig(**TINY, plane_reg="tv"), seed=4)
    path = tmp_path / "sub" / "field.safetensors"
    save_field(path, field)
    assert sorted(p.name for p in path.parent.iterdir()) == ["field.safetensors"]  # no temporary left
    loaded = load_field(path)
    assert loaded.config == field.config and torch.equal(loaded.bounds, field.bounds)
    means = torch.cat([_points(20), torch.tensor([[7.0, 7.0, 7.0]])])
    for a, b in zip(field(means, 0.4), loaded(means, 0.4), strict=True):
        assert torch.equal(a, b)
    assert torch.equal(field.regularization(), loaded.regularization())
    field64 = _perturbed(HexPlaneConfig(**TINY), seed=4, dtype=torch.float64)
    save_field(path, field64)
    loaded64 = load_field(path)
    assert loaded64.grids[0][0].dtype == torch.float64 and torch.equal(loaded64.grids[0][0], field64.grids[0][0])


def test_load_field_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="no file"):
        load_field(tmp_path / "missing.safetensors")
    garbage = tmp_path / "garbage.safetensors"
    garbage.write_bytes(b"\x07\x00\x00\x00\x00\x00\x00\x00not json")
    with pytest.raises(ValueError, match="not a readable safetensors"):
        load_field(garbage)
    other = tmp_path / "other.safetensors"
    save_file({"x": torch.zeros(2)}, str(other), metadata={"format": "something-else"})
    with pytest.raises(ValueError, match="format 'something-else'"):
        load_field(other)
    field = HexPlaneField(HexPlaneConfig(**TINY), BOX)
    tensors = {k: v.contiguous() for k, v in field.state_dict().items()}
    meta = {"format": "diff4splat-hexplane", "version": "1", "config": '{"feature_dim": 2}'}
    mismatch = tmp_path / "mismatch.safetensors"
    save_file(tensors, str(mismatch), metadata=meta)
    with pytest.raises(ValueError, match="does not match its config"):
        load_field(mismatch)
    save_file(tensors, str(mismatch), metadata={**meta, "version": "99"})
    with pytest.raises(ValueError, match="version '99'"):
        load_field(mismatch)
    save_file(tensors, str(mismatch), metadata={**meta, "config": '{"feature_dim": 0}'})
    with pytest.raises(ValueError, match="feature_dim"):
        load_field(mismatch)


def test_empty_input():
    field = _perturbed(HexPlaneConfig(**TINY))
    means = torch.zeros(0, 3, requires_grad=True)
    d_means, d_quats, d_scales = field(means, 0.5)
    assert (d_means.shape, d_quats.shape, d_scales.shape) == ((0, 3), (0, 4), (0, 3))
    (d_means.sum() + d_quats.sum() + d_scales.sum()).backward()
    d_means, d_quats, d_scales = field.deformations_at(torch.zeros(0, 3), torch.tensor([0.0, 1.0]))
    assert (d_means.shape, d_quats.shape, d_scales.shape) == ((2, 0, 3), (2, 0, 4), (2, 0, 3))


@pytest.mark.parametrize("bounds", [
    [[-1e30, -1e30, -1e30], [1e30, 1e30, 1e30]],  # huge
    [[0.0, 0.0, 0.0], [1e-9, 1e-9, 1e-9]],  # below MIN_EXTENT
    [[2.0, 3.0, 4.0], [2.0, 3.0, 4.0]],  # a single point
    [[1e6, 0.0, 0.0], [1e6, 1.0, 1.0]],  # a degenerate axis far from the origin
    [[-3e38, -3e38, -3e38], [3e38, 3e38, 3e38]],  # the extent overflows float32
])
def test_extreme_inputs_stay_finite(bounds):
    field = _perturbed(HexPlaneConfig(**TINY), bounds=torch.tensor(bounds))
    inf = float("inf")
    means = torch.tensor([[0.0, 0.0, 0.0], [1e30, -1e30, 1e30], [-3e38, 3e38, 1.0], [2.0, 3.0, 4.0],
                          [inf, -inf, 0.5]], requires_grad=True)
    out = field(means, torch.tensor([0.0, 1.0, 0.5, 0.25, 0.5]))
    assert all(bool(torch.isfinite(o).all()) for o in out)
    sum(o.sum() for o in out).backward()
    assert bool(torch.isfinite(means.grad).all())
    assert all(bool(torch.isfinite(p.grad).all()) for p in field.parameters() if p.grad is not None)


def test_degenerate_axis_gets_min_extent():
    field = HexPlaneField(HexPlaneConfig(**TINY), torch.tensor([[0.0, 0.0, 0.5], [2.0, 2.0, 0.5]])).double()
    means = torch.tensor([[1.0, 1.0, 0.5], [1.0, 1.0, 0.5 + MIN_EXTENT / 4], [0.0, 2.0, 9.0]], dtype=torch.float64)
    torch.testing.assert_close(field.normalize(means),
                               torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 0.5], [-1.0, 1.0, 1.0]], dtype=torch.float64))
    # far outside the box takes the box corner's deformation
    field = _perturbed(HexPlaneConfig(**TINY))
    for a, b in zip(field(torch.tensor([[1e30, -50.0, 9.0]]), 0.6), field(BOX[[1, 0, 1], [0, 1, 2]][None], 0.6),
                    strict=True):
        torch.testing.assert_close(a, b)


def test_deformations_at_equals_field_at_key_times():
    """deformations_at returns tensors only; DynamicGaussians built from them deforms as compose_deformation of the
    field's output at each key time."""
    field = _perturbed(HexPlaneConfig(**TINY), seed=7)
    n = 23
    torch.manual_seed(0)
    canonical = Gaussians(_points(n), torch.randn(n, 4), torch.rand(n, 3) + 0.05, torch.rand(n) * 0.9,
                          torch.randn(n, 1, 3))
    times = torch.tensor([0.0, 0.3, 0.65, 1.0])
    sampled = field.deformations_at(canonical.means, times, chunk=5)
    assert all(isinstance(x, torch.Tensor) for x in sampled)
    dyn = DynamicGaussians(canonical, times, *sampled)
    for k, t in enumerate(times.tolist()):
        d_means, d_quats, d_scales = field(canonical.means, t)
        torch.testing.assert_close(dyn.d_means[k], d_means, rtol=0, atol=1e-6)
        torch.testing.assert_close(dyn.d_quats[k], d_quats, rtol=0, atol=1e-6)
        torch.testing.assert_close(dyn.d_scales[k], d_scales, rtol=0, atol=1e-6)
        g = dyn.at(t)
        m, q, s = compose_deformation(canonical.means, canonical.quats, canonical.scales, d_means, d_quats, d_scales)
        torch.testing.assert_close(g.means, m, rtol=0, atol=1e-6)
        torch.testing.assert_close(g.quats, q, rtol=0, atol=1e-6)
        torch.testing.assert_close(g.scales, s, rtol=1e-6, atol=0)
    assert not dyn.d_means.requires_grad
    assert float((dyn.d_means[0] - dyn.d_means[-1]).abs().max()) > 1e-4  # the perturbed field moves points


@pytest.mark.parametrize("kwargs, match", [
    ({"feature_dim": 0}, "feature_dim"),
    ({"net_width": 2.5}, "net_width"),
    ({"trunk_depth": -1}, "trunk_depth"),
    ({"resolution": (64, 64, 64)}, "resolution"),
    ({"resolution": (64, 64, 2, 25)}, "resolution"),
    ({"multires": ()}, "multires"),
    ({"multires": (1, 0)}, "multires"),
    ({"plane_tv_weight": -1e-4}, "plane_tv_weight"),
    ({"time_smoothness_weight": float("nan")}, "time_smoothness_weight"),
    ({"l1_time_planes": float("inf")}, "l1_time_planes"),
    ({"plane_reg": "l2"}, "plane_reg"),
])
def test_bad_config_raises(kwargs, match):
    with pytest.raises(ValueError, match=match):
        HexPlaneConfig(**kwargs)


@pytest.mark.parametrize("bounds, match", [
    (torch.zeros(3, 3), "shape"),
    (torch.tensor([[0.0, 0, 0], [1.0, float("nan"), 1]]), "non-finite"),
    (torch.tensor([[0.0, 0, 0], [1.0, -1.0, 1]]), "max >= min"),
    (torch.zeros(2, 3, dtype=torch.int64), "float"),
])
def test_bad_bounds_raise(bounds, match):
    with pytest.raises(ValueError, match=match):
        HexPlaneField(HexPlaneConfig(**TINY), bounds)


def test_bad_times_and_means_raise():
    field = HexPlaneField(HexPlaneConfig(**TINY), BOX)
    means = _points(4)
    for t, match in ((1.5, r"\[0, 1\]"), (-0.1, r"\[0, 1\]"), (float("nan"), r"\[0, 1\]"),
                     (torch.zeros(3), r"shape \(4,\)"), (torch.tensor([0.0, 0.5, 2.0, 1.0]), r"\[0, 1\]")):
        with pytest.raises(ValueError, match=match):
            field(means, t)
    with pytest.raises(ValueError, match="means"):
        field(torch.zeros(4, 2), 0.5)
    with pytest.raises(ValueError, match="NaN"):
        field(torch.tensor([[0.0, float("nan"), 0.0]]), 0.5)
    with pytest.raises(ValueError, match="dtype"):
        field(means.double(), 0.5)
    for times, match in ((torch.tensor([0.5, 1.5]), r"times must lie in \[0, 1\]"), (torch.zeros(0), "times"),
                         (torch.zeros(2, 1), "times"), (torch.tensor([0.5, math.inf]), "times")):
        with pytest.raises(ValueError, match=match):
            field.deformations_at(means, times)
    with pytest.raises(ValueError, match="chunk must be a positive int"):
        field.deformations_at(means, torch.tensor([0.5]), chunk=0)


def test_field_on_each_device(tmp_path, device):
    """A field made on the CPU and moved, made from bounds on the device, or loaded onto it: the same numbers
    (on CUDA within float32 tolerance); its deformation stays on the device of its inputs."""
    field = _perturbed(HexPlaneConfig(**TINY), seed=5)
    means = _points(30)
    ref = field(means, 0.3)
    moved = _perturbed(HexPlaneConfig(**TINY), seed=5).to(device)
    save_field(tmp_path / "f.safetensors", field)
    loaded = load_field(tmp_path / "f.safetensors", map_location=device)
    for f in (moved, loaded):
        assert {p.device.type for p in [*f.parameters(), *f.buffers()]} == {device.type}
        out = f(means.to(device), torch.full((30,), 0.3, device=device))
        for a, b in zip(out, ref, strict=True):
            assert a.device.type == device.type
            torch.testing.assert_close(a.cpu(), b, rtol=1e-5, atol=1e-6)
        assert f.regularization().device.type == device.type
        canonical = Gaussians(means, quat_normalize(torch.randn(30, 4)), torch.full((30, 3), 0.1),
                              torch.full((30,), 0.5), torch.zeros(30, 1, 3)).to(device)
        d_means = f.deformations_at(canonical.means, torch.tensor([0.0, 0.3]))[0]  # times on the CPU
        assert d_means.device.type == device.type
        torch.testing.assert_close(d_means[1].cpu(), ref[0], rtol=1e-5, atol=1e-6)
    made = HexPlaneField(HexPlaneConfig(**TINY), BOX.to(device))  # default: the bounds' device
    assert {p.device.type for p in made.parameters()} == {device.type}
    on_cpu = HexPlaneField(HexPlaneConfig(**TINY), BOX.to(device), device="cpu")
    assert {p.device.type for p in [*on_cpu.parameters(), *on_cpu.buffers()]} == {"cpu"}


def test_load_field_leaves_the_random_state_alone(tmp_path):
    save_field(tmp_path / "f.safetensors", _perturbed(HexPlaneConfig(**TINY)))
    state = torch.get_rng_state()
    load_field(tmp_path / "f.safetensors")
    assert torch.equal(torch.get_rng_state(), state)


def test_field_makes_nothing_on_the_default_device(tmp_path, no_implicit_device):
    """With torch's default device "meta" (tests/conftest.py) a field on CPU bounds is made, run, regularised,
    sampled, saved and loaded on the CPU."""
    with torch.device("cpu"):
        bounds, means, times = BOX.clone(), _points(10), torch.tensor([0.0, 0.5, 1.0])
        canonical = Gaussians(means, torch.tensor([[1.0, 0, 0, 0]]).expand(10, 4), torch.full((10, 3), 0.1),
                              torch.full((10,), 0.5), torch.zeros(10, 1, 3))
    field = HexPlaneField(HexPlaneConfig(**TINY), bounds)
    assert {p.device.type for p in [*field.parameters(), *field.buffers()]} == {"cpu"}
    out = [*field(means, 0.5), field.regularization(), field.deformations_at(canonical.means, times)[1]]
    assert {t.device.type for t in out} == {"cpu"}
    assert HexPlaneField(HexPlaneConfig(**TINY), [[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]).bounds.device.type == "cpu"
    save_field(tmp_path / "f.safetensors", field)
    loaded = load_field(tmp_path / "f.safetensors")
    assert {p.device.type for p in [*loaded.parameters(), *loaded.buffers()]} == {"cpu"}
    assert torch.equal(loaded(means, 0.5)[0], out[0])
