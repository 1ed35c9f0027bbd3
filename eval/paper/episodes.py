"""Closed-loop episodes: the settings every closed-loop experiment shares, and running the episodes.

An :class:`Episode` is one closed-loop run: a method with N samples in one scenario (an environment, a start
pose, a goal) under one controller seed. :func:`run_episodes` drives each through
:func:`cuniform_torch.envs.simulate` with the paper's cost (:class:`cuniform_torch.envs.NavigationCost`:
squared distance to the goal + a collision penalty, both ending at a rollout's first arrival at the goal
(``stop_at_goal``, as the authors' controllers do: their ROS C-Uniform node breaks out of the horizon loop
there, their C-Free-Uniform planner zeroes the obstacle cost from the goal on), told the time every cycle so
that an obstacle counts only once it is sensed) and returns one JSON-ready record per run. The records'
statistics are :mod:`eval.common.stats`', their tables :mod:`eval.common.markdown`'s, their figures :mod:`eval.common.figures`'.

Every controller knob is the same for every method: lambda (``config.LAMBDA``), horizon, N, the cost, the
goal tolerance and the time limit. Method-specific settings are the registry's (``eval.common.methods``): the
baselines' noise level is part of the method, CU-MPPI keeps its reference defaults.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import torch

from cuniform_torch.envs import Environment, NavigationCost, simulate
from eval.common import config
from eval.common.methods import METHODS, PAPER, Method, Sources, make_controller, parse_methods
from precompute.parallel import run_jobs

__all__ = ["ControllerSettings", "Episode", "OUTCOMES", "SLOW_NOTE", "usable_methods", "run_episode", "run_episodes"]

OUTCOMES = ("goal", "collision", "timeout")
"""what an episode can end in (``cuniform_torch.envs.simulate``)"""


@dataclass(frozen=True)
class ControllerSettings:
    """The closed-loop settings both experiments share (each experiment's config adds its scenario)."""

    goal_tolerance: float = 0.3
    """m: the goal is reached within this xy distance (also the cost's cut-off)"""
    horizon: int = 15
    """controller horizon in steps (3 s; at most the table's)"""
    lambda_: float = config.LAMBDA
    collision_penalty: float = 1e6
    """added for every rollout state in a sensed obstacle (``per_state``) or once per colliding rollout"""
    per_state: bool = True
    """penalty per colliding state (True) or once per colliding rollout"""
    stop_at_goal: bool = True
    """no collision cost after a rollout's first arrival at the goal (``NavigationCost.stop_at_goal``); False:
    collisions count over the whole horizon (the experiments' cost before this option)"""
    seed: int = 0
    """draws the scenario (obstacle offsets, start poses); controller seeds derive from it"""
    methods: tuple[str, ...] | None = None
    """method keys; None: every closed-loop method whose files exist (cu_mlp only with ``include_mlp``)"""
    include_mlp: bool = False
    """add cu_mlp to a default run (``methods=None``); it is ~10x slower per cycle than the table on CPU"""
    samples: tuple[int, ...] = (500, 1000)
    """N, trajectories per control cycle"""


@dataclass
class Episode:
    """One closed-loop run to do."""

    method: str
    """registry key (``eval.common.methods.METHODS``)"""
    num_samples: int
    """N, trajectories per control cycle"""
    env: Environment
    x0: tuple[float, float, float]
    """start pose (x, y, theta)"""
    goal: tuple[float, float]
    goal_tolerance: float
    """m: the goal is reached within this xy distance (also the cost's cut-off)"""
    time_limit: float
    """s"""
    seed: int
    """controller seed (the same for every method in the same scenario)"""
    horizon: int = 15
    """controller horizon, steps"""
    tags: dict = field(default_factory=dict)
    """scenario labels copied to the record (e.g. ``{"appear": 0.5, "position": 3}``)"""


SLOW_NOTE = ("a method marked ``slow`` (cu_mlp) is left out of a default run: on a 2-core CPU the distilled MLP "
             "costs about 10x the table lookup per control cycle (about 280 s of the cluttered run and 200 s of the "
             "sudden-obstacle run, as much as all other methods together)")


def usable_methods(keys: Sequence[str] | None, sources: Sources, requested: bool,
                   include_slow: bool = False) -> list[Method]:
    """The closed-loop methods among ``keys`` (None: all but the ``slow`` ones, unless ``include_slow``)
    whose source files exist.

    Every method needs the table (the system comes from it), a C-Uniform method the file of its source too. A
    method whose file is missing is dropped with a printed note, unless the user named it (``requested``): then
    it raises ``FileNotFoundError``.
    """
    methods = parse_methods(keys, benchmark=PAPER, closed_loop=True)
    if keys is None and not include_slow:
        slow = [m.key for m in methods if m.slow]
        if slow:
            print(f"note: leaving out {', '.join(slow)} (slow on CPU; ask for it with --mlp or --methods)")
        methods = [m for m in methods if not m.slow]
    kept = []
    for m in methods:
        needed = [sources.table] + ([sources.file_of(m.source)] if m.source is not None else [])
        missing = [p for p in needed if not Path(p).exists()]
        if missing:
            path = missing[0]
            if requested:
                raise FileNotFoundError(f"{m.key} needs {path}, which does not exist (python -m eval.report builds it)")
            print(f"note: skipping {m.key}: {path} not found")
            continue
        kept.append(m)
    return kept


def _path_list(path: torch.Tensor) -> list[list[float]]:
    return [[round(float(x), 3), round(float(y), 3)] for x, y in path[:, :2].tolist()]


def run_episode(ep: Episode, sources: Sources, settings: ControllerSettings, record_paths: bool = True) -> dict:
    """One episode's record (see :func:`run_episodes`)."""
    method = METHODS[ep.method]
    cost = NavigationCost(ep.env, ep.goal, goal_tolerance=ep.goal_tolerance,
                          collision_penalty=settings.collision_penalty, per_state=settings.per_state,
                          stop_at_goal=settings.stop_at_goal)
    ctrl = make_controller(method, sources, cost, ep.num_samples, ep.horizon, ep.seed, lambda_=settings.lambda_)
    x0 = torch.tensor(ep.x0, dtype=torch.float32, device=sources.device)
    t0 = time.perf_counter()
    res = simulate(sources.system, ctrl, x0, ep.env, ep.goal, ep.goal_tolerance, ep.time_limit, cost=cost,
                   record=record_paths)
    rec = dict(ep.tags)
    rec.update(method=ep.method, num_samples=ep.num_samples, seed=ep.seed, x0=list(ep.x0), goal=list(ep.goal),
               outcome=res.outcome, success=res.success, time=round(res.time, 6),
               path_length=round(res.path_length, 6), steps=res.steps,
               wall_s=round(time.perf_counter() - t0, 4))
    if record_paths:
        rec["path"] = _path_list(res.path.cpu())
    return rec


_WORKER_SOURCES: dict[tuple, Sources] = {}
"""a worker process's sources, loaded once per process (not once per episode)"""


def _episode_in_worker(ep: Episode, files: tuple, settings: ControllerSettings, record_paths: bool) -> dict:
    """:func:`run_episode` in a worker process, on one torch thread (the workers share the cores)."""
    torch.set_num_threads(1)
    if files not in _WORKER_SOURCES:
        table, coverage_table, policy, map_policy, device = files
        _WORKER_SOURCES[files] = Sources(table, coverage_table, policy, map_policy, device)
    return run_episode(ep, _WORKER_SOURCES[files], settings, record_paths)


def run_episodes(episodes: Sequence[Episode], sources: Sources, settings: ControllerSettings,
                 record_paths: bool = True, progress: bool = True, desc: str = "episodes",
                 workers: int = 1) -> list[dict]:
    """Run every episode; one record per episode (plain JSON types), in the order of ``episodes``.

    The controllers use ``settings.lambda_``; the cost is :class:`~cuniform_torch.envs.NavigationCost` with
    ``settings.collision_penalty`` per colliding state (``per_state``, the paper's per-state obstacle cost summed
    over the horizon) or once per colliding rollout, both cost terms ending at a rollout's first arrival at the
    goal (``stop_at_goal``; False: collisions after it count too).

    ``workers`` > 1 runs the episodes in that many spawned processes (:func:`~precompute.parallel.run_jobs`),
    each on one torch thread (CPU sources only); an episode's record does not depend on where it ran (each has its
    own controller seed) apart from ``wall_s``.

    Record: the episode's ``tags``, ``method``, ``num_samples``, ``seed``, ``x0``, ``goal``, ``outcome``
    (one of :data:`OUTCOMES`), ``success``, ``time`` (s, simulated), ``path_length`` (m), ``steps``,
    ``wall_s`` (seconds of compute) and, with ``record_paths``, ``path`` (``[[x, y], ...]``, start included).
    """
    from tqdm.auto import tqdm

    if workers <= 1 or len(episodes) <= 1 or sources.device != "cpu":
        return [run_episode(ep, sources, settings, record_paths)
                for ep in tqdm(episodes, desc=desc, disable=not progress, leave=False)]
    files = (sources.table, sources.coverage_table, sources.policy, sources.map_policy, sources.device)
    with tqdm(total=len(episodes), desc=desc, disable=not progress, leave=False) as bar:
        return run_jobs(_episode_in_worker, [(ep, files, settings, record_paths) for ep in episodes], workers=workers,
                        on_done=lambda i, rec: bar.update())
