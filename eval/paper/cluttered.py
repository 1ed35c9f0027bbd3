"""Cluttered environments (the paper's Table III): a U-shaped trap and a field of rectangles.

Geometry (fixed in :data:`ENVIRONMENTS`, printed by :func:`markdown`; the paper gives none):

* ``u_shape``: a 12 m x 12 m walled arena ``[-6, 6]^2``; a U of outer size 2.5 m (x) by 3.7 m (y), walls
  0.25 m thick, centred at the origin and open towards +x (pocket 2.25 m deep, 3.2 m wide: the car's 2.55 m
  turning circle fits inside with margin); the goal (-0.4, 0) is inside the pocket, 0.6 m from its base ("a
  U-shaped obstacle with a goal point inside of the U"). A robot that starts behind or beside the U is pulled
  by the squared-distance cost against the base or a side wall: the trap. A first version had a 2.5 m wide
  pocket (outer 3 m), narrower than the turning circle: a car that reached the opening off-axis could not
  turn in, and every method ended up orbiting the U from most starts (success 0.4-0.5 for ``cu_table``,
  0-0.6 for the baselines, N = 500-2500). We widened the pocket for that physical reason, for all methods
  alike; it made the task easier for the baselines too.
* ``rectangles``: a 12 m x 10 m walled arena ``[0, 12] x [-5, 5]``; eight 0.6 m x 1.4 m rectangles in three
  staggered columns (x = 4, 6, 8 m) between a start strip on the left (x <= 3 m) and the goal (10.5, 0);
  gaps between rectangles are 1.6 m to 2.0 m wide (1.3 m to 2.6 m to the walls), and the middle rectangles
  of the first and last columns sit on the straight line to the goal.

Starts: ``starts`` = 10 random poses per environment, drawn once from ``numpy.random.default_rng([seed,
env index])`` in the environment's start box with a uniform heading, kept only when at least ``clearance``
= 1.5 m from every obstacle and the arena walls (more than the 1.27 m turning radius, so that a robot can
turn away from whatever it faces) and at least ``min_goal_distance`` from the goal. The same starts for every
method and N.

Runs: every closed-loop method of ``eval.common.methods`` (``cu_mlp`` only with ``--mlp`` / ``--methods``) with N in {500, 1000, 2500}, horizon 15 steps (3 s),
lambda = 0.567, the paper's cost (squared xy distance to the goal summed over the horizon + 1e6 per rollout
state in collision, walls included; both terms end at the rollout's first state within the goal tolerance, as
in the authors' controllers: ``NavigationCost(stop_at_goal=True)``), goal tolerance 0.3 m. The time limit
comes from the environment size: ``(width + height) / v`` (24 s for the U arena, 22 s for the rectangles),
i.e. the time to drive half the arena's perimeter. Success = goal reached with no collision within the
limit. Controller seed ``seed + 1 + 1000 * env index + start``: the same for every method and N. No knob
differs between methods beyond what defines the method (see ``eval.paper.sudden_obstacle`` for the cost).

Repeats: ``seeds_per_start`` = R (``--seeds-per-start``, default 1, the paper's one run per start) runs every
start under R controller seeds, ``seed + 1 + 1000 * env index + start + 100000 * r`` for r = 0..R-1 (r = 0 is
the default run's seed, so R = 1 is exactly the default experiment). Success rates then pool the 10 x R runs;
their Wilson interval measures the controller's randomness on *these* starts (the starts are fixed, so it does
not shrink the between-start part of the uncertainty: more starts, ``--starts``, do that), and the markdown adds
a per-start table (successes out of R).

``python -m eval.paper.cluttered [--methods ...] [--samples 500 1000 2500] [--starts 10] [--seeds-per-start 1]
[--envs u_shape rectangles] [--device cpu] [--json PATH] [--figures DIR] [--quick]``
"""

from __future__ import annotations

import math
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from cuniform_torch.common.checks import check_positive_int
from cuniform_torch.envs import Environment, Rect, u_shape
from eval.common import config
from eval.common.figures import plot_paths
from eval.common.markdown import success_markdown
from eval.common.markdown import table as md_table
from eval.common.methods import METHODS, Sources
from eval.common.stats import aggregate
from eval.paper import cli
from eval.paper.episodes import ControllerSettings, Episode, run_episodes, usable_methods

__all__ = ["EnvSpec", "ENVIRONMENTS", "ClutteredConfig", "CONFIG", "QUICK", "make_parser",
           "config_from_args", "make_env", "start_poses", "time_limit", "SEED_STRIDE", "controller_seed",
           "episodes", "episode_counts", "per_start_markdown", "run", "markdown", "figures", "main"]


