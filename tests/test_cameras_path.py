"""Tests for diff4splat.cameras.path.CameraPath: validation, relative poses, centres, resizing."""
import math

import pytest
import torch

from diff4splat.cameras import (
    CameraPath,
    camera_centers,
    camera_rays,
    center_crop_box,
    intrinsics_from_focal,
    invert_rigid,
)
from diff4splat.cameras.lenses import generate_rays
from diff4splat.render.sh import color_features
from diff4splat.scene.quaternions import axis_angle_to_quat, quat_to_rotmat


def random_viewmats(T, seed=0, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    axis = torch.randn(T, 3, generator=g, dtype=dtype)
    angle = torch.rand(T, generator=g, dtype=dtype) * math.pi
    R = quat_to_rotmat(axis_angle_to_quat(axis, angle))
    V = torch.eye(4, dtype=dtype).repeat(T, 1, 1)
    V[:, :3, :3] = R
    V[:, :3, 3] = torch.randn(T, 3, generator=g, dtype=dtype)
    return V


def make_path(T=4, dtype=torch.float64, **kw):
    K = intrinsics_from_focal(50.0, 60.0, 32, 24, dtype=dtype).expand(T, 3, 3).clone()
    return CameraPath(random_viewmats(T, dtype=dtype), K, 32, 24, **kw)


def test_default_times_and_len():
    p = make_path(5)
    assert len(p) == 5
    torch.testing.assert_close(p.times, torch.tensor([0.0, 0.25, 0.5, 0.75, 1.0], dtype=torch.float64))
    assert make_path(1).times.tolist() == [0.0]


def test_camera_centers_are_fixed_points_of_projection():
    # The centre c satisfies R c + t = 0 and equals the ray origins of camera_rays.
    p = make_path(3)
    c = p.camera_centers()
    V = p.viewmats
    cam = torch.einsum("tij,tj->ti", V[:, :3, :3], c) + V[:, :3, 3]
    torch.testing.assert_close(cam, torch.zeros_like(cam), atol=1e-12, rtol=0)
    origins, _ = camera_rays(V, p.Ks, 2, 2)
    torch.testing.assert_close(origins[:, 0, 0], c)
    torch.testing.assert_close(invert_rigid(V), torch.linalg.inv(V))


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_camera_centers_match_a_brute_force_inverse(dtype):
    """c = −Rᵀt is the translation of the inverse viewmat, for any batch shape and (3, 4) blocks."""
    V = random_viewmats(12, seed=3, dtype=dtype) * torch.tensor([1.0, 1, 1, 5.0], dtype=dtype)  # spread t
    V[:, 3] = torch.tensor([0.0, 0, 0, 1], dtype=dtype)
    want = torch.linalg.inv(V.double())[:, :3, 3].to(dtype)
    tol = {"atol": 1e-12, "rtol": 0} if dtype == torch.float64 else {"atol": 1e-5, "rtol": 1e-5}
    torch.testing.assert_close(camera_centers(V), want, **tol)
    torch.testing.assert_close(camera_centers(V.reshape(3, 4, 4, 4)), want.reshape(3, 4, 3), **tol)
    torch.testing.assert_close(camera_centers(V[:, :3]), want, **tol)
    torch.testing.assert_close(camera_centers(V[0]), want[0], **tol)
    assert camera_centers(V).dtype == dtype


@pytest.mark.parametrize("bad", [torch.eye(3), torch.zeros(4), "viewmats"])
def test_camera_centers_refuses_non_transforms(bad):
    with pytest.raises(ValueError, match="viewmats must be a tensor of shape"):
        camera_centers(bad)


def test_every_camera_centre_user_agrees():
    """CameraPath, camera_rays, the lens ray generator and the SH viewing direction use the same centre."""
    p = make_path(3)
    c = camera_centers(p.viewmats)
    torch.testing.assert_close(p.camera_centers(), c, atol=0, rtol=0)
    torch.testing.assert_close(camera_rays(p.viewmats, p.Ks, 2, 2)[0][:, 1, 1], c, atol=0, rtol=0)
    torch.testing.assert_close(generate_rays(p.viewmats, p.Ks, 2, 2, "fisheye", None)[0][:, 1, 1, 0], c, atol=0, rtol=0)
    # degree-1 SH with only the y-coefficient set: colour is linear in the unit direction mean − centre
    means = torch.tensor([[0.3, -0.2, 4.0]], dtype=torch.float64)
    sh = torch.zeros(1, 4, 3, dtype=torch.float64)
    sh[0, 1] = 1.0  # Y_1^{-1} ∝ −y
    feats = color_features(sh, means, p.viewmats, 1)  # (C, 1, 3)
    d = means[None, 0] - c
    d = d / d.norm(dim=-1, keepdim=True)
    torch.testing.assert_close(feats[:, 0, 0], (-0.4886025119029199 * d[:, 1] + 0.5).clamp(min=0))


def test_relative_to_first_preserves_relative_poses():
    p = make_path(4)
    r = p.relative_to_first()
    assert torch.equal(r.viewmats[0], torch.eye(4, dtype=torch.float64))
    for i in range(4):
        for j in range(4):
            a = p.viewmats[i] @ torch.linalg.inv(p.viewmats[j])
            b = r.viewmats[i] @ torch.linalg.inv(r.viewmats[j])
            torch.testing.assert_close(a, b)
    # A world point X maps to the same camera coordinates via V_i X and V_i' (V_0 X).
    X = torch.tensor([0.3, -0.2, 2.0, 1.0], dtype=torch.float64)
    torch.testing.assert_close(p.viewmats @ X, r.viewmats @ (p.viewmats[0] @ X))
    torch.testing.assert_close(r.Ks, p.Ks)
    torch.testing.assert_close(r.times, p.times)


def test_resized_keeps_projection_in_normalised_coordinates():
    p = make_path(2)
    q = p.resized(64, 12)
    assert (q.width, q.height) == (64, 12)
    Xc = torch.tensor([0.1, -0.3, 1.7], dtype=torch.float64)
    uv0 = (p.Ks[0] @ Xc)[:2] / Xc[2]
    uv1 = (q.Ks[0] @ Xc)[:2] / Xc[2]
    # Same point lands at the same fraction of the image width/height.
    torch.testing.assert_close(uv1 / torch.tensor([64.0, 12.0], dtype=torch.float64),
                               uv0 / torch.tensor([32.0, 24.0], dtype=torch.float64))
    with pytest.raises(ValueError, match="height"):
        p.resized(10, 0)


def _bad(field_mutator, match):
    p = make_path(3)
    vm, K, times = p.viewmats.clone(), p.Ks.clone(), p.times.clone()
    vm, K, times = field_mutator(vm, K, times)
    with pytest.raises(ValueError, match=match):
        CameraPath(vm, K, 32, 24, times)


def _set(t, idx, value):
    t[idx] = value
    return t


@pytest.mark.parametrize(
    "mutator, match",
    [
        (lambda vm, K, t: (vm[:0], K[:0], t[:0]), "zero frames"),
        (lambda vm, K, t: (_set(vm, (1, 0, 3), float("nan")), K, t), "viewmats"),
        (lambda vm, K, t: (vm, _set(K, (2, 0, 2), float("inf")), t), "Ks"),
        (lambda vm, K, t: (_set(vm, (1, slice(0, 3), 0), vm[1, :3, 0] * 1.01), K, t), r"viewmats\[1\] rotation"),
        (lambda vm, K, t: (_set(vm, (2, slice(0, 3), 0), -vm[2, :3, 0]), K, t), r"viewmats\[2\] rotation"),
        (lambda vm, K, t: (_set(vm, (0, 3, 1), 0.5), K, t), r"viewmats\[0\] bottom row"),
        (lambda vm, K, t: (vm, _set(K, (1, 1, 1), 0.0), t), r"Ks\[1\] focal"),
        (lambda vm, K, t: (vm, _set(K, (0, 0, 0), -3.0), t), r"Ks\[0\] focal"),
        (lambda vm, K, t: (vm, _set(K, (0, 2, 0), 1.0), t), r"Ks\[0\] must be"),
        (lambda vm, K, t: (vm, K, torch.tensor([0.0, 0.7, 0.6], dtype=torch.float64)), "non-decreasing"),
        (lambda vm, K, t: (vm, K, torch.tensor([0.0, 0.5, 1.5], dtype=torch.float64)), r"times must lie in \[0, 1\]"),
        (lambda vm, K, t: (vm, K, torch.tensor([-0.1, 0.5, 1.0], dtype=torch.float64)), r"times must lie in \[0, 1\]"),
        (lambda vm, K, t: (vm, K, t[:2]), r"times must be a tensor of shape \(3,\)"),
        (lambda vm, K, t: (vm, K[:2], t), r"Ks must be a tensor of shape \(3, 3, 3\)"),
    ],
)
def test_validation_names_the_field(mutator, match):
    _bad(mutator, match)


def test_validate_size_fields_and_reflection():
    p = make_path(2)
    with pytest.raises(ValueError, match="width"):
        CameraPath(p.viewmats, p.Ks, 0, 24)
    with pytest.raises(ValueError, match="height"):
        CameraPath(p.viewmats, p.Ks, 32, True)
    # An orthonormal reflection (det = −1) passes RᵀR = I but is not a rotation.
    vm = p.viewmats.clone()
    vm[0, :3, :3] = torch.diag(torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64))
    with pytest.raises(ValueError, match="det"):
        CameraPath(vm, p.Ks, 32, 24)


