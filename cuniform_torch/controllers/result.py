"""What one MPPI command returns (:class:`MPPIResult`).

Shapes: K samples (proposals), T horizon, d state dimensions, q action dimensions.

Its own module, below both the core (which makes it) and the proposals (whose ``update`` reads it), so that
neither imports the other for it.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = ["MPPIResult"]


@dataclass
class MPPIResult:
    """One command's work (returned, not kept as controller state)."""

    command: Tensor
    """``[q]`` the control to apply now"""
    nominal: Tensor
    """``[T, q]`` the weighted action sequence (before the warm-start shift)"""
    states: Tensor
    """``[K, T+1, d]`` the proposals"""
    actions: Tensor
    """``[K, T, q]``"""
    costs: Tensor
    """``[K]`` finite costs"""
    weights: Tensor
    """``[K]`` sum to 1"""

    @property
    def best(self) -> Tensor:
        """Index of the lowest-cost proposal (a 0-d tensor; no host sync)."""
        return torch.argmin(self.costs)
