"""The state a table is built from: the zero state, or a start the user gives (``--start``).

A table is valid from its start (its level 0 is the start's cell). For an SE(2)-invariant system the frame
change serves every pose, so only the dimensions after (x, y, theta) may be given: a start pose is refused
(build at pose 0 and roll out from any pose).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch

from cuniform_torch.systems import System

__all__ = ["check_start", "start_state", "start_array"]


def check_start(start: Sequence[float] | None) -> tuple[float, ...] | None:
    """``start`` as a tuple of finite floats (None stays None); a clear ValueError otherwise."""
    if start is None:
        return None
    try:
        values = tuple(float(v) for v in start)
    except (TypeError, ValueError):
        raise ValueError(f"start must be a sequence of numbers, got {start!r}") from None
    if not values or not all(math.isfinite(v) for v in values):
        raise ValueError(f"start must be finite numbers, got {list(start)}")
    return values


def start_state(system: System, start: Sequence[float] | None) -> torch.Tensor:
    """The build start of ``system`` as ``[1, d]`` float64: ``start`` (None: the zero state), checked against
    the system's dimensions and, for an SE(2)-invariant system, its pose (which must be 0)."""
    d = len(system.periodic)
    if start is None:
        return torch.zeros((1, d), dtype=torch.float64)
    values = check_start(start)
    if len(values) != d:
        raise ValueError(f"--start needs {d} numbers for {system.name} (its state dimension), got {len(values)}")
    if getattr(system, "se2_invariant", False) and any(v != 0 for v in values[:3]):
        raise ValueError(f"{system.name} is SE(2)-invariant: one table built at pose 0 serves every pose, so the "
                         f"start's x, y, theta must be 0 (got {list(values[:3])}); give only the other dimensions")
    return torch.tensor([values], dtype=torch.float64)


def start_array(start: Sequence[float] | None) -> np.ndarray | None:
    """The table's ``start`` key (float64 ``[d]``), or None for the zero state."""
    return None if start is None else np.asarray(check_start(start), dtype=np.float64)
