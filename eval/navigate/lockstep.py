"""Lockstep episodes: the episodes of one (method, K) driven together, one batched command per control cycle.

Shapes: B robots (episodes) in the batch, L of them still live, K samples, T horizon, d state, q action dimensions.

:func:`run_lockstep` runs B jobs of one method and budget as the B robots of one controller (``num_robots=B``, robot
``b`` seeded with job ``b``'s seed: its own random stream, :class:`~cuniform_torch.controllers.streams.RobotStreams`),
so robot ``b`` draws what the serial episode's controller of one robot draws
(:func:`eval.navigate.episode.run_nav_episode`), and its record is the serial run's in every field but the timing
ones (the library's batched arithmetic equals its one-robot arithmetic to the last bit, below). Each robot keeps its own world: its cost (:class:`_RobotCosts`, the core's per-robot ``batched = True`` cost:
each robot's ``[K, T+1, d]`` rollouts against its own obstacles, goal and cost-to-go), its sensed obstacles, and
for a map-conditioned method its own sensed map (:class:`_SensorPerRobot`). Per cycle, the live robots' states are
one ``[B, d]`` command; the simulator then steps, checks and retires each live robot exactly as
:func:`cuniform_torch.envs.simulate` does (goal, collision, time limit). A retired robot's state stays where its
episode ended; the controller still plans for it (its rollouts are part of the batch's tensor program), but its
cost is not evaluated (zeros) and its command is dropped.

Timing: a robot's own control cycle cannot be measured when B robots share one command, so each live robot's cycle
is recorded as the batch command's wall time divided by the live robots (``cycle_hist``), its ``wall_s`` is the
batch's wall time divided by B, and the record says ``"clock": "lockstep"`` plus ``"lockstep": B``. These are not
per-robot cycle times: the equal-compute view (:mod:`eval.navigate.budget`) must not read them as such.

Why some loops over robots stay: the world is per robot (a different obstacle set per episode), so the cost, the
sensing and the collision check run once per live robot on that robot's tensors. The simulator steps each robot as
a ``[1, d]`` row, as :func:`~cuniform_torch.envs.simulate` does (the built-in robot's step gives the same bits for
L rows at once, a user's system need not): a closed loop turns a last-bit difference in a state into a different
episode within a few hundred steps, which is why the library computes a robot of a batch exactly as a controller
of one robot (``tests/test_batch_invariance.py``; ``tests/test_navigate_lockstep.py`` shows equal records).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor

from cuniform_torch.controllers.cfu import CFUMPPI, MapSensor
from cuniform_torch.envs import COLLISION, GOAL, TIMEOUT, Environment, NavigationCost, OccupancyGrid
from cuniform_torch.maps.policy import MapPolicy
from cuniform_torch.maps.sensing import sense_patch
from eval.common.methods import NAVIGATE, make_controller, methods_of
from eval.navigate.cost_to_go import CostToGo
from eval.navigate.episode import (
    NavContext,
    NavJob,
    navigation_cost,
    sensed_world,
    sources_and_simulator,
    start_state,
)
from eval.navigate.records.cycle_hist import cycle_histogram

__all__ = ["run_lockstep", "lockstep_batches", "LOCKSTEP_CLOCK"]

LOCKSTEP_CLOCK = "lockstep"
"""the ``clock`` of a lockstep record: its cycle times are a batch command's share, not a robot's own cycle"""


class _RobotCosts:
    """B navigation costs as one per-robot cost of the core (``batched = True``): ``states [B, K, T+1, d]``,
    ``actions [B, K, T, q]`` -> ``[B, K]``, robot ``b``'s rollouts against ``costs[b]`` (its own world); a
    retired robot (``live[b]`` False) costs zeros without an evaluation."""

    batched = True

    def __init__(self, costs: Sequence[NavigationCost]):
        self.costs = list(costs)
        self.live = [True] * len(self.costs)

    def __call__(self, states: Tensor, actions: Tensor) -> Tensor:
        out = states.new_zeros(states.shape[:2])  # [B, K]
        for b, cost in enumerate(self.costs):  # each robot's world differs: one [K, T+1, d] evaluation each
            if self.live[b]:
                out[b] = cost(states[b], actions[b])
        return out


class _SensorPerRobot(MapSensor):
    """A map sensor bound to one world per robot: robot ``b``'s patch is cropped from ``worlds[b]``; the B patches
    are then encoded as one batch by the controller (:meth:`~cuniform_torch.controllers.cfu.CFUMPPI.sense`)."""

    def __init__(self, policy: MapPolicy, worlds: Sequence[OccupancyGrid | Environment], max_range: float | None):
        super().__init__(policy, worlds[0], max_range)
        self.worlds = [w.to(self.device) if isinstance(w, OccupancyGrid) else w for w in worlds]

    def sense(self, states: Tensor) -> Tensor:
        if states.shape[0] != len(self.worlds):
            raise ValueError(f"{len(self.worlds)} worlds for {states.shape[0]} robots")
        return torch.cat([sense_patch(w, states[b:b + 1, :3], self.spec, self.max_range, self.time)
                          for b, w in enumerate(self.worlds)])  # [B, H, W]


class _CFUPerRobot(CFUMPPI):
    """CFU-MPPI whose robot ``b`` senses ``worlds[b]``: CFU-MPPI as it is, with :class:`_SensorPerRobot` as its
    sensor. ``kwargs``: CFU-MPPI's (``num_samples``, ``horizon``, ``lambda_``, ``device``, ``seed``, ``num_robots``)."""

    def __init__(self, policy: MapPolicy, worlds: Sequence[Environment], cost_fn: Any, max_range: float | None = None,
                 **kwargs: Any):
        super().__init__(policy, worlds[0], cost_fn, max_range=max_range, **kwargs)
        self.sensor = _SensorPerRobot(self.map_policy, worlds, max_range)


