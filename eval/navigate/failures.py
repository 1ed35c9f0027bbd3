"""Why the benchmark's episodes failed: trapped, a sampling miss, or lost.

    python -m eval.navigate failures --out out/navigate/clutter-test-100 --budgets 256 --map-policy FILE

Replays every failed episode of a benchmark folder (:func:`eval.navigate.replay.replay_episode`, optionally only some
methods and budgets) and sorts each failure into one of three kinds:

* **trapped**: a collision, and at the first command after which every proposal of the controller collided,
  ``--probe-samples`` C-Uniform rollouts of the robot's max-flow table (a dense, even cover of the reachable set
  at the controller's horizon) found no collision-free trajectory either: from that state no sampler at this
  horizon could have escaped. The episode was lost earlier, when a trajectory that was free for the horizon led
  into a pocket the robot, at constant speed, cannot turn in; ``trapped_s`` says how long before the collision;
* **missed**: a collision where the probe did find a free trajectory that the controller's own proposals missed
  (a sampling failure; a controller that had free proposals at its last command and still collided, through the
  weighted average, counts here too);
* **lost**: a timeout (the robot circles in a local minimum of the goal-distance cost).

A sampler can only turn *missed* failures into successes; *trapped* and *lost* ones are the cost's and horizon's
(the same for every method). Prints one row per (method, budget) and, with ``--json``, every episode's kind.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import torch

from cuniform_torch import CUniformMPPI
from cuniform_torch.common.fileio import write_json
from cuniform_torch.envs import NavigationCost
from eval.navigate.episode import NavContext, context_sources, cost_environment
from eval.navigate.records import load_folder
from eval.navigate.replay import compare_records, replay_episode, summarize
from precompute.cli import MAX_COUNT, ArgumentParser, check_output_file, cli_main, int_in, positive_int

__all__ = ["FailureKind", "classify", "probe_free_share", "failure_table", "main"]

PROBE_SAMPLES = 4096
"""C-Uniform rollouts of the trap probe (module docstring)"""


@dataclass(frozen=True)
class FailureKind:
    """One failed episode's anatomy."""

    key: str
    outcome: str
    """collision or timeout"""
    kind: str
    """trapped, missed or lost (module docstring)"""
    trapped_s: float | None
    """s before the collision of the first command whose proposals all collided (None: not a collision, or its
    last command had a free proposal)"""
    probe_free_share: float | None
    """the probe's collision-free share at that command's state (None: not probed)"""


def probe_free_share(task, state: list[float], ctx: NavContext, samples: int = PROBE_SAMPLES, seed: int = 0) -> float:
    """The share of ``samples`` C-Uniform rollouts (the max-flow table of ``ctx``) from ``state [d]`` that are
    collision-free for the horizon, against the obstacles the robot senses there (the benchmark's cost)."""
    cost = NavigationCost(cost_environment(task, ctx), task.goal, goal_tolerance=task.goal_tolerance,
                          collision_penalty=ctx.collision_penalty, per_state=True, stop_at_goal=True)
    x = torch.tensor(state, dtype=torch.float32)
    if task.sensing_range is not None:
        cost.env = task.sensed_environment(x[:2])
    probe = CUniformMPPI(context_sources(ctx).load("table"), cost, samples, lambda_=0.0, horizon=ctx.horizon, seed=seed)
    states, actions = probe.propose(x)
    return float((cost(states, actions) < ctx.collision_penalty).float().mean())


def classify(record: dict, trace: list[dict], task, ctx: NavContext, samples: int = PROBE_SAMPLES) -> FailureKind:
    """The kind of a failed episode from its replayed ``record`` and per-command ``trace`` (module docstring)."""
    if record["outcome"] == "timeout":
        return FailureKind(record["key"], "timeout", "lost", None, None)
    if record["outcome"] != "collision":
        raise ValueError(f"{record['key']} did not fail (outcome {record['outcome']!r})")
    if not trace:
        raise ValueError(f"{record['key']}: its controller has no per-command trace (no plan()): cannot classify")
    s = summarize(record, trace)
    if s["trapped_commands"] == 0:  # free proposals at the last command: the controller's choice collided
        return FailureKind(record["key"], "collision", "missed", None, None)
    first = len(trace) - s["trapped_commands"]  # the first command of the final all-colliding run
    share = probe_free_share(task, trace[first]["state"], ctx, samples)
    trapped_s = round(record["time"] - trace[first]["t"], 6)
    return FailureKind(record["key"], "collision", "trapped" if share == 0 else "missed", trapped_s, share)