def test_float32_path_and_to():
    p = make_path(3, dtype=torch.float32)
    assert p.times.dtype == torch.float32
    q = p.to(torch.float64)
    assert q.viewmats.dtype == q.Ks.dtype == q.times.dtype == torch.float64


def test_fitted_crop_keeps_a_point_on_the_same_image_content():
    """A point at pixel (u, v) of a 450×300 frame lands where the centre-cropped, resized photo shows it."""
    K = torch.tensor([[[400.0, 0, 225.0], [0, 400.0, 150.0], [0, 0, 1]]], dtype=torch.float64)
    fit = CameraPath(torch.eye(4, dtype=torch.float64)[None], K, 450, 300).fitted(64, 64)
    X = torch.tensor([0.3, -0.2, 2.0], dtype=torch.float64)
    y0, x0, ch, cw = center_crop_box(300, 450, 64, 64)
    assert (y0, x0, ch, cw) == (0, 75, 300, 300)
    uv0 = (K[0] @ X)[:2] / X[2]
    expected = (uv0 - torch.tensor([x0, y0], dtype=torch.float64)) * torch.tensor([64 / cw, 64 / ch],
                                                                                  dtype=torch.float64)
    torch.testing.assert_close((fit.Ks[0] @ X)[:2] / X[2], expected)
    assert (fit.width, fit.height) == (64, 64)


