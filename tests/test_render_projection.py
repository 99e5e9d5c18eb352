"""Tests of diff4splat.render.projection against closed forms (EWA projection, culling, support)."""
import math

import pytest
import torch

from diff4splat.render import project_gaussians
from diff4splat.render.projection import covariance_3d, splat_alpha, support_extent
from diff4splat.scene.quaternions import axis_angle_to_quat, quat_to_rotmat
from diff4splat.utils.constants import ALPHA_MIN

D = torch.float64
W, H = 64, 48
K = torch.tensor([[50.0, 0, 30.0], [0, 55.0, 26.0], [0, 0, 1]], dtype=D)


def _camera(angle=0.2, t=(0.1, -0.2, 0.3)):
    vm = torch.eye(4, dtype=D)
    axis = torch.tensor([0.3, 1.0, 0.2], dtype=D)
    vm[:3, :3] = quat_to_rotmat(axis_angle_to_quat(axis, torch.tensor(angle, dtype=D)))
    vm[:3, 3] = torch.tensor(t, dtype=D)
    return vm


def _project(means, quats, scales, opac, vm, **kw):
    return project_gaussians(means, quats, scales, opac, vm[None], K[None], W, H, **kw)


def test_centre_lands_at_K_x_over_z():
    g = torch.Generator().manual_seed(0)
    vm = _camera()
    pc = torch.stack([torch.rand(20, generator=g, dtype=D) - 0.5, torch.rand(20, generator=g, dtype=D) - 0.5,
                      1 + 3 * torch.rand(20, generator=g, dtype=D)], -1)
    means = (pc - vm[:3, 3]) @ vm[:3, :3]  # world points whose camera coordinates are pc
    n = len(means)
    p = _project(means, torch.randn(n, 4, dtype=D), torch.full((n, 3), 0.01, dtype=D), torch.full((n,), 0.5, dtype=D),
                 vm)
    uvw = pc @ K.T
    torch.testing.assert_close(p.means2d[0], uvw[:, :2] / uvw[:, 2:], rtol=1e-12, atol=1e-9)
    torch.testing.assert_close(p.depths[0], pc[:, 2])
    assert bool((p.radii[0] > 0).all())


@pytest.mark.parametrize("z,s", [(2.0, 0.05), (5.0, 0.2), (1.0, 0.01)])
def test_isotropic_gaussian_on_axis_has_screen_sigma_f_s_over_z(z, s):
    k = K.clone()
    k[0, 0] = k[1, 1] = 50.0
    eps = 0.3
    means = torch.tensor([[0.0, 0.0, z]], dtype=D)
    p = project_gaussians(means, torch.randn(1, 4, dtype=D), torch.full((1, 3), s, dtype=D),
                          torch.tensor([0.7], dtype=D),
                          torch.eye(4, dtype=D)[None], k[None], W, H, eps2d=eps, antialiased=True)
    var = (50.0 * s / z) ** 2
    torch.testing.assert_close(p.covars2d[0, 0], torch.tensor([var + eps, 0.0, var + eps], dtype=D))
    torch.testing.assert_close(p.conics[0, 0], torch.tensor([1 / (var + eps), 0.0, 1 / (var + eps)], dtype=D))
    assert int(p.radii[0, 0]) == math.ceil(3 * math.sqrt(var + eps))
    # antialiased compensation sqrt(det Σ / det(Σ + eps I)) = var / (var + eps) for an isotropic Σ
    torch.testing.assert_close(p.compensations[0, 0], torch.tensor(var / (var + eps), dtype=D))
    torch.testing.assert_close(p.opacities[0, 0], torch.tensor(0.7 * var / (var + eps), dtype=D))


def test_covariance_is_jacobian_sandwich_with_fov_clamp():
    """Σ2d = J Σc Jᵀ with J the autograd Jacobian of the pinhole map, x/z clamped as gsplat."""
    vm = torch.eye(4, dtype=D)
    q = torch.tensor([[0.9, 0.2, -0.3, 0.1]], dtype=D)
    s = torch.tensor([[0.1, 0.03, 0.2]], dtype=D)
    cov = covariance_3d(q, s)[0]
    lim_x = (W - K[0, 2]) / K[0, 0] + 0.3 * W / (2 * K[0, 0])  # gsplat's positive x/z limit
    for x_over_z in (0.2, -0.4, 3.0):  # 3.0 is far outside the frustum: clamped
        z = 2.0
        mean = torch.tensor([x_over_z * z, 0.1 * z, z], dtype=D)
        p = project_gaussians(mean[None], q, s, torch.tensor([0.5], dtype=D), vm[None], K[None], W, H, eps2d=0.0)
        xc = torch.tensor([min(x_over_z, float(lim_x)) * z, 0.1 * z, z], dtype=D)
        J = torch.autograd.functional.jacobian(lambda v: (K[:2, :2] @ (v[:2] / v[2])), xc)
        want = J @ cov @ J.T
        got = p.covars2d[0, 0]
        if x_over_z == 3.0:
            assert int(p.radii[0, 0]) == 0  # and it is culled: fully outside the image
            continue
        torch.testing.assert_close(got, torch.stack([want[0, 0], want[0, 1], want[1, 1]]), rtol=1e-12, atol=1e-12)


