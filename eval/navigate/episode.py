"""One navigation episode: a method with a sample budget on one task, under one controller seed.

:func:`run_nav_episode` is a pure function of its arguments (a :class:`NavJob` and a :class:`NavContext`, both
small and picklable), so the serial, process-pool and Ray executors (:mod:`eval.navigate.execute`) give the same record
for the same job. Every process keeps what it loaded (the files of the methods' sources, the rasterized maps)
in a per-process cache. Torch runs with one CPU thread per episode in every mode: the same arithmetic in every
executor, and one episode per core is what parallel runs use anyway.

The cost is the same for every method: :class:`cuniform_torch.envs.NavigationCost` (squared distance to the
goal + ``collision_penalty`` for every colliding rollout state, both ending at the rollout's first arrival at
the goal). The obstacles it sees:

* a task with a sensing range (forest): the obstacles sensed at the robot's position, updated before every
  control cycle (:meth:`precompute.worlds.suites.NavTask.sensed_environment`);
* a static map with more than :data:`RASTER_MIN_OBSTACLES` obstacles (BARN: 181-365 cylinders): the inflated
  map rasterized once into an :class:`~cuniform_torch.envs.OccupancyGrid` of ``cost_resolution`` cells, a
  cell occupied when any of its points may be inside an obstacle (its centre's clearance is below half the
  cell's diagonal). Conservative by at most ``cost_resolution * sqrt(2)`` (1.4 cm at the default 1 cm), and
  a cost evaluation costs one gather instead of one test per cylinder;
* otherwise the task's inflated environment as it is.

The cost is told the time before every control cycle (:func:`cuniform_torch.envs.simulate`'s ``cost``): an
obstacle with an ``appear_time`` (the sudden suite) enters it then, and moving discs (the moving suite) are
tested where they will be at each rollout step's time (``dt``: the robot's step), their true constant-velocity
motion (:mod:`precompute.worlds.dynamic`).

Collisions are always judged on the exact inflated geometry (:func:`cuniform_torch.envs.simulate`).
"""

from __future__ import annotations

import hashlib
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from cuniform_torch.envs import Environment, NavigationCost, OccupancyGrid, simulate
from eval.common.methods import NAVIGATE, Sources, make_controller, methods_of
from eval.navigate.cost_to_go import CostToGo
from eval.navigate.dynamics import DYNAMICS, LearnedSources
from eval.navigate.records.cycle_hist import cycle_histogram
from eval.navigate.records.keys import episode_key
from precompute.worlds.geometry import inflate, obstacle_tables
from precompute.worlds.suites import NavTask

__all__ = ["NavJob", "NavContext", "run_nav_episode", "rasterize", "RASTER_MIN_OBSTACLES", "navigation_cost", "context_sources", "cost_environment", "sources_and_simulator",
           "start_state", "sensed_world"]

RASTER_MIN_OBSTACLES = 32
"""a static map with more obstacles than this is rasterized for the cost (module docstring)"""


@dataclass(frozen=True)
class NavJob:
    """One episode to run."""

    task: NavTask
    method: str
    """key of :data:`eval.common.methods.METHODS` of the navigation benchmark"""
    budget: int
    """K: trajectories per control cycle"""
    seed: int
    """controller seed: the same for every method and budget on the same task and repeat (paired runs)"""
    repeat: int = 0
    """which controller seed of the task (0 .. repeats - 1)"""

    @property
    def key(self) -> str:
        return episode_key(self.task.suite, self.task.task_id, self.method, self.budget, self.repeat)


@dataclass(frozen=True)
class NavContext:
    """What every episode of a run shares: the source files, the horizon and the cost's settings."""

    table: str
    """the robot's max-flow table (also the system of every method)"""
    coverage_table: str | None = None
    policy: str | None = None
    map_policy: str | None = None
    horizon: int = 15
    lambda_: float = 0.567
    collision_penalty: float = 1e6
    cost_resolution: float = 0.01
    """m: cell side of the rasterized cost map of large static maps"""
    record_path: bool = False
    """keep the driven path ``[[x, y], ...]`` in the record"""
    cost_to_go: float | None = None
    """m: the goal term's geodesic cost-to-go on cells of this side (:mod:`eval.navigate.cost_to_go`); None: the straight
    line"""
    dynamics: str = "true"
    """what the controllers plan with (:mod:`eval.navigate.dynamics`): ``true`` (the robot's) or ``learned`` (an MLP of
    it); the simulator steps the robot's own in both"""