def test_viewmat_at_interpolates_centre_and_rotation():
    """Between cameras at t = 0, 0.5, 1 rotated about y by 0, 0.4, 1.0 rad: at a key time the viewmat itself;
    half-way the rotation angle and centre are the means (nlerp of same-axis rotations at w = ½ is exact);
    outside the clip the end poses are held."""
    D = torch.float64
    angles, centres = [0.0, 0.4, 1.0], torch.tensor([[0.0, 0, 0], [1.0, 0.2, 0], [1.0, 1.2, -0.4]], dtype=D)
    vms = torch.eye(4, dtype=D).repeat(3, 1, 1)
    for i, a in enumerate(angles):
        R = quat_to_rotmat(axis_angle_to_quat(torch.tensor([0.0, 1.0, 0.0], dtype=D), torch.tensor(a, dtype=D)))
        vms[i, :3, :3] = R.T  # camera-to-world rotation R
        vms[i, :3, 3] = -R.T @ centres[i]
    K = torch.tensor([[10.0, 0, 5], [0, 10.0, 5], [0, 0, 1]], dtype=D).expand(3, 3, 3).clone()
    path = CameraPath(vms, K, 10, 10)
    for i in range(3):
        assert torch.equal(path.viewmat_at(float(path.times[i])), vms[i])
    before = path.viewmats.clone()
    path.viewmat_at(0.0)[0, 3] = 42.0  # a copy: the path is unchanged (it returned a view of it)
    assert torch.equal(path.viewmats, before)
    assert torch.equal(path.viewmat_at(-0.5), vms[0]) and torch.equal(path.viewmat_at(2.0), vms[2])
    mid = path.viewmat_at(0.75)
    c2w = invert_rigid(mid)
    expect_R = quat_to_rotmat(axis_angle_to_quat(torch.tensor([0.0, 1.0, 0.0], dtype=D), torch.tensor(0.7, dtype=D)))
    torch.testing.assert_close(c2w[:3, :3], expect_R, rtol=0, atol=1e-12)
    torch.testing.assert_close(c2w[:3, 3], 0.5 * (centres[1] + centres[2]), rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="finite"):
        path.viewmat_at(float("nan"))
