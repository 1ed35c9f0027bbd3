"""Shared machinery of the closed-loop experiments (sudden obstacle, cluttered environments).

An :class:`Episode` is one closed-loop run: a method with N samples in one scenario (an environment, a start
pose, a goal) under one controller seed. :func:`run_episodes` drives each through
:func:`cuniform_torch.envs.simulate` with the paper's cost (:class:`cuniform_torch.envs.NavigationCost`:
squared distance to the goal + a collision penalty, both ending at a rollout's first arrival at the goal
(``stop_at_goal``, as the authors' controllers do: their ROS C-Uniform node breaks out of the horizon loop
there, their C-Free-Uniform planner zeroes the obstacle cost from the goal on), told the time every cycle so
that an obstacle counts only once it is sensed) and returns one JSON-ready record per run. :func:`aggregate` turns records into success rates with
95% Wilson intervals, mean time to goal and mean path length (both over successful runs);
:func:`success_markdown` renders them with the paper's values alongside; :func:`plot_paths` draws the
closed-loop paths per method.

Every controller knob is the same for every method: lambda (``config.LAMBDA``), horizon, N, the cost, the
goal tolerance and the time limit. Method-specific settings are the registry's (``eval.methods``): the
baselines' noise level is part of the method, CU-MPPI keeps its reference defaults.

The paper's columns are MPPI, log-MPPI and C-Uniform without a noise level for the baselines (its Sigma
list names low/medium/high only for the tables that show them), so we print all three of our levels
for each baseline family and put the paper's number on its own row. The paper's C-Uniform column is our
``cu_table`` (the max-flow table on real rollouts); ``cu_coverage``, ``cu_mlp``, ``cumppi`` and ``uniform``
are ours and have no paper number.
"""

from __future__ import annotations

import math
import time
from collections import defaultdict
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Iterable, Sequence

import torch

from cuniform_torch.envs import Circle, Environment, NavigationCost, Polygon, Rect, simulate

from cuniform_torch.fileio import write_json

from . import config
from .cli import add_source_args
from .methods import METHODS, Method, Sources, make_controller, parse_methods

__all__ = [
    "Episode", "run_episodes", "wilson_interval", "aggregate", "usable_methods", "paper_label",
    "success_markdown", "fmt_rate", "plot_paths", "SLOW_METHODS", "ControllerSettings", "add_common_args",
    "config_from_args", "config_from_json", "finish_cli", "PAPER_FAMILY_OF", "OUTCOME_COLORS",
]

PAPER_FAMILY_OF = {"mppi": "MPPI", "log_mppi": "log-MPPI", "cuniform": "C-Uniform"}
"""the paper's column names, keyed by ``Method.family``"""
PAPER_METHOD = "cu_table"
"""our method that is the paper's C-Uniform column (the max-flow table on real rollouts)"""
OUTCOME_COLORS = {"goal": "tab:green", "collision": "tab:red", "timeout": "tab:orange"}


@dataclass(frozen=True)
class ControllerSettings:
    """The closed-loop settings both experiments share (each experiment's config adds its scenario)."""

    goal_tolerance: float = 0.3
    """m: the goal is reached within this xy distance (also the cost's cut-off)"""
    horizon: int = 15
    """controller horizon in steps (3 s)"""
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
    """registry key (``eval.methods.METHODS``)"""
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


SLOW_METHODS = ("cu_mlp",)
"""left out of a default run (``keys=None``) unless asked for: on a 2-core CPU the distilled MLP costs about
10x the table lookup per control cycle (it took about 280 s of the cluttered run and 200 s of the sudden-obstacle
run, as much as all other methods together)"""


def usable_methods(keys: Sequence[str] | None, sources: Sources, requested: bool,
                   include_slow: bool = False) -> list[Method]:
    """The closed-loop methods among ``keys`` (None: all but :data:`SLOW_METHODS`, unless ``include_slow``)
    whose source files exist.

    Every method needs the table (the system comes from it); ``cu_coverage`` and ``cu_mlp`` need their own file
    too. A method whose file is missing is dropped with a printed note, unless the user named it
    (``requested``): then it raises ``FileNotFoundError``.
    """
    methods = parse_methods(list(keys) if keys is not None else None, closed_loop=True)
    if keys is None and not include_slow:
        slow = [m.key for m in methods if m.key in SLOW_METHODS]
        if slow:
            print(f"note: leaving out {', '.join(slow)} (slow on CPU; ask for it with --mlp or --methods)")
        methods = [m for m in methods if m.key not in SLOW_METHODS]
    extra = {"cu_coverage": sources.coverage_table, "cu_mlp": sources.policy}
    kept = []
    for m in methods:
        missing = [p for p in (sources.table, extra.get(m.key)) if p is not None and not Path(p).exists()]
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


