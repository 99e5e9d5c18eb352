"""Tests of the physical camera models: fisheye maps vs closed forms, Newton inversion, validity
ranges, thin-lens sample pattern and ray geometry, rolling-shutter row times, validation."""
import math

import pytest
import torch

from diff4splat.cameras import camera_rays
from diff4splat.cameras.lenses import (
    FisheyeKB,
    FisheyePolynomial,
    RollingShutter,
    ThinLens,
    check_camera,
    concentric_disk,
    generate_rays,
    hammersley,
)

D = torch.float64
K = torch.tensor([[30.0, 0.0, 20.0], [0.0, 24.0, 15.0], [0.0, 0.0, 1.0]], dtype=D)


def _point(theta, phi, dist=2.0):
    """Camera-frame point at angle θ from +z, azimuth φ (from +x towards +y), distance ``dist``."""
    theta, phi = torch.as_tensor(theta, dtype=D), torch.as_tensor(phi, dtype=D)
    return torch.as_tensor(dist, dtype=D)[...,
                                          None] * torch.stack([torch.sin(theta) * torch.cos(phi),
                                                               torch.sin(theta) * torch.sin(phi), torch.cos(theta)], -1)


@pytest.mark.parametrize("k", [(0.0, 0.0, 0.0, 0.0), (0.05, -0.01, 0.002, -1e-4)])
def test_kb_projection_matches_closed_form(k):
    """OpenCV fisheye: pixel = (fx·θ_d·cosφ + cx, fy·θ_d·sinφ + cy), θ_d = θ(1 + k1θ² + … + k4θ⁸);
    θ up to 100° (behind the image plane)."""
    lens = FisheyeKB(*k)
    theta = torch.tensor([0.0, 0.3, 0.9, 1.4, math.radians(100)], dtype=D)
    phi = torch.tensor([0.2, 1.0, -2.0, 2.9, -0.7], dtype=D)
    pix, ok = lens.project(_point(theta, phi, 3.0), K)
    t2 = theta ** 2
    td = theta * (1 + k[0] * t2 + k[1] * t2**2 + k[2] * t2**3 + k[3] * t2**4)
    expect = torch.stack([30.0 * td * torch.cos(phi) + 20.0, 24.0 * td * torch.sin(phi) + 15.0], -1)
    assert bool(ok.all())
    torch.testing.assert_close(pix, expect, rtol=0, atol=1e-10)


def test_polynomial_projection_matches_quadratic_formula():
    """θ = k1·r + k2·r² inverts to r = (−k1 + sqrt(k1² + 4k2θ))/(2k2)."""
    k1, k2 = 0.01, -1e-5
    lens = FisheyePolynomial(k1=k1, k2=k2)
    theta = torch.tensor([0.0, 0.5, 1.2, math.radians(95), 2.4], dtype=D)
    phi = torch.tensor([0.0, 0.7, -1.3, 2.0, 3.0], dtype=D)
    r = (-k1 + torch.sqrt(k1 * k1 + 4 * k2 * theta)) / (2 * k2)
    pix, ok = lens.project(_point(theta, phi), K)
    expect = torch.stack([r * torch.cos(phi) + 20.0, r * torch.sin(phi) + 15.0], -1)
    assert bool(ok.all())
    torch.testing.assert_close(pix, expect, rtol=0, atol=1e-9)
    torch.testing.assert_close(lens.radius(theta), r, rtol=0, atol=1e-9)


def test_polynomial_max_angle_is_first_turning_point_or_pi():
    turn = FisheyePolynomial(k1=0.01, k2=-1e-5)  # θ' = 0 at r = 500, θ(500) = 2.5 < π
    assert turn.r_max == pytest.approx(500.0, rel=1e-12) and turn.theta_max == pytest.approx(2.5, rel=1e-12)
    steep = FisheyePolynomial(k1=0.02, k2=-1e-5)  # turning point θ(1000) = 10 > π: stop where θ = π
    r_pi = (0.02 - math.sqrt(0.02**2 - 4e-5 * math.pi)) / 2e-5
    assert steep.r_max == pytest.approx(r_pi, rel=1e-10) and steep.theta_max == pytest.approx(math.pi, rel=1e-12)
    cubic = FisheyePolynomial(k1=0.01, k3=-3e-8)  # θ' = 0.01 − 9e-8 r² = 0 at r = 1000/3, θ = 20/9 < π
    assert cubic.r_max == pytest.approx(1000 / 3, rel=1e-10) and cubic.theta_max == pytest.approx(20 / 9, rel=1e-10)


def test_kb_max_angle_is_end_of_monotone_range():
    lens = FisheyeKB(k1=-0.1)  # dθ_d/dθ = 1 − 0.3θ² = 0 at θ = sqrt(1/0.3)
    th = math.sqrt(1 / 0.3)
    assert lens.theta_max == pytest.approx(th, rel=1e-12)
    assert lens.theta_d_max == pytest.approx(th * (1 - 0.1 * th * th), rel=1e-12)
    assert FisheyeKB().theta_max == pytest.approx(math.pi)