_CACHE: dict[Any, Any] = {}


def context_sources(ctx: NavContext) -> Sources:
    """The methods' sources (tables, policies, the robot) of ``ctx``, loaded once per process."""
    key = ("sources", ctx.table, ctx.coverage_table, ctx.policy, ctx.map_policy, ctx.dynamics)
    if key not in _CACHE:
        if ctx.dynamics not in DYNAMICS:
            raise ValueError(f"unknown dynamics {ctx.dynamics!r}; choose from {', '.join(DYNAMICS)}")
        kind = LearnedSources if ctx.dynamics == "learned" else Sources
        _CACHE[key] = kind(table=Path(ctx.table), coverage_table=Path(ctx.coverage_table or ctx.table),
                              policy=Path(ctx.policy or ctx.table),
                              map_policy=Path(ctx.map_policy) if ctx.map_policy else None, device="cpu")
    return _CACHE[key]


def rasterize(environment: Environment, resolution: float) -> Environment:
    """The obstacles of ``environment`` as one conservative :class:`OccupancyGrid` of ``resolution`` cells over
    its bounds (module docstring), with the same bounds. Needs bounds.

    Each obstacle marks the cells of its own bounding box widened by the margin (all obstacles of a kind at once,
    in boxes padded to the largest), with the distance arithmetic of
    :func:`~precompute.worlds.geometry.clearance`: the same raster as testing every cell against every
    obstacle, for the cells near an obstacle only (a BARN map: ~1 M distances instead of ~150 M)."""
    if environment.bounds is None:
        raise ValueError("rasterize: the environment needs bounds")
    xmin, ymin, xmax, ymax = environment.bounds
    h = float(resolution)
    W, H = math.ceil((xmax - xmin) / h), math.ceil((ymax - ymin) / h)
    xs = xmin + h * (np.arange(W) + 0.5)  # [W] cell centres
    ys = ymin + h * (np.arange(H) + 0.5)  # [H]
    margin = h * math.sqrt(0.5)  # a cell is occupied when its centre's clearance is below this
    circles, rects = obstacle_tables(Environment(environment.obstacles))  # [C, 3], [R, 4]
    occupied = np.zeros((H, W), dtype=bool)
    boxes = np.concatenate([circles[:, :2] - circles[:, 2:3], rects[:, :2]]), \
        np.concatenate([circles[:, :2] + circles[:, 2:3], rects[:, 2:]])  # [C + R, 2] each: lower, upper corners
    if len(boxes[0]):
        lo = np.floor((boxes[0] - margin - (xmin, ymin)) / h - 0.5).astype(np.int64) - 1  # [K, 2] first cells
        hi = np.ceil((boxes[1] + margin - (xmin, ymin)) / h - 0.5).astype(np.int64) + 1  # [K, 2] last cells
        kind = np.arange(len(lo)) >= len(circles)  # [K] True: a rect
        size = np.prod(hi - lo + 1, axis=1)  # [K] cells of each box
        order = np.lexsort((size, kind))  # by kind, then size: chunks of similar boxes pad little
        start = 0
        while start < len(order):  # chunks of at most _RASTER_CHUNK padded cells bound the memory
            stop = start + 1
            while stop < len(order) and kind[order[stop]] == kind[order[start]] \
                    and (stop + 1 - start) * size[order[stop]] <= _RASTER_CHUNK:
                stop += 1
            _mark_boxes(occupied, order[start:stop], lo, hi, circles, rects, xs, ys, margin)
            start = stop
    grid = OccupancyGrid(torch.from_numpy(occupied), origin=(xmin, ymin), resolution=h)
    return Environment([grid], bounds=environment.bounds, moving=environment.moving)


_RASTER_CHUNK = 1 << 22
"""padded box cells rasterized at once (a bound on the temporaries: ~100 MB)"""


