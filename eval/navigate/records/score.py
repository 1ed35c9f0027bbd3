"""The BARN Challenge's navigation score of an episode, from its record (success, time) and its task's reference length.

The Challenge's ``run.py`` scores an episode ``success * OT / clip(time, 2 OT, 8 OT)``, with the optimal time ``OT``
the reference path's length over 2 m/s (the Jackal's top speed): at most 0.5 (a run in 2 OT or less), 1/8 for a
success in 8 OT or more, 0 for a failure. Its reference path is the polyline from the start through the map's A*
path (the dataset's ``path_<id>.npy``, in grid cells) to the goal, the cells converted to metres as its
``path_coord_to_gazebo_coord`` does: ``x = 0.15 c - 4.575``, ``y = 0.15 r + 5.075`` (0.15 m cells: two cylinder
radii; the grid's origin 30 cells left of x = -0.075, 5 m up from y = 0.075). The converted paths of the shipped maps
keep 0.30-0.46 m from every cylinder centre (with the cell's two coordinates swapped they would hit cylinders).

What differs from the Challenge: our robot drives at 0.5 m/s (the Challenge's Jackal up to 2 m/s), so a perfect run
on the reference path takes 4 OT and scores 0.25; the simulator is ours (a unicycle, no Gazebo physics). The score
still ranks episodes as the Challenge does: a success that takes a longer way scores less.

This is the arithmetic, on numbers and arrays only (no torch, no worlds): :func:`barn_score` of one episode,
:func:`score_summary` of a cell's scores. The reference lengths of a folder's tasks (rebuilding each world) are
:mod:`eval.navigate.score`'s.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

__all__ = ["CHALLENGE_SPEED", "BARN_CELL", "BARN_ORIGIN", "barn_path_xy", "polyline_length",
           "barn_reference_length", "barn_score", "score_summary"]

CHALLENGE_SPEED = 2.0
"""m/s: the Challenge's optimal time is the reference length over this"""
BARN_CELL = 0.15
"""m: a BARN grid cell (two cylinder radii of 0.075 m)"""
BARN_ORIGIN = (-0.075 - 30 * BARN_CELL, 0.075 + 5.0)
"""(x, y) in m of grid cell (0, 0): the Challenge's ``r_shift``, ``c_shift``"""


def barn_path_xy(cells: np.ndarray) -> np.ndarray:
    """``[P, 2]`` grid cells (the dataset's path file) -> ``[P, 2]`` float64 metres (the Challenge's conversion)."""
    cells = np.asarray(cells, dtype=np.float64).reshape(-1, 2)
    return np.stack((cells[:, 0] * BARN_CELL + BARN_ORIGIN[0], cells[:, 1] * BARN_CELL + BARN_ORIGIN[1]), axis=1)


def polyline_length(points: np.ndarray) -> float:
    """The length (m) of the polyline through ``points [P, 2]``."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    return float(np.linalg.norm(np.diff(points, axis=0), axis=1).sum())


def barn_reference_length(cells: np.ndarray, start: Sequence[float], goal: Sequence[float]) -> float:
    """The Challenge's reference length (m): start -> the map's path (``cells [P, 2]``, converted) -> goal."""
    path = barn_path_xy(cells)
    return polyline_length(np.concatenate(([np.asarray(start[:2], float)], path, [np.asarray(goal[:2], float)])))


def barn_score(success: bool, time: float, reference_length: float) -> float:
    """``success * OT / clip(time, 2 OT, 8 OT)``, ``OT = reference_length / 2`` (m/s): in [0, 0.5]."""
    if not (math.isfinite(reference_length) and reference_length > 0):
        raise ValueError(f"the reference length must be a finite number > 0 (m), got {reference_length!r}")
    if not (math.isfinite(time) and time >= 0):
        raise ValueError(f"an episode's time must be a finite number >= 0 (s), got {time!r}")
    ot = reference_length / CHALLENGE_SPEED
    return float(bool(success)) * ot / min(max(time, 2 * ot), 8 * ot)


def score_summary(values: Sequence[float]) -> dict[str, float | None]:
    """``score_mean`` and its 95% interval ``score_low`` / ``score_high`` (normal approximation, within [0, 0.5])
    of a cell's episode scores; all None without any."""
    n = len(values)
    if n == 0:
        return dict(score_mean=None, score_low=None, score_high=None)
    mean = float(np.mean(values))
    half = 1.96 * float(np.std(values, ddof=1)) / math.sqrt(n) if n > 1 else 0.0
    top = 0.5
    return dict(score_mean=mean, score_low=max(0.0, mean - half), score_high=min(top, mean + half))