@pytest.mark.parametrize("lens", [FisheyeKB(0.05, -0.01, 0.002, -1e-4), FisheyeKB(k1=-0.1),
                                  FisheyePolynomial(k1=0.012, k2=-2e-5, k3=1e-8), FisheyePolynomial(k1=0.02, k4=1e-12)])
def test_newton_inversion_round_trips(lens):
    g = torch.Generator().manual_seed(0)
    theta = torch.rand(500, generator=g, dtype=D) * lens.theta_max * 0.999
    phi = (torch.rand(500, generator=g, dtype=D) - 0.5) * 2 * math.pi
    p = _point(theta, phi, 1.0 + torch.rand(500, generator=g, dtype=D))
    pix, ok = lens.project(p, K)
    d, ok2 = lens.unproject(pix, K)
    assert bool(ok.all()) and bool(ok2.all())
    torch.testing.assert_close(d, p / p.norm(dim=-1, keepdim=True), rtol=0, atol=1e-9)
    pix2, _ = lens.project(d * 5.0, K)
    torch.testing.assert_close(pix2, pix, rtol=0, atol=1e-7)


def test_newton_inverse_has_implicit_function_gradient():
    lens = FisheyePolynomial(k1=0.01, k2=-1e-5, k3=3e-9)
    theta = torch.tensor([0.2, 1.0, 2.0], dtype=D, requires_grad=True)
    r = lens.radius(theta)
    (g,) = torch.autograd.grad(r.sum(), theta)
    torch.testing.assert_close(g, 1.0 / lens.dtheta(r.detach()), rtol=1e-10, atol=0)
    kb = FisheyeKB(k1=0.03, k2=-0.01)
    td = torch.tensor([0.1, 0.8, 1.3], dtype=D, requires_grad=True)
    th = kb.undistort(td)
    (g,) = torch.autograd.grad(th.sum(), td)
    torch.testing.assert_close(g, 1.0 / kb.ddistort(th.detach()), rtol=1e-10, atol=0)


def test_beyond_max_angle_is_invalid_and_finite():
    lens = FisheyeKB(k1=-0.1)
    r_pix = torch.linspace(0, 2.0, 101, dtype=D) * 30.0  # θ_d up to 2 > θ_d_max ≈ 1.217
    pix = torch.stack([20.0 + r_pix, torch.full_like(r_pix, 15.0)], -1)
    d, ok = lens.unproject(pix, K)
    assert bool(torch.isfinite(d).all())
    assert torch.equal(ok, r_pix / 30.0 <= lens.theta_d_max)
    p = _point(torch.tensor([1.0, 1.9, 3.0], dtype=D), torch.zeros(3, dtype=D))
    _, okp = lens.project(p, K)
    assert okp.tolist() == [True, False, False]
    poly = FisheyePolynomial(k1=0.01, k2=-1e-5)
    d, ok = poly.unproject(torch.tensor([[20.0 + 499.0, 15.0], [20.0 + 501.0, 15.0]], dtype=D), K)
    assert ok.tolist() == [True, False] and bool(torch.isfinite(d).all())


def test_hammersley_and_concentric_disk():
    pts = hammersley(64)
    # (0, m, 2)-net: every 8×8 stratum of the unit square holds exactly one point, at its centre
    cells = (pts * 8).floor().long()
    assert len({(int(a), int(b)) for a, b in cells}) == 64
    torch.testing.assert_close((pts * 64) % 1, torch.full_like(pts, 0.5))
    # concentric map: square boundary → unit circle, centre → origin, area preserving (E‖x‖² = ½)
    edge = torch.stack([torch.linspace(0, 1, 50, dtype=D), torch.zeros(50, dtype=D)], -1)
    torch.testing.assert_close(concentric_disk(edge).norm(dim=-1), torch.ones(50, dtype=D))
    assert concentric_disk(torch.tensor([[0.5, 0.5]], dtype=D)).abs().max() == 0
    n = 200
    g = (torch.stack(torch.meshgrid(torch.arange(n, dtype=D), torch.arange(n, dtype=D), indexing="ij"), -1) + 0.5) / n
    disk = concentric_disk(g.reshape(-1, 2))
    assert float((disk**2).sum(-1).mean()) == pytest.approx(0.5, rel=1e-4)


def test_thin_lens_samples_cover_the_aperture():
    lens = ThinLens(aperture_radius=0.05, focus_distance=2.0, spp=1024)
    s = lens.aperture_samples()
    assert s.shape == (1024, 2) and float(s.norm(dim=-1).max()) <= 0.05 + 1e-15
    assert float(s.mean(0).abs().max()) < 1e-4  # centred
    assert float((s[:, 0] ** 2).mean()) == pytest.approx(0.05**2 / 4, rel=0.01)  # uniform disk: E x² = A²/4
    assert ThinLens(0.05, 2.0, spp=1).aperture_samples().abs().max() == 0  # spp = 1 is the pinhole