def run_episodes(episodes: Sequence[Episode], sources: Sources, settings: ControllerSettings,
                 record_paths: bool = True, progress: bool = True, desc: str = "episodes") -> list[dict]:
    """Run every episode; one record per episode (plain JSON types).

    The controllers use ``settings.lambda_``; the cost is :class:`~cuniform_torch.envs.NavigationCost` with
    ``settings.collision_penalty`` per colliding state (``per_state``, the paper's per-state obstacle cost summed
    over the horizon) or once per colliding rollout, both cost terms ending at a rollout's first arrival at the
    goal (``stop_at_goal``; False: collisions after it count too).

    Record: the episode's ``tags``, ``method``, ``num_samples``, ``seed``, ``x0``, ``goal``, ``outcome``
    ("goal" / "collision" / "timeout"), ``success``, ``time`` (s, simulated), ``path_length`` (m), ``steps``,
    ``wall_s`` (seconds of compute) and, with ``record_paths``, ``path`` (``[[x, y], ...]``, start included).
    """
    from tqdm.auto import tqdm

    system = sources.system
    out = []
    for ep in tqdm(episodes, desc=desc, disable=not progress, leave=False):
        method = METHODS[ep.method]
        cost = NavigationCost(ep.env, ep.goal, goal_tolerance=ep.goal_tolerance,
                              collision_penalty=settings.collision_penalty, per_state=settings.per_state,
                              stop_at_goal=settings.stop_at_goal)
        ctrl = make_controller(method, sources, cost, ep.num_samples, ep.horizon, ep.seed, lambda_=settings.lambda_)
        x0 = torch.tensor(ep.x0, dtype=torch.float32, device=sources.device)
        t0 = time.perf_counter()
        res = simulate(system, ctrl, x0, ep.env, ep.goal, ep.goal_tolerance, ep.time_limit, cost=cost,
                       record=record_paths)
        rec = dict(ep.tags)
        rec.update(method=ep.method, num_samples=ep.num_samples, seed=ep.seed, x0=list(ep.x0), goal=list(ep.goal),
                   outcome=res.outcome, success=res.success, time=round(res.time, 6),
                   path_length=round(res.path_length, 6), steps=res.steps,
                   wall_s=round(time.perf_counter() - t0, 4))
        if record_paths:
            rec["path"] = _path_list(res.path.cpu())
        out.append(rec)
    return out


