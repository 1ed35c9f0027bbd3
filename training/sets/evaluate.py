"""Measure a start-conditioned MLP against its table set at held-out starts: ``python -m training.sets.evaluate``.

Shapes: S starts of the set, H held-out starts, k start dimensions, d state dimensions, C cells, A actions.

::

    python -m training.sets.evaluate --set out/ks_speed_set --policy out/ks_speed_set.policy.pt \\
        --held-out 0.125 0.375 0.625 0.875

For every held-out start (default: the midpoints between the set's neighbouring grid values, on every start
dimension) a table is built there by ``python -m precompute.build --start`` with the set's system, parameters,
horizon and method (cached in ``--cache``; a cached table is reused when its start and system JSON match), and
printed:

* ``KL mlp`` / ``KL set``: the mean over the held-out table's cells (centres) of KL(table || policy), for the
  MLP from that start and for the set (the table of the nearest start, as ``TableSetPolicy`` serves it; a zero
  probability where the held-out row has mass counts as log(1e-30), so this KL is large). ``TV`` is the mean
  total-variation distance of the same rows, bounded by 1. ``levels < T`` restricts both to levels 0..T-1 (the
  rows a rollout draws from; level T's rows are uniform by construction);
* ``coverage``: the cells of L_t (the held-out table's level sets) reached at step t by ``--samples``
  real rollouts from that start, summed over t, as a ratio to the held-out table's own rollouts (seeded alike).

Uniform actions (``unif``) are printed beside them as the reference a C-Uniform policy should beat.

Then the time of one ``CUniformMPPI.command`` with the MLP and with the set (``TableSetPolicy``), for each K of
``--num-samples``: both controllers are called in turn, ``--repeats`` times after ``--warmup`` calls, on one
torch thread, and the medians and their ratio printed. ``--json PATH`` writes every number.
"""

from __future__ import annotations

import itertools
import json
import statistics
import sys
import time
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from cuniform_torch.common.fileio import MAX_JSON_BYTES, read_capped_text, write_json
from cuniform_torch.controllers.mppi import CUniformMPPI
from cuniform_torch.policies.checkpoint import load_policy
from cuniform_torch.policies.start_mlp import StartMLPPolicy
from cuniform_torch.policies.table import UniformPolicy
from cuniform_torch.policies.table_set import SET_INDEX, TableSetPolicy, load_table_set
from cuniform_torch.tables.file import Table, TableError, read_table
from precompute.cli import ArgumentParser, check_output_file, cli_main, int_in, non_negative_int, positive_int
from training.tables.evaluate import cell_centres, coverage_comparison, policy_log_probs
from training.tables.train_state import UsageError

__all__ = ["default_held_out", "held_out_table", "row_distances", "evaluate_start", "time_commands", "main"]


def default_held_out(starts: np.ndarray) -> np.ndarray:
    """The midpoints between neighbouring distinct values of each column of ``starts [S, k]``, crossed:
    ``[H, k]`` (a 1-D grid 0, 0.25, ..., 1 gives 0.125, 0.375, 0.625, 0.875)."""
    mids = []
    for column in starts.T:
        v = np.unique(column)
        if len(v) < 2:
            raise UsageError("a start dimension of the set holds one value: give --held-out")
        mids.append((v[:-1] + v[1:]) / 2)
    return np.array(list(itertools.product(*mids)), dtype=np.float64)


def held_out_table(tset: TableSetPolicy, index: dict[str, Any], start: np.ndarray, cache: Path) -> Table:
    """The table built from ``start [d]`` with the set's settings, read from ``cache`` when it is there."""
    first = tset.members[0].table
    path = cache / ("start_" + "_".join(f"{v:g}" for v in start) + ".npz")
    if not path.exists():
        from precompute.coverage.method import CoverageConfig
        from precompute.flow.builder import BuildConfig
        from precompute.one_table import TableJob, build_table_file

        info = json.loads(first.build_info) if isinstance(first.build_info, str) else (first.build_info or {})
        settings = {k: info[k] for k in ("points", "points_per_cell", "seed", "ties") if info.get(k) is not None}
        where = tuple(float(v) for v in start)
        build = BuildConfig(horizon=first.horizon, start=where, **settings)  # the set's settings, another start
        coverage = (CoverageConfig(horizon=first.horizon, start=where) if index.get("method") == "coverage"
                    else None)
        build_table_file(TableJob(system=tset.system, out=path, build=build, coverage=coverage,
                                  report=False, quiet=True))
    table = read_table(path, graph=False)
    if json.loads(table.system) != json.loads(first.system) or table.start is None \
            or not np.array_equal(table.start, start):
        raise TableError(f"{path}: not the set's system built from {start.tolist()} (remove it to rebuild)")
    return table


