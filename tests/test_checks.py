"""diff4splat.checks: the one home of the argument checks (positive int, positive number, finite tensor)."""
import math
import re

import numpy as np
import pytest
import torch

from diff4splat.checks import check_finite, check_positive, check_positive_int


@pytest.mark.parametrize("value", [True, False, 0, -1, 1.5, 2.0, "3", None, np.float64(3.0)])
def test_check_positive_int_refuses(value):
    with pytest.raises(ValueError, match=rf"^width must be a positive int \(pixels\), got {re.escape(repr(value))}$"):
        check_positive_int("width", value, "pixels")


@pytest.mark.parametrize("value", [1, 7, np.int64(4), np.int32(1)])
def test_check_positive_int_accepts_integers_and_returns_python_int(value):
    out = check_positive_int("n", value)
    assert out == int(value) and type(out) is int


def test_check_positive_int_message_without_unit():
    with pytest.raises(ValueError, match=r"^num_frames must be a positive int, got 0$"):
        check_positive_int("num_frames", 0)


@pytest.mark.parametrize("value", [0, -0.5, math.nan, math.inf, -math.inf, "3", True, None, "abc"])
def test_check_positive_refuses(value):
    with pytest.raises(ValueError, match=r"^fps must be a positive finite number, got "):
        check_positive("fps", value)


@pytest.mark.parametrize("value", [3, 0.25, np.float32(2.5), torch.tensor(1.5)])
def test_check_positive_accepts_numbers(value):
    out = check_positive("fx", value)
    assert out == pytest.approx(float(value)) and type(out) is float


def test_check_finite_counts_bad_values_and_ignores_integer_and_empty_tensors():
    t = torch.tensor([1.0, math.nan, math.inf, -math.inf, 2.0])
    with pytest.raises(ValueError, match=r"^means contains 3 non-finite value\(s\) \(NaN or inf\)$"):
        check_finite("means", t)
    check_finite("ok", torch.tensor([1.0, 2.0]))
    check_finite("ints", torch.tensor([1, 2]))
    check_finite("empty", torch.empty(0, 3))


def test_check_finite_accepts_finite_values_whose_sum_overflows():
    """The fast path is a sum; finite values summing to inf take the exact test and pass."""
    check_finite("big", torch.tensor([1e308, 1e308, -1e308 / 3], dtype=torch.float64))
    check_finite("big32", torch.full((1000,), 3e38))
    with pytest.raises(ValueError, match="big contains 1 non-finite"):
        check_finite("big", torch.tensor([1e308, 1e308, math.nan], dtype=torch.float64))


def test_check_finite_has_one_home():
    """gaussians.py used to define its own copy; now every module uses the function of diff4splat.checks."""
    import diff4splat.cameras.path as path
    import diff4splat.gaussians as gaussians
    import diff4splat.render.validate as validate
    import diff4splat.scene as scene

    for module in (gaussians, scene, path, validate):
        assert module.check_finite is check_finite, module.__name__
