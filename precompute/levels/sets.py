"""Level sets on a grid and the recorded transitions between consecutive levels.

Shapes: n cells in L_t, m cells in L_{t+1}, P sample points per cell, A actions, d state dimensions,
K recorded transitions.

As the paper's reference release builds them: L_{t+1} is the set of cells reached from the *centres* of the
cells of L_t under every action. The transitions come from sample points of each cell (by default the 3^d
lattice at offsets {-1, 0, +1} x delta/2.01 around the centre, centre included), stepped under every action
and kept where they land in L_{t+1}. For every (cell, action) we record which next cells it reaches and the
fraction of its kept points that land in each.

Point modes (:class:`PointMode`):

* ``centers`` (default): level sets from the centres, transitions from the 3^d lattice.
* ``lattice``: level sets from all lattice points (larger, over-approximated level sets); all points kept.
* ``random``: level sets from the centres, transitions from the centre plus K uniform random points per cell.
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from cuniform_torch.common.options import Option, option_label
from cuniform_torch.grid.cells import CellKeys, CellSet, Grid
from cuniform_torch.systems import System

__all__ = ["PointMode", "LevelStep", "EmptyLevelError", "cell_sample_offsets", "next_level", "LATTICE_SCALE"]

LATTICE_SCALE = 1.0 / 2.01
"""lattice points sit at {-1, 0, +1} x delta x LATTICE_SCALE around the centre (delta/2.01, as the reference)"""

_CHUNK_POINTS = 1 << 21  # state-action pairs stepped at once (bounds memory on big levels)
_REUSE_LIMIT = 1 << 25  # int64 cell entries (256 MiB) kept between the two passes in lattice mode


@option_label('tie rule')
class TieRule(Option):
    """How a step that lands exactly on a cell boundary is assigned (see :meth:`~cuniform_torch.grid.cells.Grid.cells_from`)."""

    SYMMETRIC = "symmetric"
    """half-cell steps round away from their source cell: mirror-symmetric level sets, the authors' sizes"""
    GRID = "grid"
    """the state's own cell, ``round(x / delta + offset)``: the grid offset decides (before: the only rule)"""


@option_label('point mode')
class PointMode(Option):
    """How sample points of a cell are chosen (see the module docstring)."""

    CENTERS = "centers"
    LATTICE = "lattice"
    RANDOM = "random"



class EmptyLevelError(ValueError):
    """Every cell of the next level was pruned (``next_level``'s ``keep`` kept none)."""


@dataclass
class LevelStep:
    """One step L_t -> L_{t+1}: the next level and the recorded transitions (local row indices)."""

    next_cells: np.ndarray
    """``[m, d]`` int64, cells of L_{t+1} in ascending packed-key order"""
    src: np.ndarray
    """``[K]`` int64 row in L_t"""
    act: np.ndarray
    """``[K]`` int64 action index"""
    dst: np.ndarray
    """``[K]`` int64 row in L_{t+1}"""
    frac: np.ndarray
    """``[K]`` float64: fraction of the kept points of (src, act) that land in dst"""
    kept_fraction: float
    """share of all stepped (point, action) pairs that landed in L_{t+1}"""
    seconds: tuple[float, float] = (0.0, 0.0)
    """time spent building the level set, then the transitions (arcs)"""


def cell_sample_offsets(grid: Grid, mode: PointMode, n: int, points_per_cell: int, generator: torch.Generator | None) -> Tensor:
    """Offsets of the sample points from each cell centre, in state units: ``[n, P, d]`` or ``[1, P, d]`` float64.

    Point 0 is always the centre.
    """
    delta = torch.tensor(grid.cell_size, dtype=torch.float64)
    if mode is PointMode.RANDOM:
        if points_per_cell < 1:
            raise ValueError(f"points_per_cell must be >= 1 for random points, got {points_per_cell}")
        rand = torch.rand((n, points_per_cell, grid.dim), dtype=torch.float64, generator=generator) - 0.5
        centre = torch.zeros((n, 1, grid.dim), dtype=torch.float64)
        return torch.cat((centre, rand * delta), dim=1)
    grid_pts = sorted(itertools.product((-1, 0, 1), repeat=grid.dim), key=lambda p: any(p))  # centre first
    lattice = torch.tensor(grid_pts, dtype=torch.float64) * delta * LATTICE_SCALE  # [3^d, d]
    return lattice.unsqueeze(0)


def _step_cells(system: System, grid: Grid, points: Tensor, actions: Tensor, source: Tensor,
                ties: TieRule = TieRule.SYMMETRIC) -> Tensor:
    """Cells reached from ``points [n, P, d]`` of the cells ``source [n, d]`` under every action ``[A, q]``:
    ``[n, P, A, d]`` int64, counted from the source cell so that half-cell ties break by direction
    (:meth:`~cuniform_torch.grid.cells.Grid.cells_from`)."""
    n, P, d = points.shape
    A = actions.shape[0]
    x = points.unsqueeze(2).expand(n, P, A, d).reshape(-1, d)
    u = actions.unsqueeze(0).expand(n * P, A, actions.shape[1]).reshape(-1, actions.shape[1])
    reached = system.step(x, u).reshape(n, P, A, d)
    return grid.cells_from(source, reached) if ties is TieRule.SYMMETRIC else grid.cells(reached)