def _mark_boxes(occupied: np.ndarray, ks: np.ndarray, lo: np.ndarray, hi: np.ndarray, circles: np.ndarray,
                rects: np.ndarray, xs: np.ndarray, ys: np.ndarray, margin: float) -> None:
    """Mark in ``occupied [H, W]`` the cells of the boxes ``lo[ks]..hi[ks]`` whose centre is within ``margin`` of
    obstacle ``k`` (circles first, then rects, in :func:`obstacle_tables` order); one kind per call."""
    H, W = occupied.shape
    C = len(circles)
    span = (hi[ks] - lo[ks]).max(axis=0) + 1  # [2] the padded box, x and y
    ix = lo[ks, 0, None, None] + np.arange(span[0])[None, None, :]  # [k, 1, Bx] column of each box cell
    iy = lo[ks, 1, None, None] + np.arange(span[1])[None, :, None]  # [k, By, 1] row
    inside = (ix >= 0) & (ix < W) & (iy >= 0) & (iy < H) & (ix <= hi[ks, 0, None, None]) \
        & (iy <= hi[ks, 1, None, None])  # [k, By, Bx]
    px = xs[np.clip(ix, 0, W - 1)]  # [k, 1, Bx]
    py = ys[np.clip(iy, 0, H - 1)]  # [k, By, 1]
    if ks[0] < C:  # circles: the distance from the centre less the radius
        c = circles[ks][:, :, None, None]  # [k, 3, 1, 1]
        dist = np.sqrt((c[:, 0] - px) ** 2 + (c[:, 1] - py) ** 2) - c[:, 2]
    else:  # rects: outside, the distance to the box; inside, minus the distance to its nearest side
        r = rects[ks - C][:, :, None, None]  # [k, 4, 1, 1]
        qx = np.abs(px - 0.5 * (r[:, 0] + r[:, 2])) - 0.5 * (r[:, 2] - r[:, 0])
        qy = np.abs(py - 0.5 * (r[:, 1] + r[:, 3])) - 0.5 * (r[:, 3] - r[:, 1])
        dist = np.hypot(np.clip(qx, 0, None), np.clip(qy, 0, None)) + np.clip(np.maximum(qx, qy), None, 0)
    k, by, bx = np.nonzero(inside & (dist < margin))
    occupied[iy[k, by, 0], ix[k, 0, bx]] = True


def sensed_world(task: NavTask) -> Environment:
    """What a map-conditioned policy senses: the task's raw obstacles and bounds, not inflated by the robot's
    radius (the map-table farm's patches are raw; its tables inflate by the radius themselves)."""
    return inflate(task.discs, task.walls, task.bounds, 0.0)


def cost_environment(task: NavTask, ctx: NavContext) -> Environment:
    """The obstacles the cost checks: the task's own (sensed or few), else its raster at ``ctx.cost_resolution``."""
    if task.sensing_range is not None or len(task.environment.obstacles) <= RASTER_MIN_OBSTACLES:
        return task.environment
    # by content: each job brings its own (unpickled) copy of the task
    geometry = hashlib.sha1(task.discs.tobytes() + task.walls.tobytes() + repr(task.bounds).encode()).hexdigest()
    key = ("raster", geometry, task.robot_radius, ctx.cost_resolution)
    if key not in _CACHE:
        _CACHE[key] = rasterize(task.environment, ctx.cost_resolution)
    return _CACHE[key]


class _TimedSensingController:
    """Wraps a controller: updates the cost's obstacles to what the robot senses (tasks with a sensing range)
    before each command, and times each command (the control cycle; sensing is the world's, not timed).

    With a ``trace`` list and an inner controller with the core's trace hook (:attr:`MPPICore.on_plan
    <cuniform_torch.controllers.core.MPPICore.on_plan>`: the MPPI family), each command appends ``dict(t,
    free_share, min_cost, state)``: the command's time (s), the share of its proposals that are collision-free
    (cost < ``collision_penalty``), the lowest proposal cost and the state ``[d]`` it planned from. The hook only
    keeps the result; the trace's numbers are read after the command's clock stops."""

    def __init__(self, inner: Any, cost: NavigationCost, task: NavTask, trace: list | None = None,
                 dt: float = 0.0, collision_penalty: float = 1e6, to_go: CostToGo | None = None):
        self.inner, self.cost, self.task, self.to_go = inner, cost, task, to_go
        self.cycle_s: list[float] = []
        self.trace = trace if trace is not None and hasattr(inner, "on_plan") else None
        self._costs: torch.Tensor | None = None
        """``[K]`` the last command's proposal costs (set by the hook)"""
        if self.trace is not None:
            inner.on_plan = self._keep
        self.dt, self.collision_penalty = dt, collision_penalty

    def _keep(self, result: Any) -> None:
        self._costs = result.costs

    def reset(self) -> None:
        if callable(getattr(self.inner, "reset", None)):
            self.inner.reset()

    def command(self, state: torch.Tensor) -> torch.Tensor:
        if self.task.sensing_range is not None:
            self.cost.env = self.task.sensed_environment(state[:2])
        if self.to_go is not None:  # a global planner's work (untimed): recomputed when the sensed obstacles change
            self.to_go.update(self.cost.env)
        t0 = time.perf_counter()
        u = self.inner.command(state)
        self.cycle_s.append(time.perf_counter() - t0)
        if self.trace is not None and self._costs is not None:
            costs = self._costs  # [K]
            self.trace.append(dict(t=round(len(self.trace) * self.dt, 6),
                                   free_share=float((costs < self.collision_penalty).float().mean()),
                                   min_cost=float(costs.min()), state=[round(float(v), 6) for v in state.tolist()]))
        return u