def row_distances(policy: Any, table: Table, levels: int) -> tuple[float, float]:
    """Mean over the cells of levels ``0..levels-1`` of KL(table || policy) and of the total-variation distance,
    at the cell centres."""
    centres = cell_centres(table)
    kl_sum, tv_sum, n = 0.0, 0.0, 0
    for t in range(levels):
        rows = table.level(t)
        x = centres[rows].to(dtype=policy.dtype, device=policy.device)
        log_q = policy_log_probs(policy, x, t).double().cpu()  # [C_t, A]
        p = torch.from_numpy(table.action_probs[rows]).double()
        kl_sum += float((torch.xlogy(p, p) - torch.where(p > 0, p * log_q, 0.0)).sum())
        tv_sum += float(0.5 * (p - log_q.exp()).abs().sum())
        n += p.shape[0]
    return kl_sum / n, tv_sum / n


def evaluate_start(mlp: StartMLPPolicy, tset: TableSetPolicy, table: Table, samples: int, seed: int) -> dict[str, Any]:
    """KL, TV and coverage ratio of the MLP, of the set and of uniform actions at one held-out table's start
    (module docstring)."""
    x0 = torch.from_numpy(table.start).to(dtype=mlp.dtype, device=mlp.device)
    mlp.for_start(x0)
    nearest = tset.for_start(x0)
    out: dict[str, Any] = {"start": table.start.tolist(), "cells": int(table.cells.shape[0]),
                           "nearest_start": tset.starts[tset.last_index].tolist()}
    T = table.horizon
    uniform = UniformPolicy(mlp.system, device=mlp.device, dtype=mlp.dtype)
    for name, pol in (("mlp", mlp), ("set", nearest), ("uniform", uniform)):
        kl_all, tv_all = row_distances(pol, table, T + 1)
        kl_roll, tv_roll = row_distances(pol, table, T)
        with warnings.catch_warnings():  # the nearest table warns that it is not this start's: that is the point
            warnings.simplefilter("ignore")
            cov = coverage_comparison(tset if name == "set" else pol, table, samples, seed=seed, device=mlp.device)
        out[name] = {"kl": kl_all, "tv": tv_all, "kl_rollout_levels": kl_roll, "tv_rollout_levels": tv_roll,
                     "coverage_ratio": cov["ratio"]["in_level_set_sum"], "coverage_min_level": cov["ratio"]["min_level"],
                     "cells_reached": cov["policy"]["in_level_set_sum"], "table_cells_reached": cov["table"]["in_level_set_sum"]}
    return out