def lockstep_batches(jobs: Sequence[NavJob], size: int) -> list[list[NavJob]]:
    """``jobs`` grouped by (method, budget), in their first job's order, each group cut into batches of at most
    ``size`` jobs (in job order)."""
    if isinstance(size, bool) or not isinstance(size, int) or size < 1:
        raise ValueError(f"lockstep: a batch holds at least 1 episode, got {size!r}")
    groups: dict[tuple[str, int], list[NavJob]] = {}
    for job in jobs:
        groups.setdefault((job.method, job.budget), []).append(job)
    return [group[i:i + size] for group in groups.values() for i in range(0, len(group), size)]


def run_lockstep(jobs: Sequence[NavJob], ctx: NavContext) -> list[dict]:
    """Run ``jobs`` (one method and budget) in lockstep (module docstring); their records, in job order: the serial
    run's (:func:`~eval.navigate.episode.run_nav_episode`) in every field but ``cycle_hist`` and ``wall_s``, plus
    ``clock`` (:data:`LOCKSTEP_CLOCK`) and ``lockstep`` (B)."""
    jobs = list(jobs)
    if not jobs:
        return []
    if len({(j.method, j.budget) for j in jobs}) != 1:
        raise ValueError("run_lockstep: a batch is one method at one budget, got "
                         f"{sorted({(j.method, j.budget) for j in jobs})}")
    if len({j.task.sensing_range for j in jobs}) != 1:
        raise ValueError("run_lockstep: a batch's tasks must share one sensing range (one suite); got "
                         f"{sorted({str(j.task.sensing_range) for j in jobs})}: batch each suite's jobs apart")
    torch.set_num_threads(1)  # as every serial episode: the same arithmetic
    method = methods_of(NAVIGATE)[jobs[0].method]
    sources, system = sources_and_simulator(ctx)
    dt = float(system.dt)
    B = len(jobs)
    made = [navigation_cost(j.task, ctx, dt) for j in jobs]
    costs: list[NavigationCost] = [c for c, _ in made]
    to_gos: list[CostToGo | None] = [g for _, g in made]
    robot_costs = _RobotCosts(costs)
    t0 = time.perf_counter()
    sensing = jobs[0].task.sensing_range
    world: list[Environment] | None = None
    if method.source == "map_policy":  # one sensed map per robot
        if method.controller is not CFUMPPI:
            raise ValueError(f"lockstep: {method.key}'s controller senses one world; run it without --lockstep")
        method, world = dataclasses.replace(method, controller=_CFUPerRobot), [sensed_world(j.task) for j in jobs]
    ctrl = make_controller(method, sources, robot_costs, jobs[0].budget, ctx.horizon, [j.seed for j in jobs],
                           lambda_=ctx.lambda_, world=world, max_range=sensing, num_robots=B)
    if callable(getattr(ctrl, "reset", None)):
        ctrl.reset()

    x = torch.stack([start_state(j.task, system) for j in jobs])  # [B, d]
    goals = x.new_tensor([j.task.goal for j in jobs])  # [B, 2]
    tols = [float(j.task.goal_tolerance) for j in jobs]
    max_steps = [max(1, math.ceil(float(j.task.time_limit) / dt - 1e-9)) for j in jobs]
    outcome: list[str | None] = [None] * B
    for b in range(B):  # simulate's: a start within the goal tolerance is a goal after 0 steps
        if float(torch.linalg.vector_norm(x[b, :2] - goals[b])) <= tols[b]:
            outcome[b] = GOAL
    steps = [0] * B
    lengths = [x.new_zeros(()) for _ in range(B)]  # float32 sums, step by step: simulate's arithmetic
    paths: list[list[Tensor]] = [[x[b].clone()] for b in range(B)]  # a copy: x is written in place
    cycle_s: list[list[float]] = [[] for _ in range(B)]
    step = 0
    while True:
        live = [b for b in range(B) if outcome[b] is None]
        if not live:
            break
        robot_costs.live = [outcome[b] is None for b in range(B)]
        for b in live:
            costs[b].set_time(step * dt)
            if sensing is not None:
                costs[b].env = jobs[b].task.sensed_environment(x[b, :2])
            to_go = to_gos[b]
            if to_go is not None:  # a global planner's work (untimed), as the serial episode's
                to_go.update(costs[b].env)
        c0 = time.perf_counter()
        u = ctrl.command(x)  # [B, q]
        share = (time.perf_counter() - c0) / len(live)
        step += 1
        for b in live:
            cycle_s[b].append(share)
            x_new = system.step(x[b:b + 1], u[b:b + 1])[0]  # [d]: a [1, d] row, as simulate steps it
            steps[b] = step
            lengths[b] = lengths[b] + torch.linalg.vector_norm(x_new[:2] - x[b, :2])
            flags = torch.stack((
                ~torch.isfinite(x_new).all() | ~torch.isfinite(u[b]).all(),
                jobs[b].task.environment.in_collision(x_new[:2], at=step * dt),
                torch.linalg.vector_norm(x_new[:2] - goals[b]) <= tols[b],
            )).tolist()
            if flags[0]:
                raise ValueError(f"lockstep: non-finite control {u[b].tolist()} or state {x_new.tolist()} at step "
                                 f"{step} of {jobs[b].key}")
            x[b] = x_new
            if ctx.record_path:
                paths[b].append(x_new)
            if flags[1]:
                outcome[b] = COLLISION
            elif flags[2]:
                outcome[b] = GOAL
            elif step >= max_steps[b]:
                outcome[b] = TIMEOUT
    wall = round((time.perf_counter() - t0) / B, 4)
    close = getattr(ctrl, "close", None)
    if callable(close):
        close()
    records = []
    for b, job in enumerate(jobs):
        task = job.task
        rec = dict(key=job.key, suite=task.suite, task_id=task.task_id, method=job.method, budget=job.budget,
                   seed=job.seed, repeat=job.repeat, outcome=outcome[b], success=outcome[b] == GOAL,
                   time=round(steps[b] * dt, 6), path_length=round(float(lengths[b]), 6), steps=steps[b],
                   cycles=len(cycle_s[b]), cycle_hist=cycle_histogram(cycle_s[b]), wall_s=wall,
                   clock=LOCKSTEP_CLOCK, lockstep=B)
        if ctx.record_path:
            path = paths[b] if len(paths[b]) > 1 else [paths[b][0], paths[b][0]]  # simulate's [2, d] of 0 steps
            rec["path"] = [[round(float(p[0]), 3), round(float(p[1]), 3)] for p in path]
        records.append(rec)
    return records
