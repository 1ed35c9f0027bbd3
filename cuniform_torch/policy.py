"""Table policy: p(u | cell, t) looked up from a C-Uniform table by packed keys, on any device.

Shapes: N states, d state dimensions, A actions, q action dimensions, C table cells.

The table's cells of every level are packed together with the level index into one sorted int64 key array
when the policy is made, so a lookup is pure tensor ops (``torch.searchsorted``). A state whose cell is not in
the level set L_t is a *miss*; it gets uniform probabilities over the actions (documented fallback) and is
counted in ``misses``.
"""

from __future__ import annotations

import os

import numpy as np
import torch
from torch import Tensor

from .grid import CellSet, Grid
from .systems import System
from .table import Table, read_table

__all__ = ["TablePolicy", "load_table"]


class TablePolicy:
    """The Policy interface over a table: ``actions [A, q]`` and ``action_probs(x [N, d], t) -> [N, A]``."""

    def __init__(self, table: Table, device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32):
        self.table = table
        self.system: System = table.make_system()
        self.grid = Grid.of(self.system)
        self.horizon = table.horizon
        self.device = torch.device(device)
        self.actions = torch.from_numpy(table.actions).to(device=self.device, dtype=dtype)  # [A, q]
        self.probs = torch.from_numpy(table.action_probs).to(device=self.device, dtype=dtype)  # [C, A]
        self.level_offsets = torch.from_numpy(table.level_offsets).to(self.device)  # [T+2]
        level = np.repeat(np.arange(table.horizon + 1), np.diff(table.level_offsets))
        keyed = np.concatenate((level[:, None], table.cells), axis=1)  # [C, 1+d]: (t, cell)
        self.index = CellSet.build(torch.from_numpy(keyed)).to(self.device)
        self._uniform = torch.full((1, self.num_actions), 1.0 / self.num_actions, device=self.device, dtype=dtype)
        self.misses = torch.zeros((), dtype=torch.int64, device=self.device)
        self.queries = torch.zeros((), dtype=torch.int64, device=self.device)

    @property
    def num_actions(self) -> int:
        return int(self.actions.shape[0])

    def level_size(self, t: int) -> int:
        return int(self.table.level_offsets[t + 1] - self.table.level_offsets[t])

    def rows(self, x: Tensor, t: int) -> Tensor:
        """Table row of each state's cell in level ``t``: ``x [N, d]`` -> ``[N]`` int64 (-1: not in L_t)."""
        if isinstance(t, bool) or not isinstance(t, int) or not 0 <= t <= self.horizon:
            raise ValueError(f"level t={t} is outside the table's levels 0..{self.horizon}")
        d = self.grid.dim
        if x.ndim != 2 or x.shape[1] != d:
            raise ValueError(f"states must have shape [N, {d}], got {list(x.shape)}")
        if x.device != self.device:
            raise ValueError(f"states are on {x.device} but the policy is on {self.device}")
        cells = self.grid.cells(x)  # [N, d]
        keyed = torch.cat((torch.full_like(cells[:, :1], t), cells), dim=1)  # [N, 1+d]
        return self.index.lookup(keyed)

    def action_probs(self, x: Tensor, t: int) -> Tensor:
        """p(u | cell of x, t): ``x [N, d]`` -> ``[N, A]``; a state outside L_t gets uniform probabilities."""
        rows = self.rows(x, t)  # [N]
        hit = rows >= 0
        self.misses += (~hit).sum()
        self.queries += rows.numel()
        probs = self.probs[rows.clamp(min=0)]  # [N, A]
        return torch.where(hit.unsqueeze(1), probs, self._uniform)

    @property
    def miss_rate(self) -> float:
        """Fraction of lookups so far whose state was outside the level set."""
        q = int(self.queries)
        return int(self.misses) / q if q else 0.0


def load_table(path: str | os.PathLike, device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32) -> TablePolicy:
    """Read and validate a table file, and return its :class:`TablePolicy` on ``device``."""
    return TablePolicy(read_table(path), device=device, dtype=dtype)
