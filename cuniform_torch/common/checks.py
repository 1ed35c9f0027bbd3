"""Small argument checks shared across the library, and :func:`wrap_angle`.

Each check raises ``ValueError`` with the message ``"{who}: {key} must be ..., got {value!r}"``, where ``who``
names the object being checked (``"dubins"``, ``"system 'crab'"``, ``"system JSON"``). This module imports no
other module of the package, so anything may use it.
"""

from __future__ import annotations

import math
import numbers
from typing import Any

import torch
from torch import Tensor

__all__ = ["wrap_angle", "positive", "non_negative", "finite", "positive_int", "check_positive_int", "float_tuple"]


def wrap_angle(theta: Tensor) -> Tensor:
    """Wrap angles to ``[-pi, pi)``, elementwise, keeping dtype and device."""
    return torch.remainder(theta + math.pi, 2.0 * math.pi) - math.pi


def _numbers(who: str, what: str, ok, values: dict[str, Any]) -> None:
    for key, value in values.items():
        if not (isinstance(value, (int, float)) and math.isfinite(value) and ok(value)):
            raise ValueError(f"{who}: {key} must be a {what}, got {value!r}")


def positive(who: str, **values: Any) -> None:
    """Each keyword's value is a finite number > 0 (``positive("dubins", speed=s, dt=dt)``)."""
    _numbers(who, "positive number", lambda v: v > 0, values)


def non_negative(who: str, **values: Any) -> None:
    """Each keyword's value is a finite number >= 0."""
    _numbers(who, "non-negative number", lambda v: v >= 0, values)


def finite(who: str, **values: Any) -> None:
    """Each keyword's value is a finite number."""
    _numbers(who, "finite number", lambda v: True, values)


def positive_int(who: str, key: str, value: Any, at_most: int | None = None) -> int:
    """``value`` is an ``int`` (not a bool) in ``[1, at_most]`` (no upper bound when ``at_most`` is None)."""
    if isinstance(value, bool) or not isinstance(value, int) or value < 1 or (at_most is not None and value > at_most):
        bound = "" if at_most is None else f" (at most {at_most})"
        raise ValueError(f"{who}: {key} must be a positive integer{bound}, got {value!r}")
    return value


def check_positive_int(name: str, value: object, *, integral: bool = True) -> int:
    """``value`` as a positive int, else ValueError ``"{name} must be a positive integer, got {value!r}"`` (a bool
    is not an int here). ``integral``: any ``numbers.Integral`` passes (a numpy integer: a K or T computed with
    numpy); False: only a Python ``int`` (a config field that is written to JSON as it is)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral if integral else int) or value < 1:
        raise ValueError(f"{name} must be a positive integer, got {value!r}")
    return int(value)


def float_tuple(value: Any, length: int, key: str, who: str) -> tuple[float, ...]:
    """``value`` as ``length`` finite floats, one per state dimension (any sequence of numbers: a list, a tuple,
    a numpy array)."""
    try:
        out = tuple(float(v) for v in value)
    except (TypeError, ValueError):
        raise ValueError(f"{who}: {key} must be a sequence of {length} numbers, got {value!r}") from None
    if len(out) != length:
        raise ValueError(f"{who}: {key} needs {length} value(s) (one per state dimension), got {len(out)}: {out}")
    if not all(math.isfinite(v) for v in out):
        raise ValueError(f"{who}: {key} must be finite, got {out}")
    return out