def _chunks(n: int, per_cell: int):
    size = max(1, _CHUNK_POINTS // max(per_cell, 1))
    for start in range(0, n, size):
        yield start, min(n, start + size)


def next_level(
    system: System,
    cells: np.ndarray,
    mode: PointMode = PointMode.CENTERS,
    points_per_cell: int = 8,
    generator: torch.Generator | None = None,
    ties: TieRule | str = TieRule.SYMMETRIC,
    keep: Callable[[Tensor], Tensor] | None = None,
) -> LevelStep:
    """Build L_{t+1} and the transitions from the cells of L_t (``cells [n, d]`` int64).

    ``keep(cells [m, d]) -> bool [m]`` prunes L_{t+1} (safe level sets: the cells in collision with a map)
    before the transitions are recorded, so points landing in a pruned cell are dropped like points that leave
    the level set; :class:`EmptyLevelError` when it keeps no cell."""
    mode = PointMode.parse(mode)
    ties = TieRule.parse(ties)
    grid = Grid.of(system)
    actions = system.action_set(dtype=torch.float64)  # [A, q]
    A = actions.shape[0]
    cells_t = torch.from_numpy(np.ascontiguousarray(cells))
    n = cells_t.shape[0]
    centres = grid.centers(cells_t, torch.float64)  # [n, d]
    offsets = cell_sample_offsets(grid, mode, n, points_per_cell, generator)  # [n or 1, P, d]
    P = offsets.shape[1]

    def points(lo: int, hi: int) -> Tensor:  # [hi-lo, P, d]
        off = offsets if offsets.shape[0] == 1 else offsets[lo:hi]
        return grid.wrap(centres[lo:hi].unsqueeze(1) + off)

    # Pass 1: the next level, from the centres (or every lattice point).
    t0 = time.perf_counter()
    level_pts = P if mode is PointMode.LATTICE else 1
    # lattice mode steps every point in pass 1 already: keep those cells for pass 2 when they fit in memory
    reuse = mode is PointMode.LATTICE and n * P * A * grid.dim <= _REUSE_LIMIT
    found, stepped = [], []
    for lo, hi in _chunks(n, level_pts * A):
        pts = points(lo, hi) if mode is PointMode.LATTICE else centres[lo:hi].unsqueeze(1)
        reached = _step_cells(system, grid, pts, actions, cells_t[lo:hi], ties)  # [c, P or 1, A, d]
        if reuse:
            stepped.append(reached)
        reached = reached.reshape(-1, grid.dim)
        keys = CellKeys.covering(reached)
        found.append(keys.unpack(torch.unique(keys.pack(reached))))
    reached = torch.cat(found)
    keys = CellKeys.covering(reached)
    next_keys = torch.unique(keys.pack(reached))  # sorted ascending
    next_cells = keys.unpack(next_keys)  # [m, d]
    if keep is not None:
        free = keep(next_cells)  # [m] bool
        next_keys, next_cells = next_keys[free], next_cells[free]
        if len(next_keys) == 0:
            raise EmptyLevelError("no cell of the next level is free")
    next_set = CellSet(keys, next_keys, torch.arange(len(next_keys)))
    m = len(next_keys)

    # Pass 2: every sample point under every action; keep those that land in L_{t+1}.
    t1 = time.perf_counter()
    trans_keys, trans_counts = [], []
    kept_total = 0
    for k, (lo, hi) in enumerate(_chunks(n, P * A)):
        reached = stepped[k] if reuse else _step_cells(system, grid, points(lo, hi), actions, cells_t[lo:hi], ties)
        rows = next_set.lookup(reached)  # [c, P, A]
        src = torch.arange(lo, hi).view(-1, 1, 1).expand_as(rows)
        act = torch.arange(A).view(1, 1, A).expand_as(rows)
        ok = rows >= 0
        kept_total += int(ok.sum())
        combined = (src[ok] * A + act[ok]) * m + rows[ok]
        k, c = torch.unique(combined, return_counts=True)
        trans_keys.append(k)
        trans_counts.append(c)
    combined = torch.cat(trans_keys).numpy()
    counts = torch.cat(trans_counts).numpy().astype(np.float64)
    src_act, dst = np.divmod(combined, m)
    src, act = np.divmod(src_act, A)
    kept = np.bincount(src_act, weights=counts, minlength=n * A)
    frac = counts / kept[src_act]
    return LevelStep(
        next_cells=next_cells.numpy(),
        src=src,
        act=act,
        dst=dst,
        frac=frac,
        kept_fraction=kept_total / float(n * P * A),
        seconds=(t1 - t0, time.perf_counter() - t1),
    )
