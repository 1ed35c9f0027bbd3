"""The distillation's training points: jittered points inside the cells, and the level weights of the loss."""

from __future__ import annotations

import torch

from cuniform_torch.grid.cells import Grid

from training.tables.evaluate import jitter_cells

__all__ = ["make_samples", "level_weights"]


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
