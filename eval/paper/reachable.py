"""The cells that real rollouts can reach from the origin, per level, by exhaustive enumeration.

Every action sequence is applied from the origin, with states merged per sub-cell bin
(:func:`precompute.coverage.method.enumerate_reachable`, ``merge_resolution`` bins per cell and dimension), so
5^10 sequences cost about a million states. This is the reference set for coverage percentages and for
uniformity "over the cells real rollouts can reach".
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from cuniform_torch.grid.cells import CellKeys
from cuniform_torch.systems import System, system_to_json
from precompute.coverage.method import enumerate_reachable


@dataclass(frozen=True)
class Reachable:
    level_cells: tuple[torch.Tensor, ...]
    """per level t = 0..T: ``[n_t, d]`` int64 cells reached at step t"""
    total: int
    """distinct cells over all levels (the coverage definition's denominator)"""
    merge_resolution: int

    @property
    def level_sizes(self) -> list[int]:
        return [len(c) for c in self.level_cells]


def reachable(system: System, horizon: int, merge_resolution: int = 32) -> Reachable:
    """Reachable cells per level for ``system`` from the origin (cached per system JSON, horizon, resolution)."""
    key = (system_to_json(system, horizon), merge_resolution)
    if key not in _CACHE:
        levels = enumerate_reachable(system, horizon, merge_resolution=merge_resolution)
        cells = torch.cat(levels.cells)
        total = int(torch.unique(CellKeys.covering(cells).pack(cells)).numel())
        _CACHE[key] = Reachable(tuple(levels.cells), total, merge_resolution)
    return _CACHE[key]


_CACHE: dict[tuple[str, int], Reachable] = {}
