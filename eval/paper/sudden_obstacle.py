"""Sudden obstacle (the paper's Table II): a circular obstacle on the way to the goal, sensed late.

Scenario (all in :class:`SuddenObstacleConfig`, so a rerun gives the same numbers):

* Dubins car of the table (v = 1 m/s, dt = 0.2 s, |omega| <= pi/4 rad/s: turning radius 1.27 m), start
  (0, 0, 0), goal (4, 0): "4 m ahead". Success = the goal reached (within ``goal_tolerance`` = 0.3 m, 1.5
  simulation steps) without a collision within ``time_limit`` = 10 s (2.5 x the 4 s straight drive).
* One disc of radius r = 0.5 m centred halfway, at x = 2 m, with lateral offset y drawn uniformly in
  [-r, r] (the paper's rule); 20 offsets from ``numpy.random.default_rng(seed)``, the same for every method,
  N and appearance time. The paper gives neither r nor the distance; we put the disc at the midpoint and
  chose r = 0.5 m so that the appearance times span easy to hard *for the dynamics, whatever the sampler*:
  the "oracle" row (below) is feasible for every offset up to 0.8 s and for most at 1.0 s.
* The robot senses the obstacle from ``appear`` s on (0 = visible from the start; 0.2 / 0.5 / 0.8 / 1.0 s):
  the obstacle has ``appear_time = appear`` and :func:`cuniform_torch.envs.simulate` calls the cost's
  ``set_time`` each cycle, so the collision term counts it only once sensed; collisions are always checked
  against the real obstacle.
* Point robot, collisions checked at the simulated states (every 0.2 m), no workspace bounds.
* Controllers: every closed-loop method in ``eval.common.methods`` (``cu_mlp`` only with ``--mlp`` / ``--methods``:
  it is ~10x slower per cycle on CPU) with N in {500, 1000} samples per cycle, horizon 15 steps
  (3 s, the paper's T), lambda = 0.567 (the paper's), the paper's cost: sum over the horizon of the squared
  xy distance to the goal (cut off once a rollout reaches the goal tolerance) + 1e6 for every rollout state
  inside a sensed obstacle (a finite stand-in for the paper's per-state l_obs = inf, summed over the
  horizon like l_state; the same for all methods). A penalty charged once per colliding rollout would leave
  MPPI nothing to follow when every one of its samples collides (low noise, obstacle ahead): with it our
  MPPI low / medium fail even with the obstacle visible from the start, which the paper's baselines do not. MPPI / log-MPPI start each episode from
  a zero nominal and warm-start by shifting; C-Uniform methods draw fresh rollouts of the horizon-15 table
  each cycle; CU-MPPI keeps its reference defaults (half C-Uniform samples, local pass std 0.1). No knob
  differs between methods beyond what defines the method.
* Controller seed: ``seed + 1 + 1000 * appear_index + position``: the same for every method and N.

Oracle row: for each offset and appearance time, whether *some* sequence of the 5 table actions avoids the
disc after driving exactly straight until the obstacle is sensed (a breadth-first search over states, merged
on a 2.5 cm / 0.025 rad grid; whether the goal is reached afterwards is not checked). It shows how hard each
appearance time is for the dynamics alone. It is a reference, not a strict bound: the controllers' commands
are continuous (weighted averages) and they need not drive exactly straight before the obstacle is sensed, so
a controller can beat it by a position or two.

``python -m eval.paper.sudden_obstacle [--methods ...] [--samples 500 1000] [--positions 20]
[--appear 0 0.2 0.5 0.8 1.0] [--device cpu] [--json PATH] [--figures DIR] [--quick]``
"""

from __future__ import annotations

import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from cuniform_torch.envs import Circle, Environment
from eval.common import config
from eval.common.figures import plot_paths
from eval.common.markdown import success_markdown
from eval.common.methods import METHODS, Sources
from eval.common.stats import aggregate
from eval.paper import cli
from eval.paper.episodes import ControllerSettings, Episode, run_episodes, usable_methods

__all__ = ["SuddenObstacleConfig", "CONFIG", "QUICK", "make_parser", "config_from_args", "offsets",
           "make_env", "oracle_feasible", "episodes", "episode_counts", "run", "markdown", "figures", "main"]


