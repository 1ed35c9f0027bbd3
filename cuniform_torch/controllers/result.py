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
    """One command's work (returned, not kept as controller state).

    For a batch of B robots every field has a leading robot dimension (``command [B, q]``, ``states
    [B, K, T+1, d]``, ...); :meth:`robot` takes one robot's. A controller given one state ``[d]`` returns the
    fields below without it."""

    command: Tensor
    """``[q]`` the control to apply now (``[B, q]`` for a batch)"""
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
    lambda_: Tensor | None = None
    """``[]`` the temperature these weights were computed with (``[B]`` for a batch): the ``lambda_`` given, or
    the one the automatic temperature (``lambda_="auto"``) chose for this command and robot"""

    @property
    def best(self) -> Tensor:
        """Index of the lowest-cost proposal (a 0-d tensor, ``[B]`` for a batch; no host sync)."""
        return torch.argmin(self.costs, dim=-1)

    @property
    def ess(self) -> Tensor:
        """The weights' effective sample size ``1 / sum(w^2)``: 1 (all weight on one proposal) to K (uniform); a
        0-d tensor (``[B]`` for a batch), no host sync."""
        return self.weights.square().sum(dim=-1).reciprocal()

    @property
    def batched(self) -> bool:
        """Whether the fields have a leading robot dimension."""
        return self.costs.ndim == 2

    def robot(self, b: int) -> MPPIResult:
        """Robot ``b``'s result of a batched one (views, no copies)."""
        if not self.batched:
            raise ValueError("robot(b) takes one robot of a batched result; this one has no robot dimension")
        return MPPIResult(self.command[b], self.nominal[b], self.states[b], self.actions[b], self.costs[b],
                          self.weights[b], None if self.lambda_ is None else self.lambda_[b])

    def best_actions(self) -> Tensor:
        """The lowest-cost proposal's action sequence: ``[T, q]`` (``[B, T, q]`` for a batch), no host sync."""
        if not self.batched:
            return self.actions.index_select(0, self.best.reshape(1))[0]
        index = self.best.view(-1, 1, 1, 1).expand(-1, 1, *self.actions.shape[2:])  # [B, 1, T, q]
        return self.actions.gather(1, index)[:, 0]
