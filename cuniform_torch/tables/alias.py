"""Walker alias tables: draw an action from a probability row with one uniform number and two gathers.

Shapes: R probability rows, A actions, q action dimensions, E entries (rows as a lookup finds them).

:func:`alias_tables` builds, per row, a threshold and an alias per column; :class:`AliasTables` lays them out
per lookup entry the way both table kernels (:mod:`~cuniform_torch.tables.torch_kernel`,
:mod:`~cuniform_torch.tables.cpu_kernels`) read them. With ``r`` uniform in ``[0, A)`` and ``j = floor(r)``, the draw
keeps column ``j`` when ``r < threshold[e A + j]`` (``= j + p_keep``), else takes its alias; the two outcomes
sit side by side, so the comparison picks one by index: ``outcome[2 (e A + j) + keep]``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = ["AliasTables", "alias_tables"]


def alias_tables(probs: Tensor) -> tuple[Tensor, Tensor]:
    """Walker alias tables of probability rows ``[R, A]`` (float64): thresholds ``[R, A]`` in [0, 1], aliases ``[R, A]``.

    Drawing column ``j`` uniformly, then keeping it with probability ``thr[j]`` and else taking ``alias[j]``, draws
    column ``a`` with probability ``probs[a]``. Vectorized over rows (Vose): each of the ``A - 1`` passes settles, in
    every row, the open column of least mass against the open column of most; a column of zero probability gets
    threshold 0 and a positive-probability alias, so it is never drawn.
    """
    R, A = probs.shape
    q = probs * A / probs.sum(dim=1, keepdim=True)  # [R, A] mass per column, mean 1
    thr = torch.ones_like(q)
    alias = torch.arange(A).expand(R, A).clone()  # [R, A]
    open_ = torch.ones_like(q, dtype=torch.bool)
    rows = torch.arange(R)
    for _ in range(A - 1):
        small = torch.where(open_, q, torch.inf).argmin(dim=1)  # [R]
        large = torch.where(open_, q, -torch.inf).argmax(dim=1)  # [R]
        qs = q[rows, small]
        settle = qs < 1.0  # rows whose open columns are all ~1 keep threshold 1
        thr[rows, small] = torch.where(settle, qs.clamp(min=0.0), 1.0)
        alias[rows, small] = torch.where(settle, large, small)
        q[rows, large] -= torch.where(settle, 1.0 - qs, 0.0)
        open_[rows, small] = False
    return thr, alias


@dataclass(frozen=True)
class AliasTables:
    """The alias tables of every lookup entry, flattened for two gathers per draw (see the module docstring)."""

    threshold: Tensor
    """``[(E+1) A]`` policy dtype: ``j + p_keep`` of column ``j`` of entry ``e`` at ``e A + j``"""
    outcome: Tensor
    """``[(E+1) A 2]``: (alias, j) of each column, as action values (policy dtype) when
    :attr:`outcome_is_value`, else action indices (int32)"""
    outcome_is_value: bool
    """True when the actions are scalars (q == 1): a draw is then its action, with no gather of ``actions``"""

    @classmethod
    def build(cls, rows: Tensor, entry_row: Tensor, actions: Tensor, dtype: torch.dtype,
              device: torch.device) -> AliasTables:
        """Tables of the probability ``rows [R, A]`` (float64), laid out per entry: entry ``e`` draws from row
        ``entry_row[e]`` (``entry_row [E+1]``, CPU int64); ``actions [A, q]``."""
        thr, alias = alias_tables(rows)
        thr, alias = thr[entry_row], alias[entry_row]  # [E+1, A]
        cols = torch.arange(rows.shape[1])
        threshold = (cols + thr).to(dtype).reshape(-1).to(device)  # [(E+1) A]
        pair = torch.stack((alias, cols.expand_as(alias)), dim=2).reshape(-1)  # [(E+1) A 2]: alias, then j
        scalar = actions.shape[1] == 1
        if scalar:
            pair = actions[:, 0].cpu()[pair]
        outcome = pair.to(device=device, dtype=dtype if scalar else torch.int32)
        return cls(threshold, outcome, scalar)