def failure_table(kinds: Sequence[FailureKind], totals: dict[tuple[str, int], int]) -> str:
    """A markdown table: per (method, budget) the episodes, failures and their kinds, median trapped time."""
    rows = ["| method | K | episodes | failed | trapped | missed | lost | median trapped s |",
            "|---|---|---|---|---|---|---|---|"]
    by_cell: dict[tuple[str, int], list[FailureKind]] = {}
    for k in kinds:  # key: suite/task_id/method/budget/repeat
        _, _, method, budget, _ = k.key.split("/")
        by_cell.setdefault((method, int(budget)), []).append(k)
    for (method, budget), n in sorted(totals.items()):
        mine = by_cell.get((method, budget), [])
        count = {c: sum(1 for k in mine if k.kind == c) for c in ("trapped", "missed", "lost")}
        ts = sorted(k.trapped_s for k in mine if k.kind == "trapped")
        med = f"{ts[len(ts) // 2]:.1f}" if ts else "-"
        rows.append(f"| {method} | {budget} | {n} | {len(mine)} | {count['trapped']} | {count['missed']} | "
                    f"{count['lost']} | {med} |")
    return "\n".join(rows)


def make_parser() -> ArgumentParser:
    p = ArgumentParser(prog="python -m eval.navigate failures", description=(__doc__ or "").split("\n\n")[0])
    p.add_argument("--out", type=Path, required=True, help="the benchmark folder (python -m eval.navigate --out)")
    p.add_argument("--methods", nargs="+", default=None, help="only these methods (default: every one in the folder)")
    p.add_argument("--budgets", nargs="+", type=int_in(2, MAX_COUNT), default=None,
                   help="only these budgets (default: all)")
    p.add_argument("--probe-samples", type=positive_int, default=PROBE_SAMPLES,
                   help=f"C-Uniform rollouts of the trap probe (default: {PROBE_SAMPLES})")
    p.add_argument("--cache", type=Path, default=Path("out/navigate/cache"),
                   help="where the robot's tables are kept (default: out/navigate/cache)")
    for flag, what in (("table", "max-flow table"), ("coverage-table", "coverage table (cu_coverage)"),
                       ("policy", "distilled MLP (cu_mlp)"), ("map-policy", "map-conditioned policy (cfu_mppi)"),
                       ("barn-file", "BARN maps")):
        p.add_argument(f"--{flag}", type=Path, default=None, help=f"the run's {what} (as eval.navigate.replay)")
    p.add_argument("--json", type=Path, default=None, help="also write every failed episode's kind here")
    return p


@cli_main()
def main(argv: Sequence[str] | None = None) -> int:
    args = make_parser().parse_args(argv)
    if args.json is not None:
        check_output_file(args.json, "--json", "failures.json")
    if args.probe_samples < 1:
        raise ValueError(f"--probe-samples must be >= 1, got {args.probe_samples}")
    _, records = load_folder(args.out)
    chosen = [r for r in records.values() if (args.methods is None or r["method"] in args.methods)
              and (args.budgets is None or r["budget"] in args.budgets)]
    if not chosen:
        raise ValueError(f"no episode of {args.out} matches --methods {args.methods} --budgets {args.budgets}")
    totals: dict[tuple[str, int], int] = {}
    for r in chosen:
        totals[(r["method"], r["budget"])] = totals.get((r["method"], r["budget"]), 0) + 1
    given = {"table": args.table, "coverage_table": args.coverage_table, "policy": args.policy,
             "map_policy": args.map_policy}
    failed = sorted((r for r in chosen if not r["success"]), key=lambda r: r["key"])
    print(f"{len(failed)} failed episodes of {len(chosen)} in {args.out}; replaying each", flush=True)
    kinds, differ = [], []
    from tqdm import tqdm

    for r in tqdm(failed, desc="failures", disable=not sys.stderr.isatty()):
        got = replay_episode(args.out, r["key"], given, args.cache, args.barn_file)
        if compare_records(got["stored"], got["replayed"]):
            differ.append(r["key"])
        kinds.append(classify(got["replayed"], got["trace"], got["task"], got["ctx"], args.probe_samples))
    print(failure_table(kinds, totals))
    if differ:
        print(f"warning: {len(differ)} replays did not reproduce their records (e.g. {differ[0]}): their kinds are "
              "the replay's")
    if args.json is not None:
        write_json(args.json, dict(folder=str(args.out), probe_samples=args.probe_samples, not_reproduced=differ,
                                   failures=[k.__dict__ for k in kinds]))
        print(f"wrote {args.json}")
    return 0
