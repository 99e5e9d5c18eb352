"""Argument checks shared by every layer: one message format for each kind of bad value.

Each check raises ``ValueError`` naming the parameter and the value it got, e.g.
``width must be a positive int, got 0``; the CLI prints that line as is. ``bool`` is never a number here.
The predicates :func:`is_int` and :func:`is_number` serve checks whose message names a whole group
(e.g. ``resolution must be 4 ints >= 3``).
"""
from __future__ import annotations

import math
from numbers import Integral, Real

import torch
from torch import Tensor

__all__ = ["is_int", "is_number", "check_int", "check_positive_int", "check_number", "check_positive", "check_finite",
           "MissingExtraError"]


class MissingExtraError(ModuleNotFoundError):
    """An optional extra of diff4splat is not installed for what was asked (a diffusers backbone, ``--engine ray``):
    the message names the ``pip install 'diff4splat[…]'`` command. Expected (one line, exit 2), unlike any other
    missing module, which is a broken install."""


def is_int(value: object) -> bool:
    """True for an integer (``int`` or numpy integer), ``bool`` excluded."""
    return isinstance(value, Integral) and not isinstance(value, bool)


def is_number(value: object) -> bool:
    """True for a finite real number (``int``, ``float`` or numpy scalar), ``bool`` excluded."""
    return isinstance(value, Real) and not isinstance(value, bool) and math.isfinite(value)


def _unit(what: str) -> str:
    return f" ({what})" if what else ""


def check_int(name: str, value: object, lo: int, what: str = "") -> int:
    """Return ``value`` as an ``int`` if it is an integer ≥ ``lo`` (``bool`` is refused).

    Args:
        name: the parameter's name, as the caller's user knows it.
        value: the value to check (int or numpy integer).
        lo: the smallest value allowed.
        what: optional unit, e.g. ``"frames"``, appended to the message.

    Raises:
        ValueError: ``value`` is not an integer or is < ``lo``, e.g. ``size must be an integer ≥ 8, got 4``.
    """
    if not is_int(value) or value < lo:
        raise ValueError(f"{name} must be an integer ≥ {lo}{_unit(what)}, got {value!r}")
    return int(value)


def check_positive_int(name: str, value: object, what: str = "") -> int:
    """Return ``value`` as an ``int`` if it is an integer ≥ 1 (``bool`` is refused).

    Args:
        name: the parameter's name, as the caller's user knows it.
        value: the value to check (int or numpy integer).
        what: optional unit, e.g. ``"pixels"``, appended to the message.

    Raises:
        ValueError: ``value`` is not an integer or is < 1.
    """
    if not is_int(value) or value < 1:
        raise ValueError(f"{name} must be a positive int{_unit(what)}, got {value!r}")
    return int(value)


def check_number(name: str, value: object, *, lo: float | None = None, hi: float | None = None,
                 lo_open: bool = False, what: str = "") -> float:
    """Return ``value`` as a ``float`` if it is a finite real number in the range given.

    Args:
        name: the parameter's name, as the caller's user knows it.
        value: the value to check (int, float or numpy scalar; ``bool``, strings and tensors are refused).
        lo: the lower bound, or None; included unless ``lo_open``.
        hi: the upper bound (included), or None.
        lo_open: exclude ``lo`` itself (value > lo).
        what: optional unit, e.g. ``"metres"``, appended to the message.

    Raises:
        ValueError: not a finite number or out of range; the message states the range, e.g.
            ``fps must be a finite number > 0, got 0``, ``duration must be a number in [0, 1], got 2``.
    """
    ok = is_number(value)
    if ok and lo is not None:
        ok = value > lo if lo_open else value >= lo
    if ok and hi is not None:
        ok = value <= hi
    if ok:
        return float(value)
    if lo is not None and hi is not None:
        expected = f"a number in {'(' if lo_open else '['}{lo:g}, {hi:g}]"
    elif lo is not None:
        expected = f"a finite number {'>' if lo_open else '≥'} {lo:g}"
    elif hi is not None:
        expected = f"a finite number ≤ {hi:g}"
    else:
        expected = "a finite number"
    raise ValueError(f"{name} must be {expected}{_unit(what)}, got {value!r}")


def check_positive(name: str, value: object) -> float:
    """Return ``value`` as a ``float`` if it is a finite number > 0 (``bool`` and strings are refused).

    Args:
        name: the parameter's name, as the caller's user knows it.
        value: the value to check (int, float, numpy scalar or one-element tensor).

    Raises:
        ValueError: ``value`` is not a number, not finite, or ≤ 0.
    """
    if isinstance(value, (bool, str, bytes)):
        raise ValueError(f"{name} must be a positive finite number, got {value!r}")
    try:
        v = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a positive finite number, got {value!r}") from None
    if not math.isfinite(v) or v <= 0:
        raise ValueError(f"{name} must be a positive finite number, got {value!r}")
    return v


def check_finite(name: str, tensor: Tensor) -> None:
    """Raise ``ValueError`` naming ``name`` if the floating-point ``tensor`` holds NaN or ±inf.

    Integer and empty tensors pass. The message counts the bad entries, e.g.
    ``means contains 2 non-finite value(s) (NaN or inf)``.

    Args:
        name: what the message calls the tensor.
        tensor: any shape, dtype and device.

    Raises:
        ValueError: ``tensor`` is floating point and holds at least one NaN or ±inf.
    """
    if not tensor.is_floating_point() or not tensor.numel():
        return
    # One reduction first: NaN and ±inf make the sum non-finite, so a finite sum proves every entry finite; only a
    # non-finite sum (which large finite values can also give, by overflow) takes the exact test. Summed in float32
    # (float64 for float64 tensors): a float64 sum converts every float32 entry first, most of the cost of checking a
    # paper-size deformation (docs/benchmarks.md, "Writing the output folder").
    acc = torch.float64 if tensor.dtype == torch.float64 else torch.float32
    if bool(torch.isfinite(tensor.detach().sum(dtype=acc))):
        return
    bad = int((~torch.isfinite(tensor)).sum())
    if bad:
        raise ValueError(f"{name} contains {bad} non-finite value(s) (NaN or inf)")
