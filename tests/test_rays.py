"""Tests for diff4splat.cameras.rays against per-pixel Python loops and projection."""
import math

import numpy as np
import pytest
import torch

from diff4splat.cameras import camera_rays, pack_plucker, plucker_rays, unproject_depth
from diff4splat.scene.quaternions import axis_angle_to_quat, quat_to_rotmat


def make_cameras(C=2, seed=0):
    g = torch.Generator().manual_seed(seed)
    R = quat_to_rotmat(axis_angle_to_quat(torch.randn(C, 3, generator=g, dtype=torch.float64),
                                          torch.rand(C, generator=g, dtype=torch.float64) * math.pi))
    V = torch.eye(4, dtype=torch.float64).repeat(C, 1, 1)
    V[:, :3, :3] = R
    V[:, :3, 3] = torch.randn(C, 3, generator=g, dtype=torch.float64)
    K = torch.tensor([[40.0, 0, 9.0], [0, 35.0, 6.5], [0, 0, 1]], dtype=torch.float64).repeat(C, 1, 1)
    K[1, 0, 0] = 55.0
    return V, K


def test_plucker_matches_per_pixel_loop():
    V, K = make_cameras()
    W, H = 17, 11
    rays = plucker_rays(V, K, W, H)
    assert rays.shape == (2, H, W, 6)
    for c in range(2):
        Vn, Kn = V[c].numpy(), K[c].numpy()
        R, t = Vn[:3, :3], Vn[:3, 3]
        centre = -R.T @ t
        for i, j in [(0, 0), (H - 1, W - 1), (5, 3), (2, 16), (10, 8)]:
            u, v = j + 0.5, i + 0.5
            x = (u - Kn[0, 2]) / Kn[0, 0]
            y = (v - Kn[1, 2]) / Kn[1, 1]
            d = R.T @ np.array([x, y, 1.0])
            d = d / np.linalg.norm(d)
            expect = np.concatenate([np.cross(centre, d), d])
            np.testing.assert_allclose(rays[c, i, j].numpy(), expect, atol=1e-12)


def test_ray_points_project_back_to_their_pixel():
    V, K = make_cameras(seed=3)
    W, H = 9, 7
    o, d = camera_rays(V, K, W, H)
    for s in (0.5, 4.0):
        X = o + s * d  # (C, H, W, 3) points along each ray, in front of the camera
        cam = torch.einsum("cij,chwj->chwi", V[:, :3, :3], X) + V[:, None, None, :3, 3]
        assert bool((cam[..., 2] > 0).all())
        uv = torch.einsum("cij,chwj->chwi", K, cam)
        uv = uv[..., :2] / uv[..., 2:]
        jj, ii = torch.meshgrid(torch.arange(W, dtype=torch.float64), torch.arange(H, dtype=torch.float64),
                                indexing="xy")
        expect = torch.stack([jj + 0.5, ii + 0.5], -1).expand_as(uv)
        torch.testing.assert_close(uv, expect)
    # The Plücker moment is the same for every point on the ray: (o + s·d) × d = o × d.
    m = plucker_rays(V, K, W, H)[..., :3]
    torch.testing.assert_close(torch.linalg.cross(o + 2.5 * d, d, dim=-1), m)
    torch.testing.assert_close(d.norm(dim=-1), torch.ones(2, H, W, dtype=torch.float64))


def test_unproject_depth_projects_back_with_its_z_depth():
    V, K = make_cameras(seed=5)
    W, H = 9, 7
    depth = torch.rand(2, H, W, dtype=torch.float64, generator=torch.Generator().manual_seed(1)) * 5 + 0.1
    X = unproject_depth(V, K, depth)
    cam = torch.einsum("cij,chwj->chwi", V[:, :3, :3], X) + V[:, None, None, :3, 3]
    torch.testing.assert_close(cam[..., 2], depth)  # z-depth, not distance along the ray
    uv = torch.einsum("cij,chwj->chwi", K, cam)
    jj, ii = torch.meshgrid(torch.arange(W, dtype=torch.float64), torch.arange(H, dtype=torch.float64), indexing="xy")
    torch.testing.assert_close(uv[..., :2] / uv[..., 2:], torch.stack([jj + 0.5, ii + 0.5], -1).expand(2, H, W, 2))
    with pytest.raises(ValueError, match="depth"):
        unproject_depth(V, K, depth[0])


def test_identity_camera_centre_ray_is_optical_axis():
    K = torch.tensor([[[10.0, 0, 2.0], [0, 10.0, 2.0], [0, 0, 1]]])
    V = torch.eye(4)[None].clone()
    V[0, :3, 3] = torch.tensor([0.0, 0.0, -1.0])  # centre at (0, 0, 1)
    r = plucker_rays(V, K, 4, 4)
    # Pixel centre (2.5, 2.5) is 0.5 px off the principal point (2, 2); use K⁻¹ directly.
    d = torch.tensor([0.05, 0.05, 1.0])
    d = d / d.norm()
    torch.testing.assert_close(r[0, 2, 2, 3:], d)
    torch.testing.assert_close(r[0, 2, 2, :3], torch.linalg.cross(torch.tensor([0.0, 0.0, 1.0]), d, dim=0))


@pytest.mark.parametrize("temporal, spatial, T, Hp, Wp", [(4, 8, 9, 16, 24), (2, 2, 5, 4, 6), (1, 1, 3, 2, 2)])
@pytest.mark.slow
def test_pack_plucker_matches_explicit_loop(temporal, spatial, T, Hp, Wp):
    B = 2
    rays = torch.randn(B, T, Hp, Wp, 6, generator=torch.Generator().manual_seed(1))
    out = pack_plucker(rays, temporal=temporal, spatial=spatial)
    n, h, w = 1 + (T - 1) // temporal, Hp // spatial, Wp // spatial
    assert out.shape == (B, 6 * temporal * spatial * spatial, n, h, w)
    expect = torch.empty_like(out)
    for b in range(B):
        for ln in range(n):
            for f in range(temporal):
                frame = 0 if ln == 0 else 1 + (ln - 1) * temporal + f  # latent 0 repeats frame 0
                for sy in range(spatial):
                    for sx in range(spatial):
                        for comp in range(6):
                            ch = ((f * spatial + sy) * spatial + sx) * 6 + comp
                            for y in range(h):
                                for x in range(w):
                                    expect[b, ch, ln, y, x] = rays[b, frame, y * spatial + sy, x * spatial + sx, comp]
    assert torch.equal(out, expect)


def test_pack_plucker_and_rays_reject_bad_shapes():
    with pytest.raises(ValueError, match="1 \\+ 4"):
        pack_plucker(torch.zeros(1, 4, 8, 8, 6))
    with pytest.raises(ValueError, match="multiples of 8"):
        pack_plucker(torch.zeros(1, 5, 12, 8, 6))
    with pytest.raises(ValueError, match="rays"):
        pack_plucker(torch.zeros(1, 5, 8, 8, 3))
    with pytest.raises(ValueError, match="viewmats"):
        camera_rays(torch.eye(4), torch.eye(3)[None], 4, 4)
    with pytest.raises(ValueError, match="Ks"):
        camera_rays(torch.eye(4)[None], torch.eye(3), 4, 4)
