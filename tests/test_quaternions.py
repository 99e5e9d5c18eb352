import math

import pytest
import torch

from diff4splat.scene.quaternions import (
    axis_angle_to_quat,
    quat_conjugate,
    quat_multiply,
    quat_nlerp,
    quat_normalize,
    quat_to_rotmat,
    rotmat_to_quat,
)


def _rot_z(a):
    c, s = math.cos(a), math.sin(a)
    return torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)


def test_basis_products_follow_hamilton_rules():
    one, i, j, k = torch.eye(4, dtype=torch.float64)
    assert torch.equal(quat_multiply(i, j), k)
    assert torch.equal(quat_multiply(j, k), i)
    assert torch.equal(quat_multiply(k, i), j)
    assert torch.equal(quat_multiply(j, i), -k)
    for q in (i, j, k):
        assert torch.equal(quat_multiply(q, q), -one)


def test_rotmat_closed_form_rotation_about_z():
    a = 0.7
    q = axis_angle_to_quat(torch.tensor([0.0, 0.0, 2.0], dtype=torch.float64), torch.tensor(a, dtype=torch.float64))
    torch.testing.assert_close(q, torch.tensor([math.cos(a / 2), 0, 0, math.sin(a / 2)], dtype=torch.float64))
    torch.testing.assert_close(quat_to_rotmat(3.0 * q), _rot_z(a))  # unnormalised input


def test_product_composes_rotations_and_conjugate_inverts():
    g = torch.Generator().manual_seed(0)
    a, b = torch.randn(2, 64, 4, generator=g, dtype=torch.float64)
    torch.testing.assert_close(quat_to_rotmat(quat_multiply(a, b)), quat_to_rotmat(a) @ quat_to_rotmat(b))
    qa = quat_normalize(a)
    ident = torch.zeros_like(qa)
    ident[:, 0] = 1
    torch.testing.assert_close(quat_multiply(qa, quat_conjugate(qa)), ident)


def test_rotmat_to_quat_round_trip_including_180_degrees():
    g = torch.Generator().manual_seed(1)
    q = quat_normalize(torch.randn(200, 4, generator=g, dtype=torch.float64))
    q = torch.cat([q, torch.tensor([[0.0, 1, 0, 0], [0.0, 0, 1, 0], [0.0, 0, 0, 1]], dtype=torch.float64)])
    q = torch.where(q[:, :1] < 0, -q, q)
    back = rotmat_to_quat(quat_to_rotmat(q))
    # q and −q are the same rotation when w = 0
    err = torch.minimum((back - q).abs().amax(-1), (back + q).abs().amax(-1))
    assert err.max() < 1e-12


def test_zero_norm_raises():
    with pytest.raises(ValueError, match="zero-norm"):
        quat_normalize(torch.tensor([[1.0, 0, 0, 0], [0.0, 0, 0, 0]]))
    with pytest.raises(ValueError, match="last dimension 4"):
        quat_normalize(torch.zeros(3, 3))


def test_nlerp_endpoints_and_shorter_arc():
    q0 = torch.tensor([1.0, 0, 0, 0], dtype=torch.float64)
    q1 = axis_angle_to_quat(torch.tensor([1.0, 0, 0], dtype=torch.float64), torch.tensor(1.0, dtype=torch.float64))
    torch.testing.assert_close(quat_nlerp(q0, q1, 0.0), q0)
    torch.testing.assert_close(quat_nlerp(q0, q1, 1.0), q1)
    # −q1 is the same rotation: interpolation must take the same (short) path
    torch.testing.assert_close(quat_nlerp(q0, -q1, 0.5), quat_nlerp(q0, q1, 0.5))
    mid = quat_nlerp(q0, q1, 0.5)  # symmetric blend of two rotations about x → half angle
    torch.testing.assert_close(mid, axis_angle_to_quat(torch.tensor([1.0, 0, 0], dtype=torch.float64),
                                                       torch.tensor(0.5, dtype=torch.float64)))
    # the rotations are blended, not their representations: scaling an input changes nothing
    torch.testing.assert_close(quat_nlerp(3.0 * q0, 0.2 * q1, 0.3), quat_nlerp(q0, q1, 0.3))
    with pytest.raises(ValueError, match="q1"):
        quat_nlerp(q0, torch.zeros(4, dtype=torch.float64), 0.5)
