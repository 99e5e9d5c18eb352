"""Tests of the ray path: 3DGRT response vs brute force, culling vs no culling, pinhole agreement with the
rasterizer (measured tolerance), fisheye beyond 180°, validity limits, thin-lens focus and blur, gradients."""
import importlib
import math

import pytest
import torch

from diff4splat.cameras.lenses import FisheyeKB, FisheyePolynomial, RollingShutter, ThinLens, generate_rays
from diff4splat.render import rasterize
from diff4splat.render.raytrace import composite_rays, ray_gaussian_response, raytrace, whitening
from diff4splat.scene.quaternions import axis_angle_to_quat, quat_to_rotmat
from diff4splat.utils.constants import ALPHA_MIN

D = torch.float64
ID = torch.eye(4, dtype=D)[None]


def _K(f, cx, cy):
    return torch.tensor([[[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]]], dtype=D)


raytrace_module = importlib.import_module("diff4splat.render.raytrace")  # the package's name is the function


def _random(n, seed, lo=(-2.5, -2.0, 5.0), hi=(2.5, 2.0, 10.0), smin=0.01, smax=0.05, sh=None):
    g = torch.Generator().manual_seed(seed)
    r = lambda *s: torch.rand(*s, generator=g, dtype=D)  # noqa: E731
    lo, hi = torch.tensor(lo, dtype=D), torch.tensor(hi, dtype=D)
    means = lo + (hi - lo) * r(n, 3)
    quats = torch.randn(n, 4, generator=g, dtype=D)
    scales = smin + (smax - smin) * r(n, 3)
    opac = 0.1 + 0.85 * r(n)
    colors = r(n, 3) if sh is None else 0.5 * torch.randn(n, (sh + 1) ** 2, 3, generator=g, dtype=D)
    return [means, quats, scales, opac, colors]


def test_response_is_the_maximum_along_the_ray():
    """exp(−½‖d'×o'‖²/‖d'‖²) and t_max equal the max / argmax of the Gaussian sampled densely along the ray."""
    g = torch.Generator().manual_seed(0)
    means, quats, scales = torch.randn(5, 3, generator=g, dtype=D), torch.randn(5, 4, generator=g, dtype=D), \
        0.2 + torch.rand(5, 3, generator=g, dtype=D)
    origins = torch.randn(7, 3, generator=g, dtype=D)
    dirs = torch.nn.functional.normalize(torch.randn(7, 3, generator=g, dtype=D), dim=-1)
    resp, t_max = ray_gaussian_response(origins, dirs, means, whitening(quats, scales))
    W = whitening(quats, scales)
    t = torch.linspace(-8, 8, 40001, dtype=D)  # spacing 4e-4: the sampled max is within 1e-6 of the true one
    x = origins[:, None, None, :] + t[None, :, None, None] * dirs[:, None, None, :]  # (R, T, 1, 3)
    m = torch.einsum("gij,rtgj->rtgi", W, x - means)  # (R, T, G, 3)
    dens = torch.exp(-0.5 * (m * m).sum(-1))
    best, arg = dens.max(dim=1)
    torch.testing.assert_close(resp, best, rtol=0, atol=1e-6)
    torch.testing.assert_close(t_max, t[arg], rtol=0, atol=5e-4)


def test_single_isotropic_gaussian_closed_form_any_camera():
    """Isotropic Gaussian (σ = s) seen from the origin: alpha = o·exp(−½(‖μ‖² − (μ·d)²)/s²) along ray d."""
    mu, s, o = torch.tensor([[0.3, -0.2, 2.0]], dtype=D), 0.15, 0.7
    K = _K(20.0, 12.0, 10.0)
    for model, params in (("pinhole", None), ("fisheye", FisheyeKB(0.02, -0.01)),
                          ("fisheye", FisheyePolynomial(k1=0.05))):
        out, alpha, meta = raytrace(mu, torch.tensor([[1.0, 0, 0, 0]], dtype=D), torch.full((1, 3), s, dtype=D),
                                    torch.tensor([o], dtype=D), torch.ones(1, 1, dtype=D), ID, K, 24, 20,
                                    render_mode="RGB+D", camera_model=model, camera_params=params)
        _, d, _ = generate_rays(ID, K, 24, 20, model, params)
        d = d[0, :, :, 0]
        proj = (d * mu).sum(-1)
        a = o * torch.exp(-0.5 * ((mu * mu).sum() - proj**2) / s**2)
        a = torch.where(a >= ALPHA_MIN, a, 0.0)
        torch.testing.assert_close(alpha[0, ..., 0], a, rtol=0, atol=1e-12)
        torch.testing.assert_close(out[0, ..., 0], a, rtol=0, atol=1e-12)
        torch.testing.assert_close(out[0, ..., 1], a * proj * d[..., 2], rtol=0, atol=1e-12)  # D = Σ w·t_max·d_z


