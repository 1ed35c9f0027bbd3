"""Coverage of sampled trajectories: distinct grid cells visited, overall and per level.

Shapes: N trajectories, T horizon, d state dimensions.

Coverage is the number of distinct cells visited by any trajectory at any step, start included (the paper's
reference release's definition). Per level, it is the number of distinct cells at step t; against a table, the
number of distinct cells *of L_t* visited at step t. N perfectly uniform draws over m cells cover
``m (1 - (1 - 1/m)^N)`` cells on average: the ceiling for any sampler (:func:`uniform_ceiling`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from .grid import CellKeys, Grid

__all__ = ["Coverage", "coverage", "uniform_ceiling"]


@dataclass
class Coverage:
    total: int
    """distinct cells over all steps (start included)"""
    per_level: list[int]
    """distinct cells at each step t = 0..T"""
    in_level_set: list[int] | None = None
    """distinct cells of L_t visited at step t (when a table policy was given)"""


def uniform_ceiling(num_cells: int, num_samples: int) -> float:
    """Expected distinct cells hit by ``num_samples`` uniform draws over ``num_cells`` cells."""
    return num_cells * (1.0 - (1.0 - 1.0 / num_cells) ** num_samples)


def coverage(states: Tensor, grid: Grid, table_policy=None) -> Coverage:
    """Coverage of ``states [N, T+1, d]`` on ``grid``; with a TablePolicy, also the cells of each L_t reached."""
    if states.ndim != 3 or states.shape[2] != grid.dim:
        raise ValueError(f"states must have shape [N, T+1, {grid.dim}], got {list(states.shape)}")
    N, T1, d = states.shape
    cells = grid.cells(states).reshape(-1, d)  # [N*(T+1), d]
    level = torch.arange(T1, device=states.device).repeat(N).unsqueeze(1)  # step index of each row
    keyed = torch.cat((level, cells), dim=1)
    keys = CellKeys.covering(keyed)
    per_level_keys = torch.unique(keys.pack(keyed))
    per_level_t = keys.unpack(per_level_keys)[:, 0]
    per_level = torch.bincount(per_level_t, minlength=T1).tolist()
    cell_keys = CellKeys.covering(cells)
    total = int(torch.unique(cell_keys.pack(cells)).numel())
    in_level = None
    if table_policy is not None:
        in_level = []
        for t in range(min(T1, table_policy.horizon + 1)):
            rows = table_policy.rows(states[:, t].to(table_policy.dtype), t)
            in_level.append(int(torch.unique(rows[rows >= 0]).numel()))
    return Coverage(total=total, per_level=per_level, in_level_set=in_level)
