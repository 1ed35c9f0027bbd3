"""Seeded suites where time matters: discs crossing a corridor at constant velocity, and an obstacle sensed late.

Shapes used in this module: M moving discs.

:func:`moving` (DynaBARN-like): a corridor with walls like :func:`~precompute.worlds.suites.forest`'s, no
static discs, and ``M`` discs that cross it in straight lines at constant velocity
(:class:`~cuniform_torch.envs.MovingDiscs`: each position a pure function of time). Each disc crosses the
corridor's centre line at a point ``x_c`` at a time ``t_c`` drawn around the moment a robot driving straight at
``robot_speed`` reaches ``x_c``, so the discs meet the robot instead of passing before or after it. The controller
knows every disc's position and velocity at every cycle ("sensed as they are now"); the benchmark's cost
predicts them at constant velocity along each rollout's step times (:class:`~cuniform_torch.envs.NavigationCost`),
which for these straight-line discs is their true motion: what is left to decide a run is whether the sampler
finds a gap in space and time, not a wrong model of the discs. The simulator judges collisions where the discs are
at each step's true time.

:func:`sudden` (the paper's sudden obstacle, on the benchmark robot): the goal 4 m straight ahead, a disc on the
way at a seeded lateral offset, sensed only from its ``appear_time`` (:class:`~cuniform_torch.envs.Circle`), one
task per (position, appearance time).

Both are checked when made, like every suite: the start and goal are free at t = 0 and the goal is reachable at
t = 0 (:func:`~precompute.worlds.suites.validate_task`). A moving task is checked more: no disc's line
ever comes within ``start_clearance`` of the start or goal (so neither is ever hit), and the corridor is open
(certified flood fill) in the snapshots at ``0, check_every, 2 check_every, ...`` s up to the time limit; a draw
that fails is redrawn (``NavTask.attempt``). Open snapshots do not prove that a robot of this speed can get
through (a space-time search would); they rule out a corridor walled off at some moment.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from cuniform_torch.envs import Environment, MovingDiscs
from precompute.worlds.geometry import SuiteError, inflate, reachable
from precompute.worlds.suites import MAX_ATTEMPTS, NavTask, _int, _num, _range, disc_count_range, validate_task

__all__ = ["moving", "sudden", "SUDDEN_APPEAR", "sudden_id", "sudden_position"]

SUDDEN_APPEAR = (0.0, 1.5, 2.0, 2.2, 2.4)
"""s: the sudden suite's appearance times. Driving straight at 0.5 m/s, the benchmark robot (radius 0.2 m) would
touch a centred disc (0.5 m at x = 2 m) at x = 1.3 m, 2.6 s after the start; it turns at up to 1.5 rad/s (a 0.33 m
radius), so an obstacle sensed a second before that is still easy: the times crowd the last half second"""


def _line_distance(points: np.ndarray, through: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """``points [2, 2]`` and lines ``through [n, 2]`` along unit ``direction [n, 2]`` -> ``[n]``: each line's distance
    to the nearer point."""
    rel = points[None, :, :] - through[:, None, :]  # [n, 2, 2]
    cross = rel[..., 0] * direction[:, None, 1] - rel[..., 1] * direction[:, None, 0]  # [n, 2]
    return np.abs(cross).min(axis=1)


def moving(seed: int, length: float = 20.0, width: float = 6.0, num_discs: tuple[int, int] = (20, 25),
           disc_radius: tuple[float, float] = (0.3, 0.6), disc_speed: tuple[float, float] = (0.3, 0.8),
           max_angle: float = 30.0, robot_speed: float = 0.5, crossing_jitter: float = 2.0,
           robot_radius: float = 0.25, start_clearance: float = 0.5, goal_tolerance: float = 0.5,
           time_limit: float = 60.0, resolution: float = 0.1, check_every: float = 2.0) -> NavTask:
    """A corridor ``[0, length] x [-width/2, width/2]`` (walls and bounds as :func:`forest`'s; start ``(1, 0, 0)``,
    goal ``(length - 1, 0)``) crossed by ``n`` moving discs, ``n`` uniform in ``num_discs`` (ends included).

    Disc ``m``: radius uniform in ``disc_radius`` (m), speed uniform in ``disc_speed`` (m/s), heading across the
    corridor (+y or -y, even odds) turned by an angle uniform in ``[-max_angle, max_angle]`` degrees; it crosses
    ``y = 0`` at ``x_c`` uniform in ``[3, length - 3]`` at ``t_c = (x_c - 1) / robot_speed + U(-crossing_jitter,
    crossing_jitter)`` s. A disc whose line comes within ``radius + robot_radius + start_clearance`` of the start or
    goal is redrawn. Draw ``k`` uses ``numpy.random.default_rng([seed, k])``; draw 0 is kept unless a snapshot
    every ``check_every`` s up to ``time_limit`` is walled off (module docstring), then 1, 2, ... Raises
    :class:`SuiteError` for bad parameters or after :data:`MAX_ATTEMPTS` closed draws."""
    who = "moving"
    seed = _int(seed, "seed", who)
    if seed < 0:
        raise SuiteError(f"{who}: seed must be >= 0, got {seed}")
    L, Wd = _num(length, "length", who), _num(width, "width", who)
    r = _num(robot_radius, "robot_radius", who, positive=False)
    r_lo, r_hi = _range(disc_radius, "disc_radius", who)
    s_lo, s_hi = _range(disc_speed, "disc_speed", who, positive=False)
    angle = math.radians(_num(max_angle, "max_angle", who, positive=False))
    if angle >= math.pi / 2:
        raise SuiteError(f"{who}: max_angle must be below 90 degrees (the discs cross the corridor), got {max_angle}")
    v_robot, jitter = _num(robot_speed, "robot_speed", who), _num(crossing_jitter, "crossing_jitter", who, False)
    clear, every = _num(start_clearance, "start_clearance", who), _num(check_every, "check_every", who)
    limit = _num(time_limit, "time_limit", who)
    lo, hi = disc_count_range(num_discs, who)
    if not L > 6.0:
        raise SuiteError(f"{who}: length ({L}) must exceed 6 m (the discs cross within [3, length - 3])")
    if not Wd > 2 * r:
        raise SuiteError(f"{who}: width ({Wd}) must exceed 2 x robot_radius ({2 * r})")
    start, goal = (1.0, 0.0, 0.0), (L - 1.0, 0.0)
    walls = np.array([[0.0, Wd / 2, L, Wd / 2 + 0.2], [0.0, -Wd / 2 - 0.2, L, -Wd / 2]])  # [2, 4], forest's
    bounds = (0.0, -Wd / 2, L, Wd / 2)
    anchors = np.array([start[:2], goal])  # [2, 2]
    static = inflate(np.zeros((0, 3)), walls, bounds, r)
    times = np.arange(0.0, limit + 1e-9, every)  # the snapshots checked
    params = dict(length=L, width=Wd, num_discs=(lo, hi), disc_radius=(r_lo, r_hi), disc_speed=(s_lo, s_hi),
                  max_angle=float(max_angle), robot_speed=v_robot, crossing_jitter=jitter, robot_radius=r,
                  start_clearance=clear, goal_tolerance=goal_tolerance, time_limit=limit, resolution=resolution,
                  check_every=every)
    for attempt in range(MAX_ATTEMPTS):
        rng = np.random.default_rng([seed, attempt])
        n = int(rng.integers(lo, hi, endpoint=True))
        rows = np.empty((0, 5))  # (x_c, t_c, radius, vx, vy) of the discs kept
        while rows.shape[0] < n:
            m = 2 * n
            xc = rng.uniform(3.0, L - 3.0, m)
            rad = rng.uniform(r_lo, r_hi, m)
            speed = rng.uniform(s_lo, s_hi, m)
            turn = rng.uniform(-angle, angle, m)
            side = np.where(rng.random(m) < 0.5, -1.0, 1.0)
            tc = (xc - start[0]) / v_robot + rng.uniform(-jitter, jitter, m)
            direction = np.stack((np.sin(turn), side * np.cos(turn)), axis=1)  # [m, 2] unit
            through = np.stack((xc, np.zeros(m)), axis=1)  # [m, 2]
            far = _line_distance(anchors, through, direction) > rad + r + clear  # [m]
            cand = np.column_stack((xc, tc, rad, speed[:, None] * direction))  # [m, 5]
            rows = np.concatenate((rows, cand[far]))[:n]
        velocity = rows[:, 3:5]  # [n, 2]
        centre0 = np.stack((rows[:, 0], np.zeros(n)), axis=1) - velocity * rows[:, 1:2]  # [n, 2] at t = 0
        raw = MovingDiscs(torch.from_numpy(centre0), torch.from_numpy(velocity.copy()), torch.from_numpy(rows[:, 2].copy()))
        environment = Environment(static.obstacles, bounds=static.bounds, moving=raw.inflated(r))
        task = NavTask(
            suite="moving", task_id=seed, discs=np.zeros((0, 3)), walls=walls, bounds=bounds, robot_radius=r,
            environment=environment, start=start, goal=goal,
            goal_tolerance=_num(goal_tolerance, "goal_tolerance", who, positive=False), time_limit=limit,
            sensing_range=None, attempt=attempt, params=params, moving=raw,
        )
        validate_task(task, check_reachable=False)  # never fails by construction; a clear error if it does
        if all(reachable(environment.snapshot(float(t)), start[:2], goal, resolution) for t in times):
            return task
    raise SuiteError(f"{who}: seed {seed}: every one of {MAX_ATTEMPTS} draws is walled off at some moment "
                     f"(num_discs {num_discs}, width {Wd}, disc_radius {disc_radius}, robot_radius {r})")


def sudden_id(position: int, appear_index: int, appear: tuple[float, ...] = SUDDEN_APPEAR) -> int:
    """The task id of obstacle ``position`` sensed at ``appear[appear_index]``: ``position * len(appear) +
    appear_index`` (the tasks of one position are consecutive)."""
    return int(position) * len(appear) + int(appear_index)


def sudden_position(task_id: int, appear: tuple[float, ...] = SUDDEN_APPEAR) -> tuple[int, int]:
    """``(position, appear_index)`` of a task id (:func:`sudden_id`'s inverse)."""
    return int(task_id) // len(appear), int(task_id) % len(appear)


def sudden(position: int, appear_index: int, seed: int = 0, appear: tuple[float, ...] = SUDDEN_APPEAR,
           goal_distance: float = 4.0, obstacle_x: float = 2.0, disc_radius: float = 0.5, half_width: float = 2.5,
           robot_radius: float = 0.25, goal_tolerance: float = 0.3, time_limit: float = 20.0,
           resolution: float = 0.05) -> NavTask:
    """Start ``(0, 0, 0)``, goal ``(goal_distance, 0)``, one disc of ``disc_radius`` at ``(obstacle_x, y)``,
    ``y`` uniform in ``[-disc_radius, disc_radius]`` from ``numpy.random.default_rng([seed, position])`` (the
    paper's rule), sensed from ``appear[appear_index]`` s on; bounds ``[-1, goal_distance + 1] x [-half_width,
    half_width]``. Task id :func:`sudden_id`. The disc is physically there from the start: only the cost's view
    of it waits (:meth:`~cuniform_torch.envs.Environment.visible`)."""
    who = "sudden"
    position, index = _int(position, "position", who), _int(appear_index, "appear_index", who)
    seed = _int(seed, "seed", who)
    if position < 0 or seed < 0:
        raise SuiteError(f"{who}: position and seed must be >= 0, got {position} and {seed}")
    times = tuple(_num(t, "an appearance time", who, positive=False) for t in appear)
    if not 0 <= index < len(times):
        raise SuiteError(f"{who}: appear_index {index} is not one of the {len(times)} appearance times {times}")
    D, X = _num(goal_distance, "goal_distance", who), _num(obstacle_x, "obstacle_x", who)
    R, hw = _num(disc_radius, "disc_radius", who), _num(half_width, "half_width", who)
    r = _num(robot_radius, "robot_radius", who, positive=False)
    if not 0 < X < D:
        raise SuiteError(f"{who}: obstacle_x ({X}) must lie between the start (0) and the goal ({D})")
    offset = float(np.random.default_rng([seed, position]).uniform(-R, R))
    discs = np.array([[X, offset, R]])  # [1, 3]
    bounds = (-1.0, -hw, D + 1.0, hw)
    env = inflate(discs, np.zeros((0, 4)), bounds, r)
    circle = env.obstacles[0]
    environment = Environment([type(circle)(circle.center, circle.radius, appear_time=times[index])],
                              bounds=env.bounds)
    task = NavTask(
        suite="sudden", task_id=sudden_id(position, index, times), discs=discs, walls=np.zeros((0, 4)),
        bounds=bounds, robot_radius=r, environment=environment, start=(0.0, 0.0, 0.0), goal=(D, 0.0),
        goal_tolerance=_num(goal_tolerance, "goal_tolerance", who, positive=False),
        time_limit=_num(time_limit, "time_limit", who), sensing_range=None,
        params=dict(position=position, appear=times[index], offset=offset, goal_distance=D, obstacle_x=X,
                    disc_radius=R, half_width=hw, robot_radius=r, goal_tolerance=goal_tolerance,
                    time_limit=time_limit),
    )
    validate_task(task, resolution=resolution)
    return task