@dataclass(frozen=True)
class EnvSpec:
    """One cluttered environment: obstacles, arena, goal and where starts are drawn."""

    name: str
    bounds: tuple[float, float, float, float]
    """arena (xmin, ymin, xmax, ymax); leaving it is a collision"""
    goal: tuple[float, float]
    rects: tuple[tuple[float, float, float, float], ...] = ()
    """axis-aligned rectangles (xmin, ymin, xmax, ymax)"""
    u: tuple | None = None
    """u_shape arguments (center, width, depth, thickness, opening)"""
    start_box: tuple[float, float, float, float] | None = None
    """(xmin, ymin, xmax, ymax) where start positions are drawn; None: the arena"""
    min_goal_distance: float = 3.0
    """m, between a start and the goal"""

    def describe(self) -> str:
        parts = [f"arena {self.bounds}", f"goal {self.goal}"]
        if self.u is not None:
            c, w, d, t, o = self.u
            parts.append(f"U-shape centre {c}, width {w} m, depth {d} m, wall {t} m, open {o}")
        if self.rects:
            parts.append("rectangles " + ", ".join(str(r) for r in self.rects))
        parts.append(f"starts in {self.start_box or self.bounds}, >= {self.min_goal_distance} m from the goal")
        return "; ".join(parts)


ENVIRONMENTS: dict[str, EnvSpec] = {
    "u_shape": EnvSpec(
        "u_shape", bounds=(-6.0, -6.0, 6.0, 6.0), goal=(-0.4, 0.0),
        u=((0.0, 0.0), 3.7, 2.5, 0.25, "+x"), min_goal_distance=3.0),
    "rectangles": EnvSpec(
        "rectangles", bounds=(0.0, -5.0, 12.0, 5.0), goal=(10.5, 0.0),
        rects=((4.0, -3.7, 4.6, -2.3), (4.0, -0.7, 4.6, 0.7), (4.0, 2.3, 4.6, 3.7),
               (6.0, -2.4, 6.6, -1.0), (6.0, 1.0, 6.6, 2.4),
               (8.0, -3.7, 8.6, -2.3), (8.0, -0.7, 8.6, 0.7), (8.0, 2.3, 8.6, 3.7)),
        start_box=(0.0, -5.0, 3.0, 5.0), min_goal_distance=6.0),
}


@dataclass(frozen=True)
class ClutteredConfig(ControllerSettings):
    """Parameters and seeds of the cluttered-environment experiment (geometry: :data:`ENVIRONMENTS`; controller
    settings: the base class)."""

    samples: tuple[int, ...] = (500, 1000, 2500)
    """N, trajectories per control cycle"""
    environments: tuple[str, ...] = ("u_shape", "rectangles")
    """environment names (:data:`ENVIRONMENTS`)"""
    starts: int = 10
    """random start poses per environment (the paper: 10)"""
    clearance: float = 1.5
    """m, from a start to every obstacle and wall"""
    time_limit_factor: float = 1.0
    """time limit = factor * (arena width + height) / speed"""
    seeds_per_start: int = 1
    """R: controller seeds per start (1: the paper's one run per start; see the module docstring)"""


QUICK = ClutteredConfig(starts=1, samples=(100,), time_limit_factor=0.25)
"""--quick: one start per environment, N = 100, a quarter of the time limit (a few seconds)"""


def make_env(name: str) -> Environment:
    spec = ENVIRONMENTS[name]
    obstacles = [Rect(*r) for r in spec.rects]
    if spec.u is not None:
        c, w, d, t, o = spec.u
        obstacles.append(u_shape(c, w, d, t, o))
    return Environment(obstacles, bounds=spec.bounds)


def _clearance(env: Environment, xy: torch.Tensor) -> float:
    """Distance (m) from ``xy [2]`` to the nearest obstacle or wall (negative inside)."""
    d = [float(obs.signed_distance(xy)) for obs in env.obstacles]
    xmin, ymin, xmax, ymax = env.bounds
    x, y = float(xy[0]), float(xy[1])
    d.append(min(x - xmin, xmax - x, y - ymin, ymax - y))
    return min(d)


def start_poses(cfg: ClutteredConfig, name: str) -> list[tuple[float, float, float]]:
    """``cfg.starts`` collision-free start poses (x, y, theta) in ``name``, fixed by ``cfg.seed``."""
    spec = ENVIRONMENTS[name]
    env = make_env(name)
    rng = np.random.default_rng([cfg.seed, list(ENVIRONMENTS).index(name)])
    xmin, ymin, xmax, ymax = spec.start_box or spec.bounds
    out = []
    for _ in range(100000):
        if len(out) == cfg.starts:
            return out
        x, y, th = rng.uniform(xmin, xmax), rng.uniform(ymin, ymax), rng.uniform(-math.pi, math.pi)
        xy = torch.tensor([x, y], dtype=torch.float64)
        if math.hypot(x - spec.goal[0], y - spec.goal[1]) < spec.min_goal_distance:
            continue
        if _clearance(env, xy) < cfg.clearance:
            continue
        out.append((round(x, 4), round(y, 4), round(th, 4)))
    raise RuntimeError(f"could not draw {cfg.starts} starts in {name} with clearance {cfg.clearance} m")