def wilson_interval(successes: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """Wilson score interval ``(low, high)`` for a binomial proportion; ``(0, 1)`` for ``n = 0``."""
    if n < 0 or successes < 0 or successes > n:
        raise ValueError(f"need 0 <= successes <= n, got successes={successes}, n={n}")
    if n == 0:
        return 0.0, 1.0
    p = successes / n
    denom = 1.0 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    return max(0.0, centre - half), min(1.0, centre + half)


def _mean(values: list[float]) -> float | None:
    return sum(values) / len(values) if values else None


def aggregate(records: Iterable[dict], keys: Sequence[str]) -> list[dict]:
    """Group records by ``keys`` (e.g. ``("appear", "num_samples", "method")``) and summarize each group.

    Per group: ``n``, ``successes``, ``success_rate``, ``ci_low`` / ``ci_high`` (95% Wilson), ``collisions``,
    ``timeouts``, ``mean_time`` and ``mean_path_length`` over the successful runs (None without one),
    ``wall_s`` (total compute seconds). Groups keep the order in which they first appear.
    """
    groups: dict[tuple, list[dict]] = defaultdict(list)
    for r in records:
        groups[tuple(r[k] for k in keys)].append(r)
    rows = []
    for key, recs in groups.items():
        n = len(recs)
        good = [r for r in recs if r["success"]]
        lo, hi = wilson_interval(len(good), n)
        row = dict(zip(keys, key))
        row.update(n=n, successes=len(good), success_rate=len(good) / n, ci_low=lo, ci_high=hi,
                   collisions=sum(r["outcome"] == "collision" for r in recs),
                   timeouts=sum(r["outcome"] == "timeout" for r in recs),
                   mean_time=_mean([r["time"] for r in good]),
                   mean_path_length=_mean([r["path_length"] for r in good]),
                   wall_s=sum(r.get("wall_s", 0.0) for r in recs))
        rows.append(row)
    return rows


def paper_label(method_key: str) -> str:
    """How an our-method row relates to the paper's columns (for the tables' second column)."""
    m = METHODS[method_key]
    if m.family in ("mppi", "log_mppi"):
        return f"{PAPER_FAMILY_OF[m.family]} (one of our noise levels)"
    if method_key == PAPER_METHOD:
        return "C-Uniform (the paper's method)"
    return "ours, no paper column"


def fmt_rate(row: dict | None, with_ci: bool = True) -> str:
    if row is None:
        return "-"
    s = f"{row['success_rate']:.2f}"
    if with_ci:
        s += f" [{row['ci_low']:.2f}, {row['ci_high']:.2f}]"
    return s


def success_markdown(rows: list[dict], methods: Sequence[str], column_key: str, columns: Sequence[Any],
                     column_labels: Sequence[str], paper: dict | None, where: dict | None = None,
                     with_ci: bool = True) -> str:
    """A markdown table: one row per method, one column per value of ``column_key``, cells = success rate
    with its 95% Wilson interval; then one row per paper family with the paper's value in that column.

    ``rows``: :func:`aggregate` output; ``where``: other keys every used row must match (e.g. ``{"num_samples":
    500}``); ``paper``: ``{column value: {family: rate}}`` (None or missing entries: "-").
    """
    where = where or {}

    def find(method: str, col: Any) -> dict | None:
        for r in rows:
            if r["method"] == method and r[column_key] == col and all(r.get(k) == v for k, v in where.items()):
                return r
        return None

    head = ["method", "paper column"] + list(column_labels)
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for m in methods:
        cells = [fmt_rate(find(m, c), with_ci) for c in columns]
        lines.append(f"| {METHODS[m].label} | {paper_label(m)} | " + " | ".join(cells) + " |")
    if paper:
        for fam, name in PAPER_FAMILY_OF.items():
            vals = []
            for c in columns:
                v = (paper.get(c) or {}).get(fam)
                vals.append("-" if v is None else f"{v:.2f}")
            lines.append(f"| **paper: {name}** | {name} | " + " | ".join(vals) + " |")
    return "\n".join(lines)


# ------------------------------------------------------------------------------------------------ figures

def _draw_obstacle(ax, obs, **kw) -> None:
    from matplotlib import patches

    if isinstance(obs, Circle):
        ax.add_patch(patches.Circle(obs.center, obs.radius, **kw))
    elif isinstance(obs, Rect):
        ax.add_patch(patches.Rectangle((obs.xmin, obs.ymin), obs.xmax - obs.xmin, obs.ymax - obs.ymin, **kw))
    elif isinstance(obs, Polygon):
        v = torch.as_tensor(obs.vertices).tolist()
        ax.add_patch(patches.Polygon(v, closed=True, **kw))
    else:
        raise ValueError(f"cannot draw obstacle of type {type(obs).__name__}")


def plot_paths(panels: dict[str, list[dict]], envs: dict[str, Environment] | Environment, out: Path,
               title: str = "", goal_tolerance: float | None = None,
               xlim: tuple[float, float] | None = None, ylim: tuple[float, float] | None = None) -> Path:
    """One subplot per method (``panels``: label -> records with ``path``, ``outcome``, ``goal`` and, when
    ``envs`` is a dict, an ``env`` key naming its environment); paths coloured by outcome (green goal, red
    collision, orange timeout), obstacles grey, starts as dots, goals as stars. Saves a PNG to ``out``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    n = max(1, len(panels))
    ncols = min(4, n)
    nrows = math.ceil(n / ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(3.6 * ncols, 3.4 * nrows), squeeze=False)
    for ax in axes.flat[n:]:
        ax.axis("off")
    for ax, (label, recs) in zip(axes.flat, panels.items()):
        drawn = set()
        for r in recs:
            env = envs[r["env"]] if isinstance(envs, dict) else envs
            if id(env) not in drawn:
                drawn.add(id(env))
                alpha = 0.6 if len(drawn) == 1 or not isinstance(envs, dict) else max(0.08, 0.6 / len(recs) * 2)
                for obs in env.obstacles:
                    _draw_obstacle(ax, obs, facecolor="0.55", edgecolor="0.3", alpha=alpha, lw=0.5)
                if env.bounds is not None:
                    xmin, ymin, xmax, ymax = env.bounds
                    ax.plot([xmin, xmax, xmax, xmin, xmin], [ymin, ymin, ymax, ymax, ymin], color="k", lw=1)
            p = r.get("path")
            if p:
                xs, ys = zip(*p)
                ax.plot(xs, ys, color=OUTCOME_COLORS.get(r["outcome"], "k"), lw=1.0, alpha=0.8)
                ax.plot(xs[0], ys[0], "o", color="k", ms=2.5)
            ax.plot(*r["goal"], marker="*", color="gold", mec="k", ms=11, zorder=5)
        ok = sum(r["success"] for r in recs)
        ax.set_title(f"{label}\n{ok}/{len(recs)} reached the goal", fontsize=8)
        ax.set_aspect("equal")
        if xlim:
            ax.set_xlim(*xlim)
        if ylim:
            ax.set_ylim(*ylim)
        ax.tick_params(labelsize=6)
    handles = [Line2D([], [], color=c, label=k) for k, c in OUTCOME_COLORS.items()]
    fig.legend(handles=handles, loc="lower right", fontsize=8, ncol=3)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


# ------------------------------------------------------------------------------------------------ CLI

def add_common_args(parser) -> None:
    """The flags both closed-loop modules share (sources default to the 3 s tables)."""
    add_source_args(parser, horizon15=True)
    parser.add_argument("--methods", nargs="+", default=None,
                        help="method keys (default: every closed-loop method whose files exist)")
    parser.add_argument("--samples", type=int, nargs="+", default=None, help="N, trajectories per control cycle")
    parser.add_argument("--json", type=Path, default=None, help="write the results here")
    parser.add_argument("--figures", type=Path, default=None, help="write PNG figures into this folder")
    parser.add_argument("--seed", type=int, default=None, help="override the config's seed")
    parser.add_argument("--horizon", type=int, default=None, help="controller horizon in steps (default 15; at "
                        "most the table's)")
    parser.add_argument("--mlp", action="store_true", help="also run cu_mlp in a default run (slow on CPU)")
    parser.add_argument("--collisions-after-goal", action="store_true",
                        help="charge a rollout's collisions after its arrival at the goal too (the plain "
                        "NavigationCost; default: the cost ends at the goal, NavigationCost.stop_at_goal)")
    parser.add_argument("--quick", action="store_true", help="tiny sizes (a few seconds)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def config_from_args(cfg: ControllerSettings, args, **experiment_flags) -> ControllerSettings:
    """``cfg`` with the flags that were given: the common ones plus ``experiment_flags`` (name -> value; lists
    become tuples, None means "not given")."""
    given = dict(samples=args.samples, horizon=args.horizon, methods=args.methods, seed=args.seed,
                 include_mlp=args.mlp or None, stop_at_goal=False if args.collisions_after_goal else None,
                 **experiment_flags)
    return replace(cfg, **{k: tuple(v) if isinstance(v, list) else v for k, v in given.items() if v is not None})


def config_from_json(cls: type, values: dict):
    """A config dataclass from its ``asdict`` JSON (lists back to tuples)."""
    return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in values.items()})


def finish_cli(args, results: dict, markdown_fn, figures_fn) -> None:
    """Print the markdown, write the JSON (atomically) and the figures as the flags ask."""
    print(markdown_fn(results))
    if args.json is not None:
        write_json(args.json, results)
        print(f"\nwrote {args.json}")
    if args.figures is not None:
        for p in figures_fn(results, args.figures):
            print(f"wrote {p}")
