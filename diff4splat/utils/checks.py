"""Argument checks shared by every layer: one message format per kind of bad value.

Each check raises ``ValueError`` naming the parameter and the value it got (``width must be a positive int, got
0``), which the CLI prints as is. ``bool`` is never a number here.
"""
from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import field, fields
from functools import partial
from numbers import Integral, Real
from typing import Any

import torch
from torch import Tensor

__all__ = ["is_int", "is_number", "check_int", "check_positive_int", "check_number", "check_positive", "check_finite",
           "ranged", "check_ranges", "MissingExtraError"]


class MissingExtraError(ModuleNotFoundError):
    """An optional extra of diff4splat is not installed for what was asked; the message names the ``pip install
    'diff4splat[…]'`` command. An expected error (one line, exit 2), unlike any other missing module."""


def is_int(value: object) -> bool:
    """True for an integer (``int`` or numpy integer), ``bool`` excluded."""
    return isinstance(value, Integral) and not isinstance(value, bool)


def is_number(value: object) -> bool:
    """True for a finite real number (``int``, ``float`` or numpy scalar), ``bool`` excluded."""
    return isinstance(value, Real) and not isinstance(value, bool) and math.isfinite(value)


def _unit(what: str) -> str:
    """The message suffix `` (what)``, or nothing."""
    return f" ({what})" if what else ""


def check_int(name: str, value: object, lo: int, what: str = "") -> int:
    """``value`` as an ``int`` if it is an integer ≥ ``lo`` (``bool`` refused); ``what``: an optional unit for the
    message.

    Raises:
        ValueError: not an integer or < ``lo``.
    """
    if not is_int(value) or value < lo:
        raise ValueError(f"{name} must be an integer ≥ {lo}{_unit(what)}, got {value!r}")
    return int(value)


def check_positive_int(name: str, value: object, what: str = "") -> int:
    """``value`` as an ``int`` if it is an integer ≥ 1 (``bool`` refused); ``what``: an optional unit for the message.

    Raises:
        ValueError: not an integer or < 1.
    """
    if not is_int(value) or value < 1:
        raise ValueError(f"{name} must be a positive int{_unit(what)}, got {value!r}")
    return int(value)


def check_number(name: str, value: object, *, lo: float | None = None, hi: float | None = None,
                 lo_open: bool = False, what: str = "") -> float:
    """``value`` as a ``float`` if it is a finite real number in [``lo``, ``hi``] (either bound None: open; ``lo_open``
    excludes ``lo``); ``bool``, strings and tensors are refused; ``what``: an optional unit for the message.

    Raises:
        ValueError: not a finite number or out of range; the message states the range.
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
    """``value`` (int, float, numpy scalar or one-element tensor) as a ``float`` if it is finite and > 0.

    Raises:
        ValueError: not a number (``bool`` and strings included), not finite, or ≤ 0.
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


def ranged(default: object, check: Callable[..., object] = check_positive_int, **bounds: object) -> Any:
    """A dataclass field defaulting to ``default`` whose value :func:`check_ranges` checks with
    ``check(name, value, **bounds)`` (one of this module's checks, default :func:`check_positive_int`)."""
    return field(default=default, metadata={"check": partial(check, **bounds)})


def check_ranges(owner: str, obj: object) -> None:
    """Check each field of the dataclass instance ``obj`` declared with :func:`ranged`, named ``owner.field``.

    Raises:
        ValueError: the first field out of its range (its check's message).
    """
    for f in fields(obj):
        check = f.metadata.get("check")
        if check is not None:
            check(f"{owner}.{f.name}", getattr(obj, f.name))


def check_finite(name: str, tensor: Tensor) -> None:
    """Raise if the floating-point ``tensor`` holds NaN or ±inf; integer and empty tensors pass.

    Raises:
        ValueError: naming ``name`` and counting the non-finite entries.
    """
    if not tensor.is_floating_point() or not tensor.numel():
        return
    # A finite sum proves every entry finite; a non-finite one (NaN, inf, or overflow) takes the exact test.
    acc = torch.float64 if tensor.dtype == torch.float64 else torch.float32
    if bool(torch.isfinite(tensor.detach().sum(dtype=acc))):
        return
    bad = int((~torch.isfinite(tensor)).sum())
    if bad:
        raise ValueError(f"{name} contains {bad} non-finite value(s) (NaN or inf)")