def time_limit(cfg: ClutteredConfig, name: str, speed: float) -> float:
    """``factor * (width + height) / speed`` of the arena (s)."""
    xmin, ymin, xmax, ymax = ENVIRONMENTS[name].bounds
    return cfg.time_limit_factor * ((xmax - xmin) + (ymax - ymin)) / speed


SEED_STRIDE = 100000
"""controller seeds of repeat r are ``SEED_STRIDE * r`` above repeat 0's"""


def controller_seed(cfg: ClutteredConfig, env_index: int, start: int, rep: int = 0) -> int:
    """The controller seed of one run: ``seed + 1 + 1000 * env index + start + SEED_STRIDE * rep`` (the same for
    every method and N; ``rep = 0`` is the default, one-seed-per-start experiment's)."""
    return cfg.seed + 1 + 1000 * env_index + start + SEED_STRIDE * rep


def episodes(cfg: ClutteredConfig, methods: list[str], speed: float) -> list[Episode]:
    reps = cfg.seeds_per_start
    check_positive_int("seeds_per_start", reps, integral=False)
    if cfg.starts > 1000:
        raise ValueError(f"at most 1000 starts per environment (controller seeds would repeat), got {cfg.starts}")
    out = []
    for name in cfg.environments:
        ei = list(ENVIRONMENTS).index(name)
        env, spec, limit = make_env(name), ENVIRONMENTS[name], time_limit(cfg, name, speed)
        for s, pose in enumerate(start_poses(cfg, name)):
            for r in range(reps):
                tags = {"env": name, "start": s} if reps == 1 else {"env": name, "start": s, "rep": r}
                for n in cfg.samples:
                    for m in methods:
                        out.append(Episode(m, n, env, pose, spec.goal, cfg.goal_tolerance, limit,
                                           seed=controller_seed(cfg, ei, s, r), horizon=cfg.horizon, tags=tags))
    return out


def run(cfg: ClutteredConfig, sources: Sources, progress: bool = True, record_paths: bool = True,
        workers: int = 1) -> dict:
    """Run the experiment; a JSON-ready dict (config, geometry, starts, per-episode records, summary)."""
    t0 = time.perf_counter()
    unknown = [e for e in cfg.environments if e not in ENVIRONMENTS]
    if unknown:
        raise ValueError(f"unknown environment(s) {unknown}; choose from {list(ENVIRONMENTS)}")
    methods = [m.key for m in usable_methods(cfg.methods, sources, requested=cfg.methods is not None,
                                              include_slow=cfg.include_mlp)]
    speed = float(getattr(sources.system, "speed", 1.0))
    records = run_episodes(episodes(cfg, methods, speed), sources, cfg, record_paths=record_paths,
                           progress=progress, workers=workers, desc="cluttered")
    return {
        "experiment": "cluttered",
        "config": asdict(cfg),
        "geometry": {e: ENVIRONMENTS[e].describe() for e in cfg.environments},
        "time_limits": {e: time_limit(cfg, e, speed) for e in cfg.environments},
        "starts": {e: start_poses(cfg, e) for e in cfg.environments},
        "methods": methods,
        "records": records,
        "summary": aggregate(records, ("env", "num_samples", "method")),
        "seconds": round(time.perf_counter() - t0, 2),
    }


def _config(results: dict) -> ClutteredConfig:
    return cli.config_from_json(ClutteredConfig, results["config"])


def _fmt(v: float | None, unit: str) -> str:
    return "-" if v is None else f"{v:.1f} {unit}"


