"""Tests for diff4splat.cameras.intrinsics: closed forms of pinhole intrinsics and validation."""
import math

import pytest
import torch

from diff4splat.cameras import fov_from_intrinsics, intrinsics_from_focal, intrinsics_from_fov


def test_fov_90_gives_half_width_focal():
    # tan(45°) = 1 → fx = W/2 exactly; square pixels → fy = fx.
    K = intrinsics_from_fov(64, 48, fov_x_deg=90.0)
    assert K.shape == (3, 3) and K.dtype == torch.float32
    torch.testing.assert_close(K, torch.tensor([[32.0, 0, 32.0], [0, 32.0, 24.0], [0, 0, 1.0]]))


def test_fov_y_sets_vertical_focal_and_square_pixels():
    K = intrinsics_from_fov(100, 50, fov_y_deg=60.0, dtype=torch.float64)
    f = 25.0 / math.tan(math.radians(30.0))
    assert K[1, 1].item() == pytest.approx(f) and K[0, 0].item() == pytest.approx(f)
    assert (K[0, 2].item(), K[1, 2].item()) == (50.0, 25.0)


def test_both_fovs_give_independent_focals_and_roundtrip():
    K = intrinsics_from_fov(80, 60, fov_x_deg=70.0, fov_y_deg=50.0, dtype=torch.float64)
    fx, fy = fov_from_intrinsics(K, 80, 60)
    assert fx == pytest.approx(70.0) and fy == pytest.approx(50.0)


def test_edge_pixel_ray_angle_matches_fov():
    # The image edge u = W projects at angle fov/2 from the optical axis.
    W, H = 64, 64
    K = intrinsics_from_fov(W, H, fov_x_deg=75.0, dtype=torch.float64)
    x = torch.linalg.solve(K, torch.tensor([float(W), H / 2, 1.0], dtype=torch.float64))
    assert math.degrees(math.atan2(x[0].item(), x[2].item())) == pytest.approx(37.5)


def test_from_focal_default_and_explicit_principal_point():
    K = intrinsics_from_focal(100.0, 120.0, 33, 21)
    torch.testing.assert_close(K, torch.tensor([[100.0, 0, 16.5], [0, 120.0, 10.5], [0, 0, 1.0]]))
    K2 = intrinsics_from_focal(100.0, 120.0, 33, 21, cx=3.0, cy=4.0)
    assert (K2[0, 2].item(), K2[1, 2].item()) == (3.0, 4.0)


@pytest.mark.parametrize(
    "kwargs, field",
    [
        (dict(fov_x_deg=0.0), "fov_x_deg"),
        (dict(fov_x_deg=180.0), "fov_x_deg"),
        (dict(fov_y_deg=-5.0), "fov_y_deg"),
        (dict(fov_y_deg=float("nan")), "fov_y_deg"),
        (dict(), "fov_x_deg or fov_y_deg"),
    ],
)
def test_fov_validation(kwargs, field):
    with pytest.raises(ValueError, match=field):
        intrinsics_from_fov(64, 64, **kwargs)


@pytest.mark.parametrize(
    "args, field",
    [
        ((0.0, 10.0, 64, 64), "fx"),
        ((10.0, -1.0, 64, 64), "fy"),
        ((10.0, 10.0, 0, 64), "width"),
        ((10.0, 10.0, 64, 2.5), "height"),
    ],
)
def test_focal_validation(args, field):
    with pytest.raises(ValueError, match=field):
        intrinsics_from_focal(*args)
    if field in ("width", "height"):
        with pytest.raises(ValueError, match=field):
            intrinsics_from_fov(args[2], args[3], fov_x_deg=60.0)
