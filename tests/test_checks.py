"""diff4splat.utils.checks: the one home of the argument checks (int, positive int, number in a range, positive number,
finite tensor)."""
import math
import re

import numpy as np
import pytest
import torch

import data_prep.format as data_format
import data_prep.scene_files as scene_files
import data_prep.synth_dataset as synth
import diff4splat.cameras.lenses as lenses
import diff4splat.cameras.path as path
import diff4splat.render.settings as render_settings
import diff4splat.scene.dynamic as scene
import diff4splat.scene.gaussians as gaussians
import models.hexplane as hexplane
from diff4splat.utils.checks import (
    check_finite,
    check_int,
    check_number,
    check_positive,
    check_positive_int,
    is_int,
    is_number,
)


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
    check_finite("half", torch.full((1000,), 6e4, dtype=torch.float16))  # 6e7 overflows float16, not float32
    for dtype in (torch.float16, torch.bfloat16, torch.float32):
        with pytest.raises(ValueError, match="low contains 2 non-finite"):
            check_finite("low", torch.tensor([1.0, math.inf, -math.inf, 2.0], dtype=dtype))


def test_check_finite_has_one_home():
    """gaussians.py used to define its own copy; now every module uses the function of diff4splat.utils.checks."""
    for module in (gaussians, scene, path, render_settings):
        assert module.check_finite is check_finite, module.__name__


def test_is_int_and_is_number_refuse_bool():
    assert is_int(0) and is_int(np.int64(-3)) and not is_int(True) and not is_int(2.0) and not is_int("1")
    assert is_number(0) and is_number(np.float32(2.5)) and is_number(-1e300)
    assert not any(is_number(v) for v in (True, math.nan, math.inf, "1", None, torch.tensor(1.0)))


@pytest.mark.parametrize("value", [7, 3.0, True, "9", None, np.float64(8.0)])
def test_check_int_refuses(value):
    with pytest.raises(ValueError, match=rf"^size must be an integer ≥ 8 \(pixels\), got {re.escape(repr(value))}$"):
        check_int("size", value, 8, "pixels")


@pytest.mark.parametrize("value", [0, 5, np.int64(2)])
def test_check_int_returns_python_int(value):
    out = check_int("seed", value, 0)
    assert out == int(value) and type(out) is int


@pytest.mark.parametrize("kwargs, value, message", [
    ({}, math.nan, "x must be a finite number, got nan"),
    ({}, True, "x must be a finite number, got True"),
    ({"what": "metres"}, "1", "x must be a finite number (metres), got '1'"),
    ({"lo": 0}, -0.5, "x must be a finite number ≥ 0, got -0.5"),
    ({"lo": 0, "lo_open": True}, 0, "x must be a finite number > 0, got 0"),
    ({"hi": 1}, 1.5, "x must be a finite number ≤ 1, got 1.5"),
    ({"lo": 0, "hi": 1}, 2, "x must be a number in [0, 1], got 2"),
    ({"lo": 0, "hi": 1}, math.inf, "x must be a number in [0, 1], got inf"),
    ({"lo": 0, "hi": 1, "lo_open": True, "what": "clip time"}, 0.0,
     "x must be a number in (0, 1] (clip time), got 0.0"),
])
def test_check_number_states_the_range(kwargs, value, message):
    with pytest.raises(ValueError, match=f"^{re.escape(message)}$"):
        check_number("x", value, **kwargs)


@pytest.mark.parametrize("value", [0, 1, 0.5, np.float32(0.25), np.int64(1)])
def test_check_number_returns_python_float(value):
    out = check_number("ratio", value, lo=0, hi=1)
    assert out == float(value) and type(out) is float


def test_small_checkers_have_one_home():
    """data_prep, models.hexplane and cameras.lenses used to write their own int/number checkers."""
    assert data_format.is_int is is_int and scene_files.check_int is check_int and synth.check_int is check_int
    assert lenses.check_number is check_number and hexplane.check_number is check_number
    for module, name in ((scene_files, "_is_number"), (synth, "_check_int"), (lenses, "_check_number")):
        assert not hasattr(module, name), (module.__name__, name)