def markdown(results: dict) -> str:
    """Per environment: success rates (rows = methods, columns = N) beside the paper's, then the mean time to
    goal and path length of the successful runs."""
    cfg = _config(results)
    rows = results["summary"]
    reps = cfg.seeds_per_start
    runs = "" if reps == 1 else (f", each run under {reps} controller seeds (success rates pool the "
                                 f"{cfg.starts} x {reps} runs; the interval is over these fixed starts)")
    out = ["### Cluttered environments (Table III)", "",
           f"{cfg.starts} random start poses per environment (seed {cfg.seed}, >= {cfg.clearance} m from obstacles "
           f"and walls){runs}, goal tolerance {cfg.goal_tolerance} m, horizon {cfg.horizon} steps, lambda "
           f"{cfg.lambda_}. "
           "Success rate with its 95% Wilson interval; the paper's MPPI / log-MPPI columns do not name a noise "
           "level; its C-Uniform column is our `cu_table`.", ""]
    for name in cfg.environments:
        paper = {n: {fam: v.get(n) for fam, v in config.PAPER_CLUTTERED.get(name, {}).items()} for n in cfg.samples}
        starts = ", ".join(f"({x:.2f}, {y:.2f}, {th:.2f})" for x, y, th in results["starts"][name])
        out += [f"**{name}**: {results['geometry'][name]}; time limit {results['time_limits'][name]:g} s; "
                f"starts (x, y, theta): {starts}", ""]
        out.append(success_markdown(rows, results["methods"], "num_samples", list(cfg.samples),
                                    [f"N = {n}" for n in cfg.samples], paper, where={"env": name}))
        out += ["", f"Mean time to goal / path length over the successful runs ({name}):", ""]
        at = {(r["method"], r["num_samples"]): r for r in rows if r["env"] == name}
        times = [[METHODS[m].label, *("-" if (m, n) not in at else f"{_fmt(at[m, n]['mean_time'], 's')} / "
                                      f"{_fmt(at[m, n]['mean_path_length'], 'm')}" for n in cfg.samples)]
                 for m in results["methods"]]
        out += [md_table(["method", *(f"N = {n}" for n in cfg.samples)], times), ""]
        if reps > 1:
            out += [f"Per start ({name}): runs that reached the goal out of {reps} controller seeds "
                    "(c: collisions, t: timeouts):", "", per_start_markdown(results, name), ""]
    out.append(f"Run time: {results['seconds']:.0f} s for {len(results['records'])} episodes.")
    return "\n".join(out)


def per_start_markdown(results: dict, name: str) -> str:
    """A table with one row per (method, N) and one column per start of ``name``: successes out of the runs
    from that start (``k/R``), with the collisions and timeouts among the failures."""
    cfg = _config(results)
    recs = [r for r in results["records"] if r["env"] == name]

    def cell(rs: list[dict]) -> str:
        ok, c, t = (sum(r["success"] for r in rs), sum(r["outcome"] == "collision" for r in rs),
                    sum(r["outcome"] == "timeout" for r in rs))
        return f"{ok}/{len(rs)}" + (f" ({c}c {t}t)" if ok < len(rs) else "")

    body = [[METHODS[m].label, n, *(cell([r for r in recs if r["method"] == m and r["num_samples"] == n
                                          and r["start"] == s]) for s in range(cfg.starts))]
            for m in results["methods"] for n in cfg.samples]
    return md_table(["method", "N", *(f"start {s}" for s in range(cfg.starts))], body)


def figures(results: dict, outdir: Path) -> list[Path]:
    """Closed-loop paths per method, one PNG per environment (N = 1000 as in the paper's figure, when run)."""
    cfg = _config(results)
    recs = results["records"]
    if not recs or "path" not in recs[0]:
        return []
    n = 1000 if 1000 in cfg.samples else max(cfg.samples)
    paths = []
    for name in cfg.environments:
        env = make_env(name)
        xmin, ymin, xmax, ymax = env.bounds
        panels = {METHODS[m].label: [r for r in recs if r["method"] == m and r["env"] == name
                                     and r["num_samples"] == n] for m in results["methods"]}
        paths.append(plot_paths(panels, env, Path(outdir) / f"cluttered_{name}_N{n}.png",
                                title=f"{name}: closed-loop paths from {cfg.starts} starts"
                                      + (f" x {cfg.seeds_per_start} seeds" if cfg.seeds_per_start > 1 else "")
                                      + f", N = {n}",
                                xlim=(xmin - 0.2, xmax + 0.2), ylim=(ymin - 0.2, ymax + 0.2)))
    return paths


CONFIG = ClutteredConfig


def _flags(p) -> None:
    cli.add_closed_loop_args(p, ClutteredConfig, only=("starts", "environments", "seeds_per_start"),
                             flags={"environments": "--envs"}, choices={"environments": list(ENVIRONMENTS)},
                             metavars={"seeds_per_start": "R"},
                             help={"seeds_per_start": "controller seeds per start (1: one run per start, as the "
                                                      "paper); the success rates pool starts x R runs"})


def episode_counts(cfg: ClutteredConfig) -> dict[str, int]:
    """The scenario counts that multiply into episodes (with the budgets and methods; ``--no-limit``)."""
    return {"environments": len(cfg.environments), "starts": cfg.starts, "seeds per start": cfg.seeds_per_start}


make_parser, config_from_args, main = cli.entry_points(__name__, _flags, threads=1)


if __name__ == "__main__":
    sys.exit(main())