@dataclass(frozen=True)
class SuddenObstacleConfig(ControllerSettings):
    """Geometry, parameters and seeds of the sudden-obstacle experiment (controller settings: the base class)."""

    start: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """start pose (x, y, theta)"""
    goal: tuple[float, float] = (4.0, 0.0)
    """goal, 4 m ahead"""
    obstacle_x: float = 2.0
    """x of the disc's centre (m): halfway to the goal"""
    radius: float = 0.5
    """disc radius r (m); the lateral offset is uniform in [-r, r]"""
    positions: int = 20
    """number of lateral offsets (the paper: 20)"""
    appear: tuple[float, ...] = (0.0, 0.2, 0.5, 0.8, 1.0)
    """times (s) from which the robot senses the obstacle (0 = visible from the start)"""
    time_limit: float = 10.0
    """s"""


QUICK = SuddenObstacleConfig(positions=2, appear=(0.0, 1.0), samples=(100,))
"""--quick: two offsets, two appearance times, N = 100 (a few seconds)"""


def offsets(cfg: SuddenObstacleConfig) -> list[float]:
    """The ``cfg.positions`` lateral offsets (m), uniform in [-r, r], fixed by ``cfg.seed``."""
    rng = np.random.default_rng(cfg.seed)
    return [round(float(v), 4) for v in rng.uniform(-cfg.radius, cfg.radius, cfg.positions)]


def make_env(cfg: SuddenObstacleConfig, offset: float, appear: float) -> Environment:
    return Environment([Circle((cfg.obstacle_x, offset), cfg.radius, appear_time=appear)])


def oracle_feasible(cfg: SuddenObstacleConfig, system, offset: float, appear: float, max_steps: int = 30) -> bool:
    """Whether some sequence of the system's actions avoids the disc after driving straight until ``appear``."""
    env = make_env(cfg, offset, appear)
    actions = system.action_set(dtype=torch.float64)  # [A, q]
    x = torch.tensor([cfg.start], dtype=torch.float64)  # [1, d]
    zero = torch.zeros((1, actions.shape[1]), dtype=torch.float64)
    for _ in range(round(appear / system.dt)):
        x = system.step(x, zero)
        if bool(env.in_collision(x[:, :2]).any()):
            return False
    passed = cfg.obstacle_x + cfg.radius
    res = torch.tensor([0.025, 0.025, 0.025], dtype=torch.float64)
    for _ in range(max_steps):
        A = actions.shape[0]
        nxt = system.step(x.repeat_interleave(A, 0), actions.repeat(x.shape[0], 1))  # [M*A, d]
        nxt = nxt[~env.in_collision(nxt[:, :2])]
        if nxt.shape[0] == 0:
            return False
        if bool((nxt[:, 0] > passed).any()):
            return True
        _, keep = np.unique(torch.round(nxt / res).to(torch.int64).numpy(), axis=0, return_index=True)
        x = nxt[torch.as_tensor(np.sort(keep))]
    return False


def episodes(cfg: SuddenObstacleConfig, methods: list[str]) -> list[Episode]:
    offs = offsets(cfg)
    out = []
    for ai, appear in enumerate(cfg.appear):
        for p, off in enumerate(offs):
            env = make_env(cfg, off, appear)
            for n in cfg.samples:
                for m in methods:
                    out.append(Episode(m, n, env, cfg.start, cfg.goal, cfg.goal_tolerance, cfg.time_limit,
                                       seed=cfg.seed + 1 + 1000 * ai + p, horizon=cfg.horizon,
                                       tags={"appear": appear, "position": p, "offset": off, "env": f"pos{p}"}))
    return out


def run(cfg: SuddenObstacleConfig, sources: Sources, progress: bool = True, record_paths: bool = True,
        workers: int = 1) -> dict:
    """Run the experiment; a JSON-ready dict (config, offsets, oracle, per-episode records, summary)."""
    t0 = time.perf_counter()
    methods = [m.key for m in usable_methods(cfg.methods, sources, requested=cfg.methods is not None,
                                              include_slow=cfg.include_mlp)]
    offs = offsets(cfg)
    system = sources.system
    oracle = {str(a): [oracle_feasible(cfg, system, off, a) for off in offs] for a in cfg.appear}
    records = run_episodes(episodes(cfg, methods), sources, cfg, record_paths=record_paths, progress=progress, workers=workers,
                           desc="sudden obstacle")
    return {
        "experiment": "sudden_obstacle",
        "config": asdict(cfg),
        "methods": methods,
        "offsets": offs,
        "oracle": oracle,
        "records": records,
        "summary": aggregate(records, ("appear", "num_samples", "method")),
        "seconds": round(time.perf_counter() - t0, 2),
    }