def test_thin_lens_rays_meet_at_the_focus_plane():
    vm = torch.eye(4, dtype=D)
    vm[:3, 3] = torch.tensor([0.3, -0.1, 0.5], dtype=D)
    lens = ThinLens(aperture_radius=0.04, focus_distance=3.0, spp=8)
    o, d, ok = generate_rays(vm[None], K[None], 8, 6, "pinhole", lens)
    assert o.shape == d.shape == (1, 6, 8, 8, 3) and bool(ok.all())
    torch.testing.assert_close(d.norm(dim=-1), torch.ones(1, 6, 8, 8, dtype=D))
    o_pin, d_pin = camera_rays(vm[None], K[None], 8, 6)
    # the pinhole ray reaches camera depth 3 at s = 3 / d_cam,z; every lens ray passes through that point
    centre = o_pin[0, 0, 0]
    d_cam_z = d_pin[..., 2]  # R = I: camera and world axes agree
    focus = o_pin + d_pin * (3.0 / d_cam_z)[..., None]
    s = (focus[..., None, :] - o)[..., 2] / d[..., 2]
    torch.testing.assert_close(o + s[..., None] * d, focus[..., None, :].expand_as(o), rtol=0, atol=1e-12)
    assert float((o - centre).norm(dim=-1).max()) <= 0.04 + 1e-12
    assert float(o[..., 2].sub(centre[2]).abs().max()) < 1e-15  # lens plane z = 0 in camera frame


def test_pinhole_rays_are_camera_rays():
    vm = torch.eye(4, dtype=D)[None]
    o, d, ok = generate_rays(vm, K[None], 7, 5)
    o2, d2 = camera_rays(vm, K[None], 7, 5)
    assert torch.equal(d[:, :, :, 0], d2) and torch.equal(o[:, :, :, 0], o2) and bool(ok.all())


def test_rolling_shutter_row_times_and_bands():
    rs = RollingShutter(duration=0.2, chunks=None)
    H, t = 10, 0.5
    expect = (t - 0.1) + (torch.arange(H, dtype=D) + 0.5) / H * 0.2
    torch.testing.assert_close(rs.row_times(H, t), expect)
    assert rs.band_times(H, t) == pytest.approx(expect.tolist())
    assert RollingShutter(0.2, chunks=1).band_times(H, t) == pytest.approx([0.5])  # global shutter at the frame time
    bands = RollingShutter(0.2, chunks=3).row_bands(H)
    assert bands == [(0, 3), (3, 6), (6, 10)]
    start = RollingShutter(0.2, chunks=3, anchor="start")
    assert start.band_times(H, 0.3) == pytest.approx([0.3 + 0.2 * (a + b) / 20 for a, b in bands])
    assert float(rs.row_times(H, 1.0).max()) == 1.0 and float(rs.row_times(H, 0.0).min()) == 0.0  # clamped
    with pytest.raises(ValueError, match="chunks"):
        RollingShutter(0.1, chunks=11).row_bands(10)


@pytest.mark.parametrize("make,field", [
    (lambda: FisheyePolynomial(k1=0.0), "k1"), (lambda: FisheyePolynomial(k0=0.1, k1=0.01), "k0"),
    (lambda: FisheyePolynomial(k1=0.01, k3=float("nan")), "k3"), (lambda: FisheyeKB(k2=float("inf")), "k2"),
    (lambda: FisheyeKB(k1="0.1"), "k1"), (lambda: ThinLens(-0.1, 2.0), "aperture_radius"),
    (lambda: ThinLens(0.1, 0.0), "focus_distance"), (lambda: ThinLens(0.1, 2.0, spp=0), "spp"),
    (lambda: ThinLens(0.1, 2.0, spp=2.5), "spp"), (lambda: RollingShutter(-0.1), "duration"),
    (lambda: RollingShutter(1.5), "duration"), (lambda: RollingShutter(0.1, chunks=0), "chunks"),
    (lambda: RollingShutter(0.1, anchor="end"), "anchor"),
])
def test_bad_parameters_raise_naming_the_field(make, field):
    with pytest.raises(ValueError, match=field):
        make()


def test_check_camera_pairs():
    assert check_camera("pinhole", None) is None
    assert check_camera("fisheye", None) == FisheyeKB()
    with pytest.raises(ValueError, match="camera_model"):
        check_camera("ortho", None)
    with pytest.raises(ValueError, match="ThinLens"):
        check_camera("pinhole", FisheyeKB())
    with pytest.raises(ValueError, match="FisheyeKB or FisheyePolynomial"):
        check_camera("fisheye", ThinLens(0.1, 1.0))
    with pytest.raises(ValueError, match="render_rolling_shutter"):
        check_camera("pinhole", RollingShutter(0.1))