def time_commands(mlp: StartMLPPolicy, tset: TableSetPolicy, start: torch.Tensor, num_samples: Sequence[int],
                  repeats: int, warmup: int) -> list[dict[str, Any]]:
    """Median seconds of ``CUniformMPPI.command`` with the MLP and with the set, called in turn (one thread)."""
    q = min(2, mlp.config.state_dim)  # a goal in (x, y), or x for a 1-D system
    goal = torch.tensor([2.0, 1.0][:q], dtype=mlp.dtype)

    def cost(states: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:  # [K, T+1, d] -> [K]
        return ((states[:, :, :q] - goal) ** 2).sum(dim=(1, 2))

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    rows = []
    try:
        for k in num_samples:
            ctrls = {"mlp": CUniformMPPI(mlp, cost, num_samples=k, seed=0),
                     "set": CUniformMPPI(tset, cost, num_samples=k, seed=0)}
            times: dict[str, list[float]] = {name: [] for name in ctrls}
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                for i in range(warmup + repeats):
                    for name, ctrl in ctrls.items():
                        t0 = time.perf_counter()
                        ctrl.command(start)
                        if i >= warmup:
                            times[name].append(time.perf_counter() - t0)
            med = {name: statistics.median(v) for name, v in times.items()}
            rows.append({"num_samples": k, "mlp_seconds": med["mlp"], "set_seconds": med["set"],
                         "ratio": med["mlp"] / med["set"], "repeats": repeats})
    finally:
        torch.set_num_threads(threads)
    return rows


def make_parser() -> ArgumentParser:
    parser = ArgumentParser(prog="python -m training.sets.evaluate", description=__doc__.splitlines()[0])
    parser.add_argument("--set", required=True, help="the table-set folder the policy was distilled from")
    parser.add_argument("--policy", required=True, help="its checkpoint (python -m training.distill --tables DIR)")
    parser.add_argument("--held-out", nargs="+", default=None, metavar="V[,V...]",
                        help="held-out starts over the start dimensions, comma-separated per start (default: the "
                             "midpoints between the set's grid values)")
    parser.add_argument("--cache", default=None, help="folder of the held-out tables (default: <set>/held_out)")
    parser.add_argument("--samples", type=positive_int, default=1000, help="rollouts N of the coverage comparison")
    parser.add_argument("--num-samples", type=positive_int, nargs="+", default=[256, 1000],
                        help="K of the command timing")
    parser.add_argument("--repeats", type=positive_int, default=30, help="timed commands per controller and K")
    parser.add_argument("--warmup", type=non_negative_int, default=5, help="untimed commands first")
    parser.add_argument("--seed", type=int_in(0, 2**63 - 1), default=0, help="seed of the coverage rollouts")
    parser.add_argument("--json", default=None, help="also write every number to this JSON file")
    return parser


@cli_main()
def main(argv: Sequence[str] | None = None) -> int:
    """Print the held-out comparison and the command times (module docstring); 0, or 2 after ``error: ...``."""
    args = make_parser().parse_args(argv)
    if args.json:
        check_output_file(args.json, "--json", "set_eval.json")
    for name in ("samples", "repeats"):
        if getattr(args, name) < 1:
            raise UsageError(f"--{name} must be a positive integer")
    if any(k < 1 for k in args.num_samples) or args.warmup < 0:
        raise UsageError("--num-samples must be positive and --warmup >= 0")
    folder = Path(args.set)
    tset = load_table_set(folder)
    index = json.loads(read_capped_text(folder / SET_INDEX, MAX_JSON_BYTES, "the table-set index"))
    mlp = load_policy(args.policy)
    if not isinstance(mlp, StartMLPPolicy):
        raise UsageError(f"--policy {args.policy} is not start-conditioned (distil the set folder itself)")
    dims = mlp.region.dims
    if not torch.equal(mlp.region.starts, tset.starts[:, dims]) or mlp.system.name != tset.system.name:
        raise UsageError(f"--policy {args.policy} was trained on other starts than the set {folder}")
    if args.held_out is None:
        held = default_held_out(mlp.region.starts.numpy())
    else:
        try:
            held = np.array([[float(v) for v in item.split(",")] for item in args.held_out], dtype=np.float64)
        except ValueError:
            raise UsageError(f"--held-out: {args.held_out} are not numbers") from None
        if held.ndim != 2 or held.shape[1] != len(dims):
            raise UsageError(f"--held-out: each start needs {len(dims)} value(s), over dimensions {dims}")
    cache = Path(args.cache) if args.cache else folder / "held_out"
    cache.mkdir(parents=True, exist_ok=True)
    results = []
    for values in held:
        start = np.zeros(tset.grid.dim)
        start[dims] = values
        table = held_out_table(tset, index, np.round(start, 12), cache)
        results.append(evaluate_start(mlp, tset, table, args.samples, args.seed))
    mid = torch.tensor(results[len(results) // 2]["start"], dtype=mlp.dtype)  # the timing's start
    timing = time_commands(mlp, tset, mid, args.num_samples, args.repeats, args.warmup)
    print(format_report(results, timing, args.samples))
    if args.json:
        write_json(args.json, {"set": str(folder), "policy": str(args.policy), "held_out": results, "timing": timing,
                               "samples": args.samples, "threads": 1})
    return 0


def format_report(results: list[dict[str, Any]], timing: list[dict[str, Any]], samples: int) -> str:
    """The held-out rows and the command times as text."""
    lines = ["held-out start     cells  nearest start |  KL mlp  KL set KL unif |  TV mlp  TV set TV unif | levels < T: "
             f"KL mlp  KL set | coverage (N={samples}): mlp   set  unif"]
    for r in results:
        m, s, u = r["mlp"], r["set"], r["uniform"]
        start = ",".join(f"{v:g}" for v in r["start"])
        near = ",".join(f"{v:g}" for v in r["nearest_start"])
        lines.append(f"{start:17s} {r['cells']:6d} {near:>14s} | {m['kl']:7.4f} {s['kl']:7.3f} {u['kl']:7.4f} | "
                     f"{m['tv']:7.4f} {s['tv']:7.4f} {u['tv']:7.4f} | {m['kl_rollout_levels']:18.4f} "
                     f"{s['kl_rollout_levels']:7.3f} | {m['coverage_ratio']:20.3f} {s['coverage_ratio']:5.3f} "
                     f"{u['coverage_ratio']:5.3f}")
    lines.append("CUniformMPPI.command, median of the timed calls, torch threads 1:")
    for row in timing:
        lines.append(f"  K = {row['num_samples']:5d}: MLP {row['mlp_seconds'] * 1e3:7.3f} ms, table set "
                     f"{row['set_seconds'] * 1e3:7.3f} ms, ratio {row['ratio']:.2f}x ({row['repeats']} calls each)")
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