def _config(results: dict) -> SuddenObstacleConfig:
    return cli.config_from_json(SuddenObstacleConfig, results["config"])


def markdown(results: dict) -> str:
    """Success-rate tables (one per N; rows = methods, columns = appearance times) beside the paper's."""
    cfg = _config(results)
    rows = results["summary"]
    labels = ["fully visible" if a == 0 else f"{a:g} s" for a in cfg.appear]
    out = [
        "### Sudden obstacle (Table II)",
        "",
        f"Start {cfg.start}, goal {cfg.goal} (tolerance {cfg.goal_tolerance} m), a disc of radius {cfg.radius} m "
        f"centred at x = {cfg.obstacle_x} m with lateral offsets uniform in [-{cfg.radius}, {cfg.radius}] "
        f"({cfg.positions} positions, seed {cfg.seed}: {', '.join(f'{o:+.2f}' for o in results['offsets'])}), "
        f"sensed from the given time on; time limit {cfg.time_limit:g} s, horizon {cfg.horizon} steps "
        f"({cfg.horizon * config.DT:g} s), lambda {cfg.lambda_}. Success rate over the positions, 95% Wilson "
        "interval in brackets. The paper does not say which noise level its MPPI / log-MPPI columns used; "
        "its C-Uniform column is our `cu_table`.",
        "",
    ]
    oracle = results["oracle"]
    for n in cfg.samples:
        paper = {a: {fam: v.get(n) for fam, v in config.PAPER_SUDDEN_OBSTACLE.get(a, {}).items()} for a in cfg.appear}
        out.append(f"**N = {n}**")
        out.append("")
        table = success_markdown(rows, results["methods"], "appear", list(cfg.appear), labels, paper,
                                 where={"num_samples": n})
        feas = [sum(oracle[str(a)]) / len(oracle[str(a)]) if oracle[str(a)] else float("nan") for a in cfg.appear]
        table += "\n| *oracle: avoidable with the 5 actions after driving straight* | reference | " + " | ".join(
            f"{f:.2f}" for f in feas) + " |"
        out += [table, ""]
    out.append(f"Run time: {results['seconds']:.0f} s for {len(results['records'])} episodes.")
    return "\n".join(out)


def figures(results: dict, outdir: Path) -> list[Path]:
    """Closed-loop paths per method, one PNG per appearance time (the largest N; every obstacle position)."""
    cfg = _config(results)
    recs = results["records"]
    if not recs or "path" not in recs[0]:
        return []
    n = max(cfg.samples)
    outdir = Path(outdir)
    paths = []
    for a in cfg.appear:
        envs = {f"pos{p}": make_env(cfg, off, a) for p, off in enumerate(results["offsets"])}
        panels = {METHODS[m].label: [r for r in recs if r["method"] == m and r["appear"] == a
                                     and r["num_samples"] == n] for m in results["methods"]}
        tag = "visible" if a == 0 else f"{a:g}s"
        paths.append(plot_paths(panels, envs, outdir / f"sudden_obstacle_{tag}_N{n}.png",
                                title=f"Sudden obstacle, sensed {'from the start' if a == 0 else f'after {a:g} s'}, "
                                      f"N = {n} (all {cfg.positions} obstacle positions overlaid)",
                                xlim=(-0.5, 5.0), ylim=(-2.5, 2.5)))
    return paths


CONFIG = SuddenObstacleConfig


def episode_counts(cfg: SuddenObstacleConfig) -> dict[str, int]:
    """The scenario counts that multiply into episodes (with the budgets and methods; ``--no-limit``)."""
    return {"positions": cfg.positions, "appearance times": len(cfg.appear)}


make_parser, config_from_args, main = cli.entry_points(
    __name__, lambda p: cli.add_closed_loop_args(p, SuddenObstacleConfig, only=("positions", "appear")), threads=1)


if __name__ == "__main__":
    sys.exit(main())
