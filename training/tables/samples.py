"""The distillation's training points: the pooled cells (:class:`PooledCells`, made by
:func:`training.tables.setup.pool_cells`, read by :func:`training.tables.loop.run_epochs`), jittered points inside
the cells, and the level weights of the loss.

Shapes: C cells (all tables, all levels), V validation points, d state dimensions, A actions.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from cuniform_torch.grid.cells import Grid
from training.tables.evaluate import jitter_cells

__all__ = ["PooledCells", "make_samples", "level_weights"]


@dataclass
class PooledCells:
    """Every cell of every (table, level) group (the group of a cell sets its weight) and the validation points."""

    centres: Tensor
    """``[C, d]`` float64 cell centres (on the CPU: the jitter is drawn there)"""
    probs: Tensor
    """``[C, A]`` each cell's row of ``action_probs``, on the device"""
    levels: Tensor
    """``[C]`` each cell's level t (its time feature)"""
    group: Tensor
    """``[C]`` each cell's (table, level) group: ``table index * (T + 1) + t``"""
    G: int
    """the number of groups"""
    best_rows: Tensor
    """``[C, A]`` the table's most likely actions of each cell"""
    val_rows: Tensor
    """``[V]`` the cell of each validation point, on the device"""
    val_x: Tensor
    """``[V, d]`` float32 validation points"""
    val_t: Tensor
    """``[V]`` their levels"""
    val_w: Tensor
    """``[V]`` their level weights (sum to 1)"""


def make_samples(centres: torch.Tensor, grid: Grid, jitter: int, with_centres: bool,
                 generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """Sample rows (cells) and states of one pass: the centres (when asked) + ``jitter`` points per cell.

    Returns ``rows [N]`` and ``x [N, d]`` float64; every cell gets the same number k of samples.
    """
    C = centres.shape[0]
    jittered = torch.arange(C).repeat(jitter)  # [C * jitter]
    x = jitter_cells(centres, grid, jittered, generator)
    if with_centres:
        return torch.cat((torch.arange(C), jittered)), torch.cat((centres, x))
    return jittered, x


def level_weights(sample_group: torch.Tensor, num_groups: int) -> torch.Tensor:
    """Weight of each sample ``[N]``: 1 / (samples of its (table, level) group) / (number of groups); sums to 1."""
    per_group = torch.bincount(sample_group, minlength=num_groups).double()  # [G]
    return 1.0 / (per_group[sample_group] * num_groups)