def sources_and_simulator(ctx: NavContext) -> tuple[Sources, Any]:
    """The controllers' sources (with learned dynamics, every policy's system is the model) and the system the
    simulator steps (the robot's own)."""
    sources = context_sources(ctx)
    return sources, (sources.true_system if isinstance(sources, LearnedSources) else sources.system)


def navigation_cost(task: NavTask, ctx: NavContext, dt: float) -> tuple[NavigationCost, CostToGo | None]:
    """The episode's cost (module docstring) and its cost-to-go planner (None: the straight line)."""
    to_go = CostToGo(task.bounds, task.goal, ctx.cost_to_go) if ctx.cost_to_go is not None else None
    cost = NavigationCost(cost_environment(task, ctx), task.goal, goal_tolerance=task.goal_tolerance,
                          collision_penalty=ctx.collision_penalty, per_state=True, stop_at_goal=True,
                          goal_distance=to_go, dt=dt)
    return cost, to_go


def start_state(task: NavTask, system: Any) -> torch.Tensor:
    """``[d]`` float32: the task's start pose, zeros in the other state dimensions."""
    x0 = torch.zeros(len(system.periodic), dtype=torch.float32)
    x0[:3] = torch.tensor(task.start, dtype=torch.float32)
    return x0


def run_nav_episode(job: NavJob, ctx: NavContext, trace: list | None = None) -> dict:
    """Run one episode; its record (plain JSON types, :mod:`eval.navigate.records`' format) with the job's ``key``,
    ``repeat``, ``outcome``, ``success``, ``time`` (s), ``path_length`` (m), ``steps``, ``cycles``,
    ``cycle_hist``, ``wall_s`` (and ``path`` with ``ctx.record_path``).

    ``trace``: a list to append one ``dict(t, free_share, min_cost, state)`` per command to (:mod:`eval.navigate.replay`;
    MPPI-family controllers only, others append nothing); the record is the same with or without it."""
    torch.set_num_threads(1)
    task, method = job.task, methods_of(NAVIGATE)[job.method]
    sources, system = sources_and_simulator(ctx)
    cost, to_go = navigation_cost(task, ctx, float(system.dt))
    t0 = time.perf_counter()
    world = sensed_world(task) if method.source == "map_policy" else None
    inner = make_controller(method, sources, cost, job.budget, ctx.horizon, job.seed, lambda_=ctx.lambda_,
                            world=world, max_range=task.sensing_range)
    ctrl = _TimedSensingController(inner, cost, task, trace, dt=float(system.dt),
                                   collision_penalty=ctx.collision_penalty, to_go=to_go)
    x0 = start_state(task, system)
    res = simulate(system, ctrl, x0, task.environment, task.goal, task.goal_tolerance, task.time_limit, cost=cost,
                   record=ctx.record_path)
    rec = dict(key=job.key, suite=task.suite, task_id=task.task_id, method=job.method, budget=job.budget,
               seed=job.seed, repeat=job.repeat, outcome=res.outcome, success=res.success,
               time=round(res.time, 6), path_length=round(res.path_length, 6), steps=res.steps,
               cycles=len(ctrl.cycle_s), cycle_hist=cycle_histogram(ctrl.cycle_s),
               wall_s=round(time.perf_counter() - t0, 4))
    if ctx.record_path:
        rec["path"] = [[round(float(x), 3), round(float(y), 3)] for x, y in res.path[:, :2].tolist()]
    return rec