def test_clamp_limits_jacobian_for_wide_gaussian_outside_view():
    """A huge Gaussian centred outside the view still reaches the image; its Jacobian uses the clamp."""
    vm = torch.eye(4, dtype=D)
    z, xz = 2.0, 1.5
    lim = float((W - K[0, 2]) / K[0, 0] + 0.3 * W / (2 * K[0, 0]))
    assert xz > lim
    mean = torch.tensor([[xz * z, 0.0, z]], dtype=D)
    scales = torch.full((1, 3), 1.0, dtype=D)
    p = project_gaussians(mean, torch.tensor([[1.0, 0, 0, 0]], dtype=D), scales, torch.tensor([0.5], dtype=D),
                          vm[None], K[None], W, H, eps2d=0.0)
    fx, fy = float(K[0, 0]), float(K[1, 1])
    J = torch.tensor([[fx / z, 0, -fx * lim * z / z**2], [0, fy / z, 0]], dtype=D)
    want = J @ J.T
    assert int(p.radii[0, 0]) > 0
    torch.testing.assert_close(p.covars2d[0, 0], torch.stack([want[0, 0], want[0, 1], want[1, 1]]))


def test_culling_near_far_and_outside():
    vm = torch.eye(4, dtype=D)
    means = torch.tensor([
        [0.0, 0.0, 2.0],     # visible
        [0.0, 0.0, -2.0],    # behind the camera
        [0.0, 0.0, 0.005],   # in front of the near plane
        [0.0, 0.0, 50.0],    # beyond far_plane=20
        [30.0, 0.0, 2.0],    # far outside the image
    ], dtype=D)
    n = len(means)
    p = _project(means, torch.randn(n, 4, dtype=D), torch.full((n, 3), 0.05, dtype=D), torch.full((n,), 0.5, dtype=D),
                 vm, far_plane=20.0)
    assert p.radii[0].tolist() == [p.radii[0, 0].item(), 0, 0, 0, 0] and p.radii[0, 0] > 0
    for t in (p.means2d, p.conics, p.covars2d, p.opacities, p.depths):
        assert bool(torch.isfinite(t).all()) and bool((t[0, 1:] == 0).all())


def test_zero_norm_quaternion_raises():
    q = torch.tensor([[1.0, 0, 0, 0], [0.0, 0, 0, 0]], dtype=D)
    with pytest.raises(ValueError, match="quats"):
        _project(torch.tensor([[0, 0, 2.0], [0, 0, 3.0]], dtype=D), q, torch.full((2, 3), 0.1, dtype=D),
                 torch.full((2,), 0.5, dtype=D), torch.eye(4, dtype=D))


def test_unknown_camera_model_raises():
    with pytest.raises(ValueError, match="camera_model"):
        _project(torch.zeros(1, 3, dtype=D), torch.ones(1, 4, dtype=D), torch.ones(1, 3, dtype=D),
                 torch.ones(1, dtype=D), torch.eye(4, dtype=D), camera_model="fisheye")


@pytest.mark.slow
def test_support_box_contains_every_visible_pixel_and_is_tight():
    g = torch.Generator().manual_seed(1)
    n = 40
    a = 0.05 + 2 * torch.rand(n, generator=g, dtype=D)
    c = 0.05 + 2 * torch.rand(n, generator=g, dtype=D)
    b = (torch.rand(n, generator=g, dtype=D) - 0.5) * 1.8 * torch.sqrt(a * c)
    cov = torch.stack([a, b, c], -1)
    det = a * c - b * b
    conics = torch.stack([c / det, -b / det, a / det], -1)
    opac = torch.rand(n, generator=g, dtype=D)
    ext = support_extent(cov, opac)
    dx, dy = torch.meshgrid(torch.linspace(-12, 12, 241, dtype=D), torch.linspace(-12, 12, 241, dtype=D), indexing="ij")
    alpha = splat_alpha(dx[..., None], dy[..., None], conics, opac)  # (241, 241, n)
    vis = alpha >= ALPHA_MIN
    for i in range(n):
        if opac[i] < ALPHA_MIN:
            assert ext[i, 0] < 0 and not vis[..., i].any()
            continue
        if opac[i] < 0.05:  # support smaller than the 0.1 px test grid
            continue
        assert float(dx[..., None].expand_as(alpha)[..., i][vis[..., i]].abs().max()) <= float(ext[i, 0])
        assert float(dy[..., None].expand_as(alpha)[..., i][vis[..., i]].abs().max()) <= float(ext[i, 1])
        # tight: the box is at most one grid step (0.1 px) + the 0.1 % margin larger than the support
        assert float(dx[..., None].expand_as(alpha)[..., i][vis[..., i]].abs().max()) >= float(ext[i, 0]) * 0.998 - 0.1
