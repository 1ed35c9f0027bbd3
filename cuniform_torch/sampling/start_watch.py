"""The start check of a policy valid from one start (a table, an MLP distilled from one): :class:`StartWatch`
warns once, :class:`StartMismatchWarning`, when such a policy is rolled out from another start (read by
:func:`cuniform_torch.rollout.rollout` through a policy's ``watch_start``).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable

import torch
from torch import Tensor

from cuniform_torch.grid.cells import Grid
from cuniform_torch.systems import System

__all__ = ["OWN_ROBOT", "StartMismatchWarning", "StartWatch"]

OWN_ROBOT = 'README, "Your own robot"'
"""where the README tells how to build a table at another start, or a table set"""


class StartMismatchWarning(UserWarning):
    """A table (or an MLP distilled from one) rolled out from a start it was not built for: its probabilities
    there are mostly the fallback's (uniform actions), not C-Uniform ones."""


class StartWatch:
    """Warns once per policy (:class:`StartMismatchWarning`) when a policy valid from one start is rolled out
    from another.

    ``build_start [d]`` is the start the table was built from (the zero state: tables record no other). A start
    *differs* when its cell (:class:`~cuniform_torch.grid.cells.Grid`) differs from the build start's in a dimension
    the rollout does not move into the start's frame: every dimension, or for an SE(2)-relative rollout the
    dimensions after ``(x, y, theta)`` (speeds, steering angles: a frame change does not move them). A pose-only
    SE(2) rollout is never watched; any other costs one host read of the start per rollout until it warns.
    """

    def __init__(self, who: str, system: System, build_start: Tensor | None = None):
        self.who = who
        self.system = system
        self.grid = Grid.of(system)
        d = self.grid.dim
        start = torch.zeros(d, dtype=torch.float64) if build_start is None else build_start.detach().double().cpu()
        if start.shape != (d,):
            raise ValueError(f"{who}: build_start must have shape [{d}], got {list(start.shape)}")
        self.build_start = start  # [d] float64
        self._build_cell = self.grid.cells(start)  # [d] int64
        self.warned = False

    def begin(self, policy: object, x0: Tensor, relative: bool) -> Callable[[], None] | None:
        """Before a rollout from ``x0 [d]`` (or ``[N, d]``): None when there is nothing to say, else the call that
        warns after the rollout, with the miss rate of that rollout (``policy.queries`` and ``policy.misses``)."""
        first = 3 if relative else 0
        if self.warned or first >= self.grid.dim:
            return None
        cells = self.grid.cells(x0.detach().double().cpu())[..., first:]  # [d - first] or [N, d - first]
        if bool((cells == self._build_cell[first:]).all()):
            return None
        queries, misses = int(getattr(policy, "queries", 0)), getattr(policy, "misses", None)
        misses = misses.clone() if isinstance(misses, Tensor) else None  # 0-d device tensor: no sync yet
        return lambda: self._warn(policy, x0, relative, queries, misses)

    def _warn(self, policy: object, x0: Tensor, relative: bool, queries: int, misses: Tensor | None) -> None:
        self.warned = True
        asked = int(getattr(policy, "queries", 0)) - queries
        missed = int(getattr(policy, "misses")) - int(misses) if misses is not None else 0
        rate = f"{missed / asked:.3f} ({missed} of {asked} lookups)" if asked else "not counted"
        name = getattr(self.system, "name", type(self.system).__name__)
        why = (f"{name}'s dimensions after (x, y, theta) are not moved by the frame change" if relative
               else f"{name} is not SE(2)-invariant, so no frame change moves the table to another start")
        start = [round(v, 4) for v in (x0 if x0.ndim == 1 else x0[0]).tolist()]
        warnings.warn(
            f"{self.who} is valid from its build start {self.build_start.tolist()} only and is rolled out from {start}; "
            f"{why}. Miss rate on this rollout: {rate}; a miss gets the fallback's uniform actions, not C-Uniform "
            f"ones. Build a table at that start, or a table set over the starts you need (see {OWN_ROBOT}). "
            f"Warned once per policy.", StartMismatchWarning, stacklevel=5)
