"""A cost-to-go for the navigation benchmark: the geodesic distance to the goal around the sensed obstacles.

The benchmark's goal term is the squared straight-line distance to the goal, whose minima sit behind every
obstacle between the robot and its goal: a pocket facing the goal is where the cost is lowest, and a controller
that avoids crashing there circles there (``python -m eval.navigate failures`` calls it *lost*). A global planner
gives a local controller a distance that knows the way; :class:`CostToGo` is that distance, computed on a grid of
``resolution`` cells over the task's bounds by Dijkstra's algorithm (scipy, 8-connected, edge length the step)
from the goal's cell through the cells whose centres are free in the robot-inflated obstacles the robot senses,
and recomputed whenever the sensed obstacles change. Unsensed space counts as free (the optimistic planner's
assumption); a cell that cannot reach the goal gets :data:`UNREACHABLE` m. Looked up at the cell holding each
point (a rollout state), it replaces the straight-line distance in
:class:`~cuniform_torch.envs.NavigationCost` (its ``goal_distance``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra
from torch import Tensor

from cuniform_torch.envs import Environment

__all__ = ["CostToGo", "geodesic_distance", "UNREACHABLE", "RESOLUTION"]

RESOLUTION = 0.1
"""m: the default cell side"""
UNREACHABLE = 1000.0
"""m: the distance given to a cell from which the goal cannot be reached (finite, so costs stay finite)"""

_STEPS = ((0, 1), (1, 0), (1, 1), (1, -1))  # (dy, dx): each undirected 8-neighbour edge once
_GROW = 3
"""cells into the obstacles that get a distance (the robot's centre may be free in a cell whose centre is not)"""


def geodesic_distance(free: np.ndarray, goal_cell: tuple[int, int], resolution: float) -> np.ndarray:
    """``free bool [H, W]`` -> ``float64 [H, W]``: the shortest 8-connected path length (m) from each free cell to
    ``goal_cell`` (row, col) through free cells; :data:`UNREACHABLE` where there is none. Occupied cells up to
    three cells from a free one get that one's distance plus the step (the others :data:`UNREACHABLE`)."""
    H, W = free.shape
    index = np.arange(H * W).reshape(H, W)
    rows, cols, lengths = [], [], []
    for dy, dx in _STEPS:
        a = index[0:H - dy, max(0, -dx):W - max(0, dx)]  # [H - dy, W - |dx|]
        b = index[dy:H, max(0, dx):W - max(0, -dx)]
        ok = free.ravel()[a.ravel()] & free.ravel()[b.ravel()]
        rows.append(a.ravel()[ok])
        cols.append(b.ravel()[ok])
        lengths.append(np.full(int(ok.sum()), resolution * math.hypot(dx, dy)))
    graph = coo_matrix((np.concatenate(lengths), (np.concatenate(rows), np.concatenate(cols))),
                       shape=(H * W, H * W)).tocsr()
    dist = dijkstra(graph, directed=False, indices=goal_cell[0] * W + goal_cell[1])
    dist[~np.isfinite(dist)] = UNREACHABLE
    dist = dist.reshape(H, W)
    dist[~free] = UNREACHABLE
    for _ in range(_GROW):  # a state just inside an occupied cell's centre may itself be free: give those cells the
        grown = dist.copy()  # distance of a free neighbour plus the step, so the cost does not jump at obstacles
        for dy, dx in _STEPS + tuple((-a, -b) for a, b in _STEPS):
            shifted = np.full_like(dist, UNREACHABLE)
            shifted[max(0, dy):H + min(0, dy), max(0, dx):W + min(0, dx)] = \
                dist[max(0, -dy):H + min(0, -dy), max(0, -dx):W + min(0, -dx)]
            grown = np.minimum(grown, np.where(shifted < UNREACHABLE, shifted + resolution * math.hypot(dx, dy),
                                               UNREACHABLE))
        dist = np.where(free, dist, grown)
    return dist


class CostToGo:
    """The geodesic distance to ``goal`` (m) around the obstacles of the environment last given to :meth:`update`
    (module docstring), on ``resolution`` cells over ``bounds`` (xmin, ymin, xmax, ymax). Call it on ``xy [..., 2]``
    (a tensor) for ``[...]`` distances (the cell's; outside the bounds, the nearest cell's)."""

    def __init__(self, bounds: Sequence[float], goal: Sequence[float], resolution: float = RESOLUTION):
        if not (isinstance(resolution, (int, float)) and math.isfinite(resolution) and resolution > 0):
            raise ValueError(f"CostToGo: resolution must be a finite number > 0, got {resolution!r}")
        self.xmin, self.ymin, xmax, ymax = (float(v) for v in bounds)
        self.resolution = float(resolution)
        self.W = max(1, math.ceil((xmax - self.xmin) / self.resolution))
        self.H = max(1, math.ceil((ymax - self.ymin) / self.resolution))
        gx = self.xmin + self.resolution * (np.arange(self.W) + 0.5)
        gy = self.ymin + self.resolution * (np.arange(self.H) + 0.5)
        mx, my = np.meshgrid(gx, gy)  # [H, W]
        self._centres = torch.from_numpy(np.stack((mx.ravel(), my.ravel()), axis=1)).float()  # [H W, 2]
        self.goal = (float(goal[0]), float(goal[1]))
        self.goal_cell = self._cell(*self.goal)
        self._key: tuple | None = None
        self.table = torch.full((self.H, self.W), UNREACHABLE)
        self.updates = 0
        """how many times the distance was recomputed"""

    def _cell(self, x: float, y: float) -> tuple[int, int]:
        col = min(self.W - 1, max(0, int((x - self.xmin) // self.resolution)))
        row = min(self.H - 1, max(0, int((y - self.ymin) // self.resolution)))
        return row, col

    def update(self, env: Environment) -> None:
        """Recompute the distance for the obstacles of ``env`` unless they are the ones of the last call."""
        key = tuple(id(obs) for obs in env.obstacles)
        if key == self._key:
            return
        free = ~env.in_collision(self._centres).numpy().reshape(self.H, self.W)
        free[self.goal_cell] = True  # the goal is free by the suites' construction; its cell may clip an obstacle
        self.table = torch.from_numpy(geodesic_distance(free, self.goal_cell, self.resolution)).float()
        self._key = key
        self.updates += 1

    def __call__(self, xy: Tensor) -> Tensor:
        """``xy [..., 2]`` -> ``[...]``: the distance at each point's cell (float32 on xy's device)."""
        col = ((xy[..., 0] - self.xmin) / self.resolution).floor().long().clamp(0, self.W - 1)
        row = ((xy[..., 1] - self.ymin) / self.resolution).floor().long().clamp(0, self.H - 1)
        table = self.table.to(xy.device)
        return table[row, col].to(xy.dtype)
