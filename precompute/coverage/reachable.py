"""Step 1 of the coverage method (:mod:`precompute.coverage.method`): the states reachable from the start, level
by level under every action, merged per sub-cell bin, with their cells and successors.

Shapes: M_t merged reachable states at level t, n_t reachable cells of level t, A actions, d state dims.

States that fall in the same bin (``merge_resolution`` bins per cell and dimension) merge; each bin keeps its
first state as the representative, so the approximation error is below 1/merge_resolution of a cell per step.
A level that would hold more than ``state_budget`` merged states is merged more coarsely (the resolution is cut
by a quarter, from that level on, until it fits). With a local map, states whose cell is not free are dropped.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch

from cuniform_torch.grid.cells import CellKeys, Grid
from cuniform_torch.systems import System
from precompute.levels.safe_map import MapError, SafeCells
from precompute.levels.start import start_state

__all__ = ["ReachableLevels", "enumerate_reachable"]


@dataclass
class ReachableLevels:
    """The merged reachable states of every level and their successors."""

    cells: list[torch.Tensor] = field(default_factory=list)
    """per level: ``[n_t, d]`` int64 reachable cells, ascending packed-key order"""
    state_cell: list[torch.Tensor] = field(default_factory=list)
    """per level: ``[M_t]`` index of each state's cell in ``cells[t]``"""
    successor: list[torch.Tensor] = field(default_factory=list)
    """per level t < T: ``[M_t, A]`` index of the successor state in level t+1 (-1: pruned by a map)"""
    num_states: list[int] = field(default_factory=list)
    resolution: list[int] = field(default_factory=list)
    """per level: the merge resolution its states were merged with (level 0: the origin alone)"""


def _index_cells(cells: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Distinct cells (ascending key order) and each row's index among them."""
    keys = CellKeys.covering(cells)
    uniq, inverse = torch.unique(keys.pack(cells), return_inverse=True)
    return keys.unpack(uniq), inverse


def _merge(nxt: torch.Tensor, cell_size: torch.Tensor, resolution: int,
           pair: torch.Tensor) -> tuple[int, torch.Tensor, torch.Tensor]:
    """Merge states ``[K, d]`` per bin of ``cell_size / resolution``: the number of bins (ascending key order), each
    state's bin and each bin's smallest ``pair`` (``[K]``, ascending: the index of the state's (state, action)
    pair), its representative. The bins' keys come from two compiled passes (:mod:`precompute.coverage.loops`:
    the box, then the keys) instead of five ``[K, d]`` temporaries."""
    from precompute.coverage.loops import bin_box, bin_keys  # numba: compiled (or loaded) on first use

    states, size = np.ascontiguousarray(nxt.numpy()), (cell_size / resolution).numpy()
    d = states.shape[1]
    lo, hi = np.empty(d, np.int64), np.empty(d, np.int64)
    bin_box(states, size, lo, hi)
    box = CellKeys.covering(torch.from_numpy(np.stack((lo, hi))))  # refuses a box too large for int64 keys
    keys = np.empty(states.shape[0], np.int64)
    bin_keys(states, size, lo, box.span.numpy(), keys)
    uniq, inverse = torch.unique(torch.from_numpy(keys), return_inverse=True)
    first = torch.empty(len(uniq), dtype=torch.int64).scatter_reduce(0, inverse, pair, reduce="amin",
                                                                     include_self=False)  # every bin has a state
    return len(uniq), inverse, first


def _merge_within(nxt: torch.Tensor, cell_size: torch.Tensor, resolution: int, budget: int,
                  pair: torch.Tensor) -> tuple[int, torch.Tensor, torch.Tensor, int]:
    """:func:`_merge` at the finest resolution (``resolution`` cut by a quarter, down to 1) whose bins number at
    most ``budget`` (0: no budget); returns the bins, each state's bin, each bin's smallest pair and the resolution
    used."""
    count, inverse, first = _merge(nxt, cell_size, resolution, pair)
    while budget and count > budget and resolution > 1:  # about (3/4)^d fewer bins per cut: few cuts per level
        resolution = min(resolution - 1, resolution * 3 // 4)
        count, inverse, first = _merge(nxt, cell_size, resolution, pair)
    return count, inverse, first, resolution


def enumerate_reachable(system: System, horizon: int, merge_resolution: int = 32, max_states: int = 20_000_000,
                        progress: Callable[[int, int, int], None] | None = None,
                        state_budget: int = 0, start: tuple[float, ...] | None = None,
                        safe: SafeCells | None = None) -> ReachableLevels:
    """Reachable states from ``start`` (None: the origin), merged per sub-cell bin, with their cells and successors.

    ``state_budget`` > 0: a level with more merged states is merged with a quarter less resolution until it
    fits (or the resolution is 1); the later levels keep the coarser resolution (states never split again).
    ``safe``: states whose cell is not free are dropped (successor -1)."""
    grid = Grid.of(system)
    actions = system.action_set(dtype=torch.float64)  # [A, q]
    A = actions.shape[0]
    cell_size = torch.tensor(grid.cell_size, dtype=torch.float64)  # [d]
    x = start_state(system, start)  # [1, d]
    if safe is not None:
        safe.check_start(grid.cells(x), x)
    levels = ReachableLevels()
    cells, inv = _index_cells(grid.cells(x))
    levels.cells.append(cells)
    levels.state_cell.append(inv)
    levels.num_states.append(1)
    levels.resolution.append(merge_resolution)
    resolution = merge_resolution
    for t in range(horizon):
        M = x.shape[0]
        nxt = system.step(x.repeat_interleave(A, dim=0), actions.repeat(M, 1))  # [M*A, d]
        pair = torch.arange(M * A)
        if safe is not None:
            ok = safe.keep(grid.cells(nxt))  # [M*A]
            if not ok.any():
                raise MapError(f"the map leaves no free cell at level {t + 1}: every state reachable in {t + 1} "
                               f"steps lies within --radius {safe.radius:g} m of an obstacle (the start is boxed in)")
            pair = pair[ok]
        count, inverse, first, resolution = _merge_within(nxt if safe is None else nxt[pair], cell_size, resolution,
                                                          state_budget, pair)
        if count > max_states:
            raise ValueError(f"level {t + 1} has {count} merged states (> max_states={max_states}); "
                             f"lower --merge-resolution or --state-budget")
        x = nxt[first]  # representatives [M', d]
        if safe is not None:
            inverse = torch.full((M * A,), -1, dtype=torch.int64).index_put_((pair,), inverse)
        levels.successor.append(inverse.view(M, A))
        cells, inv = _index_cells(grid.cells(x))
        levels.cells.append(cells)
        levels.state_cell.append(inv)
        levels.num_states.append(count)
        levels.resolution.append(resolution)
        if progress is not None:
            progress(t, count, len(cells))
    return levels
