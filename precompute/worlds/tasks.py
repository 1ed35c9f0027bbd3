"""The navigation benchmark's tasks: the BARN maps as :class:`~precompute.worlds.suites.NavTask`, and every suite by name.

BARN (:func:`barn_tasks`): each map's cylinders become raw discs, inflated by the robot's radius; the start and
goal are the BARN Challenge's (``run.py``: start (-2.25, 3) heading +y, goal 10 m ahead), reached within 1 m,
within 100 s. The walls of a BARN map are cylinders too (three sides; the top is open toward the goal), so the
workspace bounds are only a generous box around the map and the goal that keeps a lost robot from wandering
off: (-6, -1.5) to (1.5, 15) m.

:func:`make_tasks` makes any suite's tasks (``barn``, ``forest``, ``gaps``, ``clutter``, the suites where
time matters, ``moving`` and ``sudden``: :mod:`precompute.worlds.dynamic`, and ``narrow``: passages barely wider
than the robot at staggered offsets, :func:`~precompute.worlds.suites.narrow`, driven by the faster robot
:data:`~precompute.worlds.robot.FAST_ROBOT`) and checks each one the same way
(:func:`precompute.worlds.suites.validate_task`): a start or goal in collision, or a goal that a certified flood fill cannot
reach, is a :class:`~precompute.worlds.suites.SuiteError` naming the task, raised before any episode runs.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Sequence
from typing import Any, cast

import numpy as np

from precompute.worlds.barn import CHALLENGE_GOAL, CHALLENGE_START, BarnMap, load_barn
from precompute.worlds.dynamic import SUDDEN_APPEAR, moving, sudden, sudden_position
from precompute.worlds.geometry import inflate
from precompute.worlds.suites import NavTask, SuiteError, forest, make_suite, narrow, validate_task

__all__ = ["SUITES", "CLUTTER", "SPLITS", "split_of", "BARN_BOUNDS", "GAP_OFFSETS", "RESOLUTIONS", "TIME_LIMITS",
           "barn_task", "barn_tasks", "make_tasks", "make_task", "DEFAULT_COUNTS"]

SUITES = ("barn", "forest", "gaps", "clutter", "moving", "sudden", "narrow")
"""the suites of ``python -m eval.navigate``"""
CLUTTER: dict[str, Any] = {"num_discs": (90, 120), "disc_radius": 0.5}
"""the ``clutter`` suite: the forest's corridor and rules with 90-120 discs of radius 0.5 m, 24% of the corridor
on average (the forest's 10-30 discs of 1 m: 18%), 46% once inflated by the robot's 0.2 m (overlaps counted
twice; the forest's: 26%); chosen, before any map-conditioned run, as dense enough that the best Gaussian baseline
fails often (a probe with 110-150 discs: MPPI std 1.0 succeeded 1 and 2 times in 8 at K = 64 and 256) but every
map stays reachable"""
SPLITS = ("all", "train", "test")
"""task splits (:func:`split_of`): ``all`` keeps every task"""
BARN_BOUNDS = (-6.0, -1.5, 1.5, 15.0)
"""raw workspace bounds of every BARN task (m): the map (x in [-4.5, 0], y in [0, 9.6]) and its goal, with room"""
DEFAULT_COUNTS: dict[str, int | None] = {"barn": None, "forest": 50, "gaps": 9, "clutter": 50, "moving": 50,
                                          "sudden": 20 * len(SUDDEN_APPEAR), "narrow": 50}
"""tasks per suite by default (None: every map of the file); 9 gaps: 3 widths x :data:`GAP_OFFSETS`; sudden: 20
obstacle positions (the paper's) x the appearance times"""
TIME_LIMITS = {"barn": 100.0, "forest": 120.0, "gaps": 30.0, "clutter": 120.0, "moving": 60.0, "sudden": 20.0,
               "narrow": 30.0}
"""s per episode: BARN's is the Challenge's; the forest's 120 s is 1.8x the straight drive at 0.5 m/s (33 m);
the gaps' 30 s is 2.5x theirs (6 m); moving's 60 s 1.7x its 18 m; sudden's 20 s 2.5x its 4 m; narrow's 30 s 2.4x
its 12.5 m at the fast robot's 1.0 m/s"""
GAP_OFFSETS = (0.0, 0.75, 1.5)
"""m: where the gap sits off the start-goal line (an offset gap puts a wall between the robot and its goal)"""
RESOLUTIONS = {"barn": 0.05, "forest": 0.1, "gaps": 0.02, "clutter": 0.05, "moving": 0.1, "sudden": 0.05,
               "narrow": 0.05}
"""m: flood-fill cell per suite (the gap suite's narrowest free band is 0.2 m wide for a 0.2 m robot, the narrow
suite's too: 4 cells)"""


def split_of(key: int) -> str:
    """The split of the map with ``key`` (a BARN map id, a forest, moving or narrow seed, a sudden obstacle's position):
    test when ``key % 5 == 0``, else train.
    The map-table farm (:mod:`precompute.maps.worlds`) trains on the train split only, so a benchmark run on
    ``--split test`` drives on maps no map-conditioned policy has seen."""
    return "test" if key % 5 == 0 else "train"


def barn_task(m: BarnMap, robot_radius: float, goal_tolerance: float = 1.0, time_limit: float = 100.0,
              start: tuple[float, float, float] = CHALLENGE_START,
              goal: tuple[float, float] = CHALLENGE_GOAL) -> NavTask:
    """One BARN map as a task (module docstring); not yet validated (see :func:`make_tasks`)."""
    discs = np.concatenate((m.centers.astype(np.float64), np.full((m.centers.shape[0], 1), float(m.radius))), axis=1)
    walls = np.zeros((0, 4))
    return NavTask(suite="barn", task_id=int(m.map_id), discs=discs, walls=walls, bounds=BARN_BOUNDS,
                   robot_radius=float(robot_radius), environment=inflate(discs, walls, BARN_BOUNDS, robot_radius),
                   # the signature promises 3 and 2 values; a generator's tuple loses the length
                   start=cast("tuple[float, float, float]", tuple(float(v) for v in start)),
                   goal=cast("tuple[float, float]", tuple(float(v) for v in goal)),
                   goal_tolerance=float(goal_tolerance), time_limit=float(time_limit), sensing_range=None,
                   params=dict(goal_tolerance=goal_tolerance, time_limit=time_limit))


def barn_tasks(robot_radius: float, path: str | os.PathLike | None = None, count: int | None = None,
               **kwargs: Any) -> list[NavTask]:
    """The first ``count`` (None: all) maps of the BARN file ``path`` (None: the shipped one) as tasks."""
    maps = load_barn(path)
    if count is not None:
        maps = maps[:count]
    return [barn_task(m, robot_radius, **kwargs) for m in maps]


def make_tasks(suite: str, robot_radius: float, count: int | None = None, seed: int = 0,
               barn_file: str | os.PathLike | None = None, sensing_range: float | None = 3.0,
               resolution: float | None = None, time_limits: dict[str, float] | None = TIME_LIMITS,
               split: str = "all") -> list[NavTask]:
    """The tasks of ``suite`` for a robot of ``robot_radius``, each validated (module docstring).

    ``count``: tasks (None: :data:`DEFAULT_COUNTS`); ``seed``: the first forest / moving / narrow seed, the sudden
    offsets' seed; ``split``: keep only the maps of that split (:func:`split_of` of the BARN map id, the forest,
    moving or narrow seed, the sudden obstacle's position, so every appearance time of a position is in the same split: the
    first ``count`` of them from ``seed`` / position 0 on; the gap sweep is no farm map, so all of it is ``test``
    and none ``train``); ``barn_file``: another
    BARN file in the shipped format; ``sensing_range``: the forest's (None: all obstacles known);
    ``resolution``: of the reachability flood fill (m; None: :data:`RESOLUTIONS`); ``time_limits``: per suite, overriding the suites'
    own (s; default :data:`TIME_LIMITS`, the benchmark's).
    """
    if suite not in SUITES:
        raise SuiteError(f"unknown suite {suite!r}; choose from {', '.join(SUITES)}")
    if count is None:
        count = DEFAULT_COUNTS[suite]
    if count is not None and (isinstance(count, bool) or not isinstance(count, int) or count < 1):
        raise SuiteError(f"the number of tasks must be an integer >= 1, got {count!r}")
    if split not in SPLITS:
        raise SuiteError(f"unknown split {split!r}; choose from {', '.join(SPLITS)}")
    limit: dict[str, Any] = {} if not time_limits or suite not in time_limits else {
        "time_limit": float(time_limits[suite])}
    if suite == "barn":
        tasks = barn_tasks(robot_radius, barn_file, None if split != "all" else count, **limit)
        if split != "all":
            tasks = [t for t in tasks if split_of(t.task_id) == split][:count]
    elif suite in ("forest", "clutter", "moving", "narrow"):
        assert count is not None  # only BARN's default count is None (every map)
        seeds = [s for s in range(seed, seed + 5 * count + 5) if split in ("all", split_of(s))][:count]
        tasks = [_seeded_task(suite, s, robot_radius, sensing_range, limit) for s in seeds]
    elif suite == "sudden":
        assert count is not None
        n = len(SUDDEN_APPEAR)
        positions = [p for p in range(5 * (count // n + 1) + 5) if split in ("all", split_of(p))]
        ids = [p * n + a for p in positions for a in range(n)][:count]
        tasks = [sudden(*sudden_position(i), seed=seed, robot_radius=robot_radius, **limit) for i in ids]
    else:
        assert count is not None  # only BARN's default count is None (every map)
        tasks = [] if split == "train" else make_suite("gaps", count, offsets=GAP_OFFSETS, robot_radius=robot_radius,
                                                       **limit)
    if not tasks:
        raise SuiteError(f"the {split} split of {suite} holds no task")
    for task in tasks:
        validate_task(task, resolution=resolution or RESOLUTIONS[suite])
    return tasks


def _seeded_task(suite: str, seed: int, robot_radius: float, sensing_range: float | None,
                 limit: dict[str, Any]) -> NavTask:
    """The forest, clutter, moving or narrow task of ``seed`` (``narrow`` validates itself; the others are not)."""
    if suite == "moving":
        return moving(seed, robot_radius=robot_radius, **limit)
    if suite == "narrow":
        return narrow(seed, robot_radius=robot_radius, **limit)
    shape = CLUTTER if suite == "clutter" else {}
    return dataclasses.replace(forest(seed, robot_radius=robot_radius, sensing_range=sensing_range, **shape, **limit),
                               suite=suite)


def make_task(suite: str, task_id: int, robot_radius: float, seed: int = 0,
              barn_file: str | os.PathLike | None = None, sensing_range: float | None = 3.0,
              time_limits: dict[str, float] | None = TIME_LIMITS, count: int | None = None,
              resolution: float | None = None) -> NavTask:
    """The one task ``task_id`` of ``suite``, the same as :func:`make_tasks` makes, validated the same way.

    ``task_id``: forest / clutter / moving / narrow: the seed (one of a run from ``seed`` on, so >= ``seed``); BARN: the map
    id in ``barn_file``; sudden: :func:`~precompute.worlds.dynamic.sudden_id`; gaps: the index in the
    sweep of ``count`` tasks (None: :data:`DEFAULT_COUNTS`; the sweep's
    widths depend on it, so give the run's). The other arguments are :func:`make_tasks`' (only this task is
    validated; a BARN file is read whole, the gap sweep's few walls are all made)."""
    if suite not in SUITES:
        raise SuiteError(f"unknown suite {suite!r}; choose from {', '.join(SUITES)}")
    if isinstance(task_id, bool) or not isinstance(task_id, (int, np.integer)):
        raise SuiteError(f"a task id must be an integer, got {task_id!r}")
    task_id = int(task_id)
    limit: dict[str, Any] = {} if not time_limits or suite not in time_limits else {
        "time_limit": float(time_limits[suite])}
    if suite == "barn":
        maps = {m.map_id: m for m in load_barn(barn_file)}
        if task_id not in maps:
            raise SuiteError(f"barn: no map {task_id} in {barn_file or 'the shipped BARN file'} (it holds "
                             f"{len(maps)} maps, ids {min(maps)}..{max(maps)})")
        task = barn_task(maps[task_id], robot_radius, **limit)
    elif suite in ("forest", "clutter", "moving", "narrow"):
        if task_id < seed:
            raise SuiteError(f"{suite}: task {task_id} is a seed below the run's first seed {seed}")
        task = _seeded_task(suite, task_id, robot_radius, sensing_range, limit)
    elif suite == "sudden":
        if task_id < 0:
            raise SuiteError(f"sudden: a task id must be >= 0, got {task_id}")
        task = sudden(*sudden_position(task_id), seed=seed, robot_radius=robot_radius, **limit)
    else:
        count = DEFAULT_COUNTS["gaps"] if count is None else count
        assert count is not None  # the gaps' default is a number
        if not 0 <= task_id < count:
            raise SuiteError(f"gaps: task {task_id} is not in a sweep of {count} tasks (0..{count - 1})")
        task = make_suite("gaps", count, offsets=GAP_OFFSETS, robot_radius=robot_radius, **limit)[task_id]
    validate_task(task, resolution=resolution or RESOLUTIONS[suite])
    return task


def task_summary(tasks: Sequence[NavTask]) -> dict[str, Any]:
    """A short JSON description of a task list (ids, obstacle counts), for the benchmark's record."""
    return dict(count=len(tasks), task_ids=[t.task_id for t in tasks],
                obstacles=[int(t.discs.shape[0] + t.walls.shape[0] + (len(t.moving) if t.moving is not None else 0))
                           for t in tasks])