@pytest.mark.parametrize("model,params", [
    ("pinhole", None), ("pinhole", ThinLens(0.08, 4.0, spp=4)), ("fisheye", FisheyePolynomial(k1=0.06, k2=-2e-4)),
])
@pytest.mark.slow
def test_culling_and_batching_change_nothing(model, params, monkeypatch):
    """Tiles, cone culling and pair batches vs one brute-force composite of every ray with every Gaussian; the
    culling takes as many tiles at once as keep (tiles × Gaussians) within the budget (25 of the 30 tiles here)."""
    culled = []
    cull = raytrace_module.cull_tiles
    monkeypatch.setattr(raytrace_module, "cull_tiles",
                        lambda cones, *a: culled.append(len(cones[0])) or cull(cones, *a))
    args = _random(150, 1, lo=(-4, -4, -3), hi=(4, 4, 8), smin=0.05, smax=0.3)
    args[0] = args[0][(args[0].norm(dim=-1) > 0.5)][:120]
    args = [a[: len(args[0])] for a in args]
    vm = ID.clone()
    vm[0, :3, :3] = torch.linalg.matrix_exp(torch.tensor([[0, -0.1, 0.2], [0.1, 0, -0.05], [-0.2, 0.05, 0]], dtype=D))
    vm[0, :3, 3] = torch.tensor([0.1, -0.2, 0.3], dtype=D)
    K, bg = _K(14.0, 13.0, 11.0), torch.tensor([[0.2, 0.5, 0.1]], dtype=D)
    out, alpha, meta = raytrace(*args, vm, K, 26, 22, camera_model=model, camera_params=params, backgrounds=bg,
                                tile_size=5, budget=3000)
    o, d, ok = generate_rays(vm, K, 26, 22, model, params)
    S = d.shape[3]
    col, acc, dist = composite_rays(o.reshape(-1, 3), d.reshape(-1, 3), args[0], whitening(args[1], args[2]),
                                    args[3], args[4], 0.01, 1e10)
    ok = ok.reshape(-1)
    col, acc, dist = col * ok[:, None], acc * ok, dist * ok
    ref_rgb = (col + (1 - acc)[:, None] * bg).reshape(22, 26, S, 3).mean(2)
    ref_a = acc.reshape(22, 26, S).mean(2)
    z_axis = vm[0, 2]  # a hit's camera z: o_z + t·d_z, so Σ w·z = o_z·Σ w + d_z·Σ w·t per ray
    z_sum = (o.reshape(-1, 3) @ z_axis[:3] + z_axis[3]) * acc + (d.reshape(-1, 3) @ z_axis[:3]) * dist
    ref_ed = z_sum.reshape(22, 26, S).mean(2) / ref_a.clamp(min=1e-10)
    assert float(ref_a.max()) > 0.5 and meta["n_pairs"][0] < 26 * 22 * S * len(args[0])  # culling did cull
    assert culled == [3000 // len(args[0]), 30 - 3000 // len(args[0])]
    torch.testing.assert_close(out[0, ..., :3], ref_rgb, rtol=0, atol=1e-12)
    torch.testing.assert_close(alpha[0, ..., 0], ref_a, rtol=0, atol=1e-12)
    torch.testing.assert_close(out[0, ..., 3], ref_ed, rtol=0, atol=1e-9)


@pytest.mark.slow
def test_pinhole_ray_path_agrees_with_rasterizer():
    """Small Gaussians (1–5 cm at 5–10 m, ≤ 1.5 px σ) seen through a 56° pinhole, SH degree 2.

    The rasterizer uses the EWA affine approximation of the projected Gaussian, composites by centre
    depth and dilates by eps2d (set to 0 here); the ray path is exact along each ray and sorts by hit
    distance. Measured over seeds 0–3 (48×40, 200 Gaussians): colour max |Δ| ≤ 3.9e-3, mean ≤ 3.2e-5;
    alpha max ≤ 4.8e-3, mean ≤ 8.2e-5. Bounds below leave ~2.5× margin. (Dense overlapping scenes
    differ more where two Gaussians swap order between centre depth and hit distance: up to 0.15 in
    one pixel at 800 Gaussians, mean 4e-4.)
    """
    args = _random(200, 2, sh=2)
    K, bg = _K(45.0, 24.0, 20.0), torch.tensor([[0.1, 0.2, 0.3]], dtype=D)
    r1, a1, m1 = rasterize(*args, ID, K, 48, 40, eps2d=0.0, backgrounds=bg, sh_degree=2)
    r2, a2, m2 = raytrace(*args, ID, K, 48, 40, backgrounds=bg, sh_degree=2)
    assert "radii" in m1 and m2["samples_per_pixel"] == 1
    assert float(a1.max()) > 0.5
    dc, da = (r1[..., :3] - r2[..., :3]).abs(), (a1 - a2).abs()
    assert float(dc.max()) < 1e-2 and float(dc.mean()) < 1e-4
    assert float(da.max()) < 1.2e-2 and float(da.mean()) < 2e-4
    # depth: both give camera z, the ray path the hits' z, within a Gaussian's extent (≤ 5 cm) of the
    # rasterizer's centre z where a pixel is mostly covered
    cover = a1[..., 0] > 0.3
    assert float((r2[..., 3] - r1[..., 3])[cover].abs().max()) < 0.05


@pytest.mark.parametrize("lens", [FisheyeKB(), ThinLens(aperture_radius=0.05, focus_distance=2.0, spp=4)],
                         ids=["fisheye", "thin-lens"])
def test_the_depth_channel_is_camera_z_for_every_camera(lens):
    """An opaque Gaussian 45° off the axis of a rotated, moved camera, at camera z = 2 m: "ED" at its pixel is its
    z (as the rasterizer's and gsplat's depth), not its distance along the ray (2.83 m), for a fisheye and for a
    thin lens whose rays start across its aperture; "D" is that times alpha."""
    R = axis_angle_to_quat(torch.tensor([0.3, 1.0, -0.2], dtype=D), torch.tensor(0.7, dtype=D))
    rot = quat_to_rotmat(R)
    vm = torch.eye(4, dtype=D)
    vm[:3, :3], vm[:3, 3] = rot, torch.tensor([0.4, -0.1, 0.3], dtype=D)
    p_cam = torch.tensor([2.0, 0.0, 2.0], dtype=D)
    mean = (rot.T @ (p_cam - vm[:3, 3]))[None]
    args = [mean, torch.tensor([[1.0, 0, 0, 0]], dtype=D), torch.full((1, 3), 0.1, dtype=D),
            torch.tensor([0.99], dtype=D), torch.ones(1, 3, dtype=D)]
    K = _K(24.0, 32.0, 24.0)
    model = "fisheye" if isinstance(lens, FisheyeKB) else "pinhole"
    out, alpha, _ = raytrace(*args, vm[None], K, 64, 48, render_mode="RGB+ED", camera_model=model, camera_params=lens)
    d, _, _ = raytrace(*args, vm[None], K, 64, 48, render_mode="D", camera_model=model, camera_params=lens)
    i, j = divmod(int(alpha[0, ..., 0].argmax()), 64)
    assert float(alpha[0, i, j, 0]) > 0.5
    assert float(out[0, i, j, 3]) == pytest.approx(2.0, abs=0.05)  # z within σ, not the 2.83 m along the ray
    torch.testing.assert_close(d[..., 0], out[..., 3] * alpha[..., 0])


@pytest.mark.parametrize("lens", [None, ThinLens(0.01, 3.0, spp=2)], ids=["pinhole", "thin-lens"])
def test_low_precision_inputs_and_autocast_compute_in_float32(lens):
    """float16/bfloat16 inputs are computed in float32, as the tile path computes them (the ray path called
    torch.linalg.inv on half Ks: "Low precision dtypes not supported"), and a bfloat16 autocast region changes
    nothing: the float32 result, bit for bit."""
    args = [a.float() for a in _random(30, 4)] + [ID.float(), _K(20.0, 12.0, 10.0).float()]
    ref, ref_a, _ = raytrace(*args, 24, 20, camera_params=lens)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        auto, auto_a, _ = raytrace(*args, 24, 20, camera_params=lens)
    assert auto.dtype == torch.float32 and torch.equal(auto, ref) and torch.equal(auto_a, ref_a)
    for dtype in (torch.float16, torch.bfloat16):
        low = [a.to(dtype).requires_grad_(i == 0) for i, a in enumerate(args)]
        out, alpha, _ = raytrace(*low, 24, 20, camera_params=lens)
        want, want_a, _ = raytrace(*[a.detach().float() for a in low], 24, 20, camera_params=lens)
        assert out.dtype == torch.float32 and torch.equal(out, want) and torch.equal(alpha, want_a)
        out.sum().backward()
        assert low[0].grad.dtype == dtype and bool(torch.isfinite(low[0].grad).all())


def test_hits_are_sorted_by_distance_not_z():
    """Behind the image plane (fisheye, ray at 120° from the axis) the nearer Gaussian has the larger z:
    a z sort would composite the far one first."""
    lens = FisheyePolynomial(k1=math.radians(130) / 16)
    K = _K(1.0, 16.5, 16.5)  # the centre of pixel (16, 16 + r) lies r px along +x from the principal point
    r_pix = 14.0
    theta = lens.theta(torch.tensor(r_pix, dtype=D))
    d = torch.stack([torch.sin(theta), torch.tensor(0.0, dtype=D), torch.cos(theta)])
    means = torch.stack([2.0 * d, 4.0 * d])  # z = 2cos120° > 4cos120°
    out, alpha, _ = raytrace(means, torch.tensor([[1.0, 0, 0, 0]] * 2, dtype=D), torch.full((2, 3), 0.1, dtype=D),
                             torch.tensor([0.9, 0.9], dtype=D), torch.eye(3, dtype=D)[:2], ID, K, 33, 33,
                             render_mode="RGB", camera_model="fisheye", camera_params=lens)
    assert float(theta) > math.pi / 2 and float(means[0, 2]) > float(means[1, 2])
    torch.testing.assert_close(out[0, 16, 16 + 14], torch.tensor([0.9, 0.1 * 0.9, 0.0], dtype=D), rtol=0, atol=1e-9)


def test_early_termination_matches_3dgs_rule():
    """Six opaque layers on the axis (alpha 0.95): T = 1, .05, .0025, 1.25e-4, then < 1e-4 stops."""
    n = 6
    means = torch.tensor([[0.0, 0.0, 2.0 + 0.5 * i] for i in range(n)], dtype=D)[torch.tensor([3, 0, 5, 1, 4, 2])]
    rank = torch.argsort(torch.argsort(means[:, 2]))
    cols = torch.eye(n, dtype=D).requires_grad_()
    out, alpha, _ = raytrace(means, torch.tensor([[1.0, 0, 0, 0]] * n, dtype=D), 0.3 * means[:, 2:3].expand(n, 3),
                             torch.full((n,), 0.95, dtype=D), cols, ID, _K(10.0, 2.5, 2.5), 5, 5, render_mode="RGB")
    w = torch.tensor([0.95 * 0.05**k if k < 3 else 0.0 for k in range(n)], dtype=D)[rank]
    torch.testing.assert_close(out[0, 2, 2], w, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(alpha[0, 2, 2, 0], torch.tensor(1 - 0.05**3, dtype=D), rtol=1e-12, atol=1e-12)
    (g,) = torch.autograd.grad(out[0, 2, 2].sum(), cols)
    torch.testing.assert_close(g, w[:, None].expand(n, n))


def test_fisheye_beyond_180_degrees_sees_behind_the_image_plane():
    """Equidistant-like polynomial with a 220° image circle: a Gaussian at θ = 100° (z < 0) lands where
    the closed form r = θ/k1 says; the pinhole camera does not see it."""
    k1 = math.radians(110) / 32
    lens = FisheyePolynomial(k1=k1)
    K = _K(1.0, 32.0, 32.0)
    theta, phi = math.radians(100), math.radians(30)
    mu = 2.0 * torch.tensor([[math.sin(theta) * math.cos(phi), math.sin(theta) * math.sin(phi), math.cos(theta)]],
                            dtype=D)
    g = [mu, torch.tensor([[1.0, 0, 0, 0]], dtype=D), torch.full((1, 3), 0.12, dtype=D), torch.tensor([0.9], dtype=D),
         torch.ones(1, 1, dtype=D)]
    _, alpha, _ = rasterize(*g, ID, K, 64, 64, render_mode="RGB", camera_model="fisheye", camera_params=lens)
    a = alpha[0, ..., 0]
    r = theta / k1
    expect = torch.tensor([32.0 + r * math.cos(phi), 32.0 + r * math.sin(phi)], dtype=D)
    pix, ok = lens.project(mu, K[0])
    torch.testing.assert_close(pix[0], expect, rtol=0, atol=1e-9)
    ys, xs = torch.meshgrid(torch.arange(64, dtype=D) + 0.5, torch.arange(64, dtype=D) + 0.5, indexing="ij")
    centroid = torch.stack([(a * xs).sum(), (a * ys).sum()]) / a.sum()
    assert float(mu[0, 2]) < 0 and float(a.max()) > 0.8
    assert float((centroid - expect).norm()) < 0.2
    _, a_pin, _ = rasterize(*g, ID, K, 64, 64, render_mode="RGB")
    assert float(a_pin.max()) == 0.0


@pytest.mark.slow
def test_rays_beyond_max_angle_give_background_and_no_nan():
    """KB lens with k1 = −0.1 folds back at θ ≈ 104.6°; with f = 12 px the image corners lie past it."""
    lens = FisheyeKB(k1=-0.1)
    g = torch.Generator().manual_seed(3)
    dirs = torch.nn.functional.normalize(torch.randn(300, 3, generator=g, dtype=D), dim=-1)
    args = [3.0 * dirs, torch.randn(300, 4, generator=g, dtype=D), torch.full((300, 3), 0.25, dtype=D),
            torch.full((300,), 0.6, dtype=D), torch.rand(300, 3, generator=g, dtype=D)]
    args = [a.clone().requires_grad_() for a in args]
    K, bg = _K(12.0, 16.0, 16.0), torch.tensor([[0.3, 0.6, 0.9]], dtype=D)
    out, alpha, _ = rasterize(*args, ID, K, 32, 32, backgrounds=bg, camera_model="fisheye", camera_params=lens)
    _, _, ok = generate_rays(ID, K, 32, 32, "fisheye", lens)
    ok = ok[0, ..., 0]
    assert 0 < int((~ok).sum()) < 32 * 32 // 2
    assert bool(torch.isfinite(out).all()) and bool(torch.isfinite(alpha).all())
    assert bool((alpha[0][~ok] == 0).all()) and bool((out[0][~ok][:, :3] == bg).all())
    assert bool((out[0][~ok][:, 3] == 0).all())
    assert float(alpha[0][ok].detach().mean()) > 0.3  # Gaussians all around, also behind the camera
    grads = torch.autograd.grad((out * torch.rand(out.shape, generator=g, dtype=D)).sum() + alpha.sum(), args)
    for gr in grads:
        assert bool(torch.isfinite(gr).all()) and float(gr.abs().max()) > 0


def _flat_plane(z):
    """8×7 grid (0.5 m pitch) of Gaussians flat in z (σz = 0.1 mm, rotated only about z) centred on the
    plane z; in-plane σ ≤ 7 cm, so their alpha ≥ 1/255 supports (≤ 3.3σ) do not overlap and no hit order
    is ambiguous."""
    g = torch.Generator().manual_seed(5)
    gy, gx = torch.meshgrid(torch.arange(7, dtype=D) - 3.0, torch.arange(8, dtype=D) - 3.5, indexing="ij")
    n = gx.numel()
    means = torch.stack([0.5 * gx.reshape(-1), 0.5 * gy.reshape(-1), torch.full((n,), z, dtype=D)], -1)
    quats = axis_angle_to_quat(torch.tensor([0.0, 0.0, 1.0], dtype=D).expand(n, 3),
                               torch.rand(n, generator=g, dtype=D) * 3)
    scales = torch.cat([0.03 + 0.04 * torch.rand(n, 2, generator=g, dtype=D), torch.full((n, 1), 1e-4, dtype=D)], -1)
    return [means, quats, scales, 0.2 + 0.7 * torch.rand(n, generator=g, dtype=D),
            torch.rand(n, 3, generator=g, dtype=D)]


@pytest.mark.slow
def test_in_focus_plane_matches_pinhole_and_spp1_is_pinhole():
    args = _flat_plane(4.0)
    K, bg = _K(30.0, 16.0, 14.0), torch.tensor([[0.0, 0.1, 0.2]], dtype=D)
    pin, a_pin, _ = raytrace(*args, ID, K, 32, 28, backgrounds=bg)
    dof, a_dof, meta = rasterize(*args, ID, K, 32, 28, backgrounds=bg, camera_params=ThinLens(0.1, 4.0, spp=16))
    assert meta["samples_per_pixel"] == 16 and float(a_pin.max()) > 0.5
    # every lens ray of a pixel crosses the plane at the pinhole ray's point: measured |Δ| ≤ 3e-10
    torch.testing.assert_close(dof[..., :3], pin[..., :3], rtol=0, atol=1e-8)
    torch.testing.assert_close(a_dof, a_pin, rtol=0, atol=1e-8)
    one, a_one, _ = rasterize(*args, ID, K, 32, 28, backgrounds=bg, camera_params=ThinLens(0.1, 4.0, spp=1))
    torch.testing.assert_close(one, pin, rtol=0, atol=1e-12)
    torch.testing.assert_close(a_one, a_pin, rtol=0, atol=1e-12)
    # the same aperture focused elsewhere blurs the plane
    far, _, _ = rasterize(*args, ID, K, 32, 28, backgrounds=bg, camera_params=ThinLens(0.1, 8.0, spp=16))
    assert float((far[..., :3] - pin[..., :3]).abs().max()) > 0.05


def _second_moment_x(alpha):
    xs = torch.arange(alpha.shape[1], dtype=D) + 0.5
    w = alpha.sum(0)
    m = (w * xs).sum() / w.sum()
    return float((w * (xs - m) ** 2).sum() / w.sum())


@pytest.mark.slow
def test_defocus_blur_grows_as_circle_of_confusion_predicts():
    """A point at depth z seen through a thin lens focused at z_f spreads over lens offsets
    δ = f·l·(1/z_f − 1/z) pixels (l the lens point, metres): the image variance grows by
    f²(1/z_f − 1/z)²·Var(l_x), and for a uniform disk of radius A by (CoC/2)²/4 with the circle of
    confusion diameter CoC = 2·f·A·|z − z_f|/(z·z_f)."""
    f, z, zf, s = 40.0, 2.0, 4.0, 0.05
    K = _K(f, 32.0, 32.0)
    g = [torch.tensor([[0.0, 0.0, z]], dtype=D), torch.tensor([[1.0, 0, 0, 0]], dtype=D),
         torch.full((1, 3), s, dtype=D),
         torch.tensor([0.5], dtype=D), torch.ones(1, 1, dtype=D)]
    var0 = _second_moment_x(raytrace(*g, ID, K, 64, 64, render_mode="RGB")[1][0, ..., 0])
    for A in (0.2, 0.4):
        lens = ThinLens(A, zf, spp=64)
        var = _second_moment_x(rasterize(*g, ID, K, 64, 64, render_mode="RGB", camera_params=lens)[1][0, ..., 0])
        lx = lens.aperture_samples()[:, 0]
        pattern = f**2 * (1 / zf - 1 / z) ** 2 * float(((lx - lx.mean()) ** 2).mean())
        assert var - var0 == pytest.approx(pattern, rel=0.02)
        coc = 2 * f * A * abs(z - zf) / (z * zf)
        assert var - var0 == pytest.approx((coc / 2) ** 2 / 4, rel=0.05)


@pytest.mark.slow
def test_gradcheck_fisheye_and_thin_lens():
    means = torch.tensor([[0.05, -0.02, 2.0], [-0.1, 0.08, 2.5], [0.12, 0.1, 3.0]], dtype=D)
    quats = torch.tensor([[1.0, 0.1, -0.2, 0.05], [0.8, -0.3, 0.1, 0.2], [0.9, 0.0, 0.3, -0.1]], dtype=D)
    scales = torch.tensor([[0.5, 0.35, 0.2], [0.45, 0.6, 0.3], [0.7, 0.5, 0.4]], dtype=D)
    opac = torch.tensor([0.5, 0.6, 0.7], dtype=D)
    colors = torch.tensor([[0.9, 0.1, 0.2], [0.2, 0.8, 0.3], [0.1, 0.3, 0.9]], dtype=D)
    K, bg = _K(6.0, 3.0, 3.0), torch.tensor([[0.3, 0.2, 0.1]], dtype=D)
    wts = torch.rand(1, 6, 6, 4, generator=torch.Generator().manual_seed(0), dtype=D)
    for model, params in (("fisheye", FisheyeKB(0.05)), ("pinhole", ThinLens(0.3, 2.5, spp=4))):
        def fn(m, q, s, o, c, model=model, params=params):  # weighted sums of the image keep the Jacobian small
            col, alpha, _ = rasterize(m, q, s, o, c, ID, K, 6, 6, backgrounds=bg, camera_model=model,
                                      camera_params=params)
            return (col * wts).sum((0, 1, 2)), (alpha[..., 0] * wts[..., 0]).sum()

        inputs = tuple(t.clone().requires_grad_() for t in (means, quats, scales, opac, colors))
        assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-6, rtol=1e-5, fast_mode=True)


@pytest.mark.parametrize("mode,channels", [("RGB", 3), ("D", 1), ("ED", 1), ("RGB+D", 4)])
def test_render_modes_and_backgrounds(mode, channels):
    args = _random(40, 7, smin=0.05, smax=0.2)
    K, bg = _K(30.0, 12.0, 10.0), torch.tensor([[0.2, 0.4, 0.6]], dtype=D)
    lens = FisheyeKB()
    out, alpha, _ = raytrace(*args, ID, K, 24, 20, render_mode=mode, backgrounds=bg, camera_model="fisheye",
                             camera_params=lens)
    full, alpha_full, _ = raytrace(*args, ID, K, 24, 20, render_mode="RGB+ED", backgrounds=bg, camera_model="fisheye",
                                   camera_params=lens)
    assert out.shape == (1, 20, 24, channels)
    torch.testing.assert_close(alpha, alpha_full)
    if mode == "RGB":
        torch.testing.assert_close(out, full[..., :3])
    if mode == "ED":
        torch.testing.assert_close(out, full[..., 3:])
    if mode == "D":
        torch.testing.assert_close(out[..., 0], full[..., 3] * alpha_full[..., 0])


def test_plain_pinhole_stays_on_the_tile_path():
    args = _random(20, 8)
    _, _, meta = rasterize(*args, ID, _K(30.0, 12.0, 10.0), 24, 20)
    assert "radii" in meta and "samples_per_pixel" not in meta
    _, _, meta = rasterize(*args, ID, _K(30.0, 12.0, 10.0), 24, 20, camera_model="fisheye")
    assert meta["camera_params"] == FisheyeKB() and "radii" not in meta


@pytest.mark.parametrize("kw,match", [
    ({"camera_model": "orthographic"}, "camera_model"),
    ({"camera_model": "fisheye", "camera_params": ThinLens(0.1, 2.0)}, "camera_params"),
    ({"camera_params": FisheyeKB()}, "camera_params"),
    ({"camera_params": RollingShutter(0.1)}, "render_rolling_shutter"),
    ({"camera_params": ThinLens(0.1, 2.0), "rasterize_mode": "antialiased"}, "rasterize_mode"),
    ({"camera_params": ThinLens(0.1, 2.0), "render_mode": "RGBD"}, "render_mode"),
])
def test_bad_camera_options_raise(kw, match):
    with pytest.raises(ValueError, match=match):
        rasterize(*_random(5, 0), ID, _K(30.0, 12.0, 10.0), 24, 20, **kw)


def test_bad_tensor_on_ray_path_names_it():
    args = _random(5, 0)
    args[2] = args[2][:, :2]
    with pytest.raises(ValueError, match="scales"):
        rasterize(*args, ID, _K(30.0, 12.0, 10.0), 24, 20, camera_model="fisheye")


@pytest.mark.slow
def test_float32_far_gaussians_match_float64():
    """Gaussians of 2–5 cm at 20–60 m: ‖o'‖ ~ 10³, where the expanded form ‖o'‖²‖d'‖² − (o'·d')² would
    lose float32; the cross-product form keeps the image within 2e-4 of float64 (measured 1.3e-5)."""
    args = _random(150, 11, lo=(-15, -12, 20), hi=(15, 12, 60), smin=0.02, smax=0.05)
    K = _K(60.0, 16.0, 14.0)
    c64, a64, _ = raytrace(*args, ID, K, 32, 28, render_mode="RGB")
    c32, a32, _ = raytrace(*[t.float() for t in args], ID.float(), K.float(), 32, 28, render_mode="RGB")
    assert c32.dtype == torch.float32 and float(a64.max()) > 0.2
    torch.testing.assert_close(c32.double(), c64, rtol=0, atol=2e-4)
    torch.testing.assert_close(a32.double(), a64, rtol=0, atol=2e-4)
