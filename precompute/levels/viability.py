"""Viable safe level sets: the cells from which some trajectory stays collision-free to the horizon.

Pruning each level forward (the cells whose centre lies in an inflated obstacle) leaves *dead ends*: free cells
of L_t every one of whose successors is blocked. The max-flow of L_{t-1} -> L_t still makes L_t uniform, so it
sends trajectories into them, and they all collide at the next step (on a wall ahead, more than half of a
forward-pruned table's rollouts did). :func:`viable_levels` removes them: a forward pass builds the safe levels,
a backward pass keeps a cell of L_t only if one of its transitions lands in a kept cell of L_{t+1}
(L_T: every safe cell). The table is then built on these sets (:func:`viable_keep` gives the builder's per-step
``keep``), so every cell of every level has a collision-free continuation to the horizon.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch
from torch import Tensor

from cuniform_torch.systems import System
from precompute.levels.safe_map import MapError, SafeCells
from precompute.levels.sets import EmptyLevelError, PointMode, TieRule, next_level

__all__ = ["SAFE_RULE", "viable_levels", "viable_keep", "step_generator"]

SAFE_RULE = "viable"
"""the pruning rule of a map build, recorded in its settings: cells without a collision-free continuation removed"""


def step_generator(points: PointMode, seed: int, t: int) -> torch.Generator | None:
    """The per-step stream of the random point mode (the builder's: resumable per step), None otherwise."""
    if points is not PointMode.RANDOM:
        return None
    return torch.Generator().manual_seed(seed * 1_000_003 + t)


def viable_levels(system: System, start_cells: np.ndarray, horizon: int, safe: SafeCells, points: PointMode,
                  points_per_cell: int, seed: int, ties: TieRule) -> list[np.ndarray]:
    """The viable cells ``[n_t, d]`` int64 of every level t = 0..T (module docstring); MapError when the start
    itself has no collision-free trajectory of ``horizon`` steps."""
    levels, steps = [np.ascontiguousarray(start_cells)], []
    for t in range(horizon):
        try:
            step = next_level(system, levels[-1], points, points_per_cell, step_generator(points, seed, t), ties,
                              keep=safe.keep)
        except EmptyLevelError:
            raise MapError(f"the map leaves no free cell at level {t + 1}: every cell reachable in {t + 1} step(s) "
                           f"lies within --radius {safe.radius:g} m of an obstacle (the start is boxed in)") from None
        steps.append(step)
        levels.append(step.next_cells)
    alive = np.ones(len(levels[-1]), dtype=bool)
    masks = [alive]
    for t in range(horizon - 1, -1, -1):  # a cell lives when one of its transitions lands on a living cell
        step = steps[t]
        lands = alive[step.dst]
        alive = np.zeros(len(levels[t]), dtype=bool)
        alive[step.src[lands]] = True
        masks.append(alive)
        if not alive.any():
            raise MapError(f"every trajectory from the start meets an obstacle (within --radius {safe.radius:g} m) "
                           f"by step {horizon}: no cell of level {t} has a collision-free continuation")
    masks.reverse()
    return [cells[mask] for cells, mask in zip(levels, masks)]


def _packer(*arrays: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
    """One int64 key per cell row, by mixed radix over the bounding box of ``arrays`` (rows ``[n, d]``)."""
    stacked = np.concatenate([a.reshape(-1, a.shape[-1]) for a in arrays])
    lo, span = stacked.min(axis=0), np.ptp(stacked, axis=0) + 1
    radix = np.concatenate(([1], np.cumprod(span[:-1]))).astype(np.int64)
    return lambda cells: (cells - lo) @ radix


def viable_keep(safe: SafeCells, viable_next: np.ndarray) -> Callable[[Tensor], Tensor]:
    """The builder's ``keep`` for the step into a level whose viable cells are ``viable_next [m, d]``: safe and
    viable (``cells [n, d]`` int64 tensor -> bool ``[n]``)."""

    def keep(cells: Tensor) -> Tensor:
        free = safe.keep(cells)
        arr = cells.numpy()
        pack = _packer(arr, viable_next)
        return free & torch.from_numpy(np.isin(pack(arr), pack(viable_next)))

    return keep
