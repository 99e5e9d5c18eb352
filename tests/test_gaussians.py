import math

import pytest
import torch

from diff4splat.scene.gaussians import SH_C0, Gaussians, rgb_to_sh0, sh0_to_rgb


def _args(n=4):
    return dict(means=torch.zeros(n, 3), quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
                scales=torch.ones(n, 3), opacities=torch.full((n,), 0.5), sh=torch.zeros(n, 1, 3))


def test_sh0_colour_round_trip_and_constant():
    assert SH_C0 == pytest.approx(1 / (2 * math.sqrt(math.pi)))
    rgb = torch.rand(10, 3)
    torch.testing.assert_close(sh0_to_rgb(rgb_to_sh0(rgb)), rgb)


def test_sh_degree_from_coefficient_count():
    a = _args()
    a["sh"] = torch.zeros(4, 16, 3)
    assert Gaussians(**a).sh_degree == 3


def test_gaussians_move_to_the_meta_device():
    """Shapes only (a model's size, a sharding plan): the value checks, which read values, are skipped there."""
    g = Gaussians(**_args()).to("meta")
    assert g.means.is_meta and g.num_gaussians == 4


@pytest.mark.parametrize("field,value,match", [
    ("means", torch.zeros(4, 2), "means"),
    ("scales", torch.zeros(4, 3), "scales"),
    ("opacities", torch.full((4,), 1.5), "opacities"),
    ("sh", torch.zeros(4, 5, 3), "sh"),
    ("sh", torch.zeros(4, 0, 3), "sh must hold"),  # accepted before, with sh_degree −1
    ("quats", torch.zeros(4, 4), "zero-norm"),
    ("means", torch.full((4, 3), math.nan), "means"),
])
def test_invalid_fields_raise_naming_the_field(field, value, match):
    a = _args()
    a[field] = value
    with pytest.raises(ValueError, match=match):
        Gaussians(**a)


def test_a_cast_that_underflows_a_scale_is_refused_and_a_move_keeps_the_values():
    """``to`` validates again when a dtype changes (1e-50 m is 0 in float32, which no Gaussian may have), not when only
    the device does; ``detach`` keeps the values."""
    a = {k: v.double() for k, v in _args().items()}
    a["scales"][0, 0] = 1e-50
    g = Gaussians(**a)
    with pytest.raises(ValueError, match="scales must be > 0"):
        g.to(torch.float32)
    same = g.to("cpu").detach()
    assert all(torch.equal(getattr(same, k), v) for k, v in a.items())
