"""The worlds of the map-table farm: which maps a split holds, free start poses, and local map patches.

Shapes: M discs, W wall rectangles, H x W patch cells, P candidate poses.

Maps by suite (each has an integer key; the source string names it):

* ``barn``: the shipped BARN maps (``precompute/worlds/data/barn_train.npz``), key = the BARN world id, ``barn:<id>``.
* ``forest``: :func:`precompute.worlds.suites.forest` of seed = key, every obstacle known, ``forest:seed=<key>``.
* ``clutter``: the same with the benchmark's clutter density (:data:`precompute.worlds.tasks.CLUTTER`), ``clutter:seed=<key>``.
* ``gaps``: :func:`precompute.worlds.suites.gaps` with width uniform in [0.6, 1.2] m and offset uniform in [-1.5, 1.5] m drawn
  from ``numpy.random.default_rng(key)``, ``gaps:seed=<key>``.

Split rule: a map is in the test split when its key is divisible by 5 (:func:`precompute.worlds.tasks.split_of`, the
benchmark's ``--split``), else in train, for
every suite and every ``--seed``, so the two splits never share a map. ``--seed`` picks which maps of the split
(BARN: a seeded permutation of the split's maps; forest, clutter, gaps: keys drawn from ``default_rng(seed)``) and the
start poses (``default_rng([seed, key])``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from precompute.worlds.barn import load_barn
from precompute.worlds.geometry import clearance, inflate
from precompute.worlds.suites import forest, gaps
from precompute.worlds.tasks import CLUTTER, split_of

__all__ = ["FARM_SUITES", "SPLITS", "World", "split_of", "suite_worlds", "world_of", "crop_patch", "candidate_poses"]

SPLITS = ("train", "test")
FARM_SUITES = ("barn", "forest", "gaps", "clutter")
"""the suites whose maps the farm crops (module docstring)"""
_KEY_RANGE = 1 << 31
_GAP_WIDTHS = (0.6, 1.2)
_GAP_OFFSET = 1.5


@dataclass(frozen=True, eq=False)
class World:
    """One map: raw obstacles (not inflated), bounds, and the box its start poses are drawn from."""

    suite: str
    key: int
    source: str
    discs: np.ndarray  # [M, 3] (x, y, radius)
    walls: np.ndarray  # [W, 4] (xmin, ymin, xmax, ymax)
    bounds: tuple[float, float, float, float] | None
    region: tuple[float, float, float, float]


def _barn_world(m, radius: float) -> World:
    discs = np.concatenate((m.centers.astype(np.float64), np.full((len(m.centers), 1), float(m.radius))), axis=1)
    lo, hi = m.centers.min(axis=0).astype(float), m.centers.max(axis=0).astype(float)
    return World("barn", int(m.map_id), f"barn:{int(m.map_id)}", discs, np.zeros((0, 4)), None,
                 (lo[0], lo[1], hi[0], hi[1]))


def _task_world(suite: str, key: int, radius: float) -> World:
    if suite in ("forest", "clutter"):
        task = forest(key, robot_radius=radius, sensing_range=None, **(CLUTTER if suite == "clutter" else {}))
    else:
        rng = np.random.default_rng(key)
        width, offset = rng.uniform(*_GAP_WIDTHS), rng.uniform(-_GAP_OFFSET, _GAP_OFFSET)
        task = gaps(width=float(width), offset=float(offset), robot_radius=radius, task_id=key)
    return World(suite, key, f"{suite}:seed={key}", task.discs, task.walls, task.bounds, task.bounds)


def suite_worlds(suite: str, count: int, split: str, seed: int, radius: float) -> list[World]:
    """``count`` maps of ``suite`` in ``split`` (module docstring); ValueError when the split has fewer."""
    if split not in SPLITS:
        raise ValueError(f"--split must be train or test, got {split!r}")
    if suite == "barn":
        maps = [m for m in load_barn() if split_of(int(m.map_id)) == split]
        if count > len(maps):
            raise ValueError(f"--count {count}: the BARN {split} split has only {len(maps)} maps")
        order = np.random.default_rng(seed).permutation(len(maps))[:count]
        return [_barn_world(maps[i], radius) for i in order.tolist()]
    if suite not in FARM_SUITES:
        raise ValueError(f"--suite must be one of {', '.join(FARM_SUITES)}, got {suite!r}")
    rng, keys = np.random.default_rng(seed), []
    while len(keys) < count:
        for key in rng.integers(0, _KEY_RANGE, size=4 * count).tolist():
            if split_of(key) == split and key not in keys and len(keys) < count:
                keys.append(key)
    return [_task_world(suite, key, radius) for key in keys]


def world_of(suite: str, key: int, radius: float) -> World:
    """The map of ``suite`` with ``key`` (a farm job rebuilds its world from these)."""
    if suite == "barn":
        for m in load_barn():
            if int(m.map_id) == key:
                return _barn_world(m, radius)
        raise ValueError(f"no BARN map with id {key} in the shipped file")
    return _task_world(suite, key, radius)


def _occupied(world: World, xy: np.ndarray, reach: float) -> np.ndarray:
    """``xy [P, 2]`` world points -> bool ``[P]``: inside a raw obstacle or outside the bounds."""
    hit = np.zeros(len(xy), dtype=bool)
    centre = xy.mean(axis=0)
    discs = world.discs[np.hypot(*(world.discs[:, :2] - centre).T) <= reach + world.discs[:, 2]]
    if len(discs):
        d2 = ((xy[:, None, :] - discs[None, :, :2]) ** 2).sum(axis=2)  # [P, M]
        hit |= (d2 < discs[None, :, 2] ** 2).any(axis=1)
    for x0, y0, x1, y1 in world.walls.tolist():  # a handful of walls per map
        hit |= (xy[:, 0] >= x0) & (xy[:, 0] <= x1) & (xy[:, 1] >= y0) & (xy[:, 1] <= y1)
    if world.bounds is not None:
        x0, y0, x1, y1 = world.bounds
        hit |= (xy[:, 0] < x0) | (xy[:, 0] > x1) | (xy[:, 1] < y0) | (xy[:, 1] > y1)
    return hit


def crop_patch(world: World, pose: np.ndarray, shape: tuple[int, int], resolution: float,
               origin: tuple[float, float]) -> np.ndarray:
    """The local map ``uint8 [H, W]`` in the robot frame of ``pose [3]`` (robot at the origin heading +x): cell
    (i, j) is occupied when its centre, taken to the world, lies in a raw obstacle or outside the bounds."""
    H, W = shape
    px = origin[0] + (np.arange(W) + 0.5) * resolution
    py = origin[1] + (np.arange(H) + 0.5) * resolution
    gx, gy = np.meshgrid(px, py)  # [H, W]: row i is y, column j is x
    c, s = math.cos(pose[2]), math.sin(pose[2])
    xy = np.stack((pose[0] + c * gx - s * gy, pose[1] + s * gx + c * gy), axis=-1).reshape(-1, 2)
    reach = math.hypot(max(abs(origin[0]), abs(origin[0] + W * resolution)),
                       max(abs(origin[1]), abs(origin[1] + H * resolution)))
    return _occupied(world, xy, reach).reshape(H, W).astype(np.uint8)


def candidate_poses(world: World, rng: np.random.Generator, radius: float, margin: float,
                    batch: int = 256) -> np.ndarray:
    """``[P, 3]`` poses drawn uniformly in the world's region (heading uniform in [-pi, pi)), kept where the
    robot's disc clears every obstacle and bound by more than ``margin``."""
    x0, y0, x1, y1 = world.region
    xy = np.stack((rng.uniform(x0, x1, batch), rng.uniform(y0, y1, batch)), axis=1)
    theta = rng.uniform(-math.pi, math.pi, batch)
    env = inflate(world.discs, world.walls, world.bounds or (x0 - 10, y0 - 10, x1 + 10, y1 + 10), radius)
    ok = clearance(env, xy) > margin
    return np.concatenate((xy, theta[:, None]), axis=1)[ok]
