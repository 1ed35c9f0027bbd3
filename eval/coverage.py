"""Coverage (the paper's Table I): distinct cells visited by N trajectories of each method, mean +- std over seeds.

    python -m eval.coverage                                  # every open-loop method, N = 250 ... 10000, 5 seeds
    python -m eval.coverage --methods cu_table cu_coverage --samples 1000 --seeds 3 --json out/coverage.json

N trajectories of the table's horizon (10 steps = 2 s on the default preset) from the start pose (0, 0, 0);
baselines sample around a zero nominal (a first solve). Coverage = distinct (x, y, theta) cells visited by any
trajectory at any step, start included (the reference release's definition), on the default table's grid. It
is reported as a count, as % of the cells real rollouts can reach (exhaustive enumeration of every action
sequence, :mod:`eval.reachable`), as % of the union of the table's level sets, and as % of the ideal ceiling:
N perfectly uniform draws over the reachable cells of every level, ``sum_t n_t (1 - (1 - 1/n_t)^N)``. Per-level
coverage is kept in the JSON. The paper's Table I counts are printed beside ours (its C-Uniform column is
graph sampling, ``cu_graph`` here).
"""

from __future__ import annotations

import statistics
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch

from cuniform_torch.cli import ArgumentParser, cli_main
from cuniform_torch.coverage import coverage, uniform_ceiling

from . import config
from .cli import add_source_args, run_experiment
from .methods import Sources, parse_methods, sample_states
from .reachable import reachable


@dataclass
class CoverageConfig:
    """What the coverage experiment runs; the defaults are the paper's Table I."""

    methods: list[str] | None = None
    """method keys (None: every open-loop method)"""
    samples: list[int] = field(default_factory=lambda: [250, 500, 1000, 2500, 5000, 10000])
    seeds: int = 5
    merge_resolution: int = 32
    """sub-cell merging of the reachable-set enumeration"""


def run(cfg: CoverageConfig, sources: Sources, progress: bool = True) -> dict:
    """Run the experiment; returns ``{"config", "reachable", "results": [row per method and N]}``."""
    methods = parse_methods(cfg.methods)
    table = sources.table_policy()
    grid, T = table.grid, table.horizon
    reach = reachable(table.system, T, cfg.merge_resolution)
    level_sets = sum(table.level_size(t) for t in range(T + 1))
    rows = []
    for method in methods:
        start = time.perf_counter()
        for N in cfg.samples:
            totals, per_level = [], []
            for seed in range(cfg.seeds):
                gen = torch.Generator(device=sources.device).manual_seed(seed)
                cov = coverage(sample_states(method, sources, N, T, gen), grid)
                totals.append(cov.total)
                per_level.append(cov.per_level)
            ceiling = sum(uniform_ceiling(n, N) for n in reach.level_sizes)
            mean = statistics.mean(totals)
            rows.append({
                "method": method.key, "label": method.label, "family": method.family, "samples": N,
                "seeds": cfg.seeds, "cells_mean": mean, "cells_std": statistics.stdev(totals) if cfg.seeds > 1 else 0.0,
                "pct_reachable": 100 * mean / reach.total, "pct_level_sets": 100 * mean / level_sets,
                "pct_ceiling": 100 * mean / ceiling, "ceiling": ceiling,
                "per_level_mean": [statistics.mean(c) for c in zip(*per_level)],
                "paper": config.PAPER_COVERAGE.get(N, {}).get(method.key),
            })
        if progress:
            at = {r["samples"]: r["cells_mean"] for r in rows if r["method"] == method.key}
            print(f"  {method.key:<16} " + "  ".join(f"N={n}: {c:.0f}" for n, c in at.items())
                  + f"  ({time.perf_counter() - start:.1f} s)", flush=True)
    return {"config": asdict(cfg), "table": str(sources.table), "horizon": T,
            "reachable": {"total": reach.total, "per_level": reach.level_sizes,
                          "merge_resolution": cfg.merge_resolution},
            "level_sets_total": level_sets, "results": rows}


def markdown(result: dict) -> str:
    """The coverage table: one row per N, one column per method, the paper's counts in brackets."""
    rows = result["results"]
    methods = list(dict.fromkeys(r["method"] for r in rows))
    samples = list(dict.fromkeys(r["samples"] for r in rows))
    at = {(r["method"], r["samples"]): r for r in rows}
    reach = result["reachable"]["total"]
    lines = [
        f"Distinct cells visited (mean +- std over {rows[0]['seeds']} seeds; % of the {reach} cells real rollouts "
        f"can reach; *paper's Table I in italics*). Horizon {result['horizon']} steps.",
        "",
        "| N | " + " | ".join(methods) + " |",
        "|---:|" + "---:|" * len(methods),
    ]
    for N in samples:
        cells = []
        for m in methods:
            r = at[(m, N)]
            cell = f"{r['cells_mean']:.0f} +- {r['cells_std']:.0f} ({r['pct_reachable']:.0f}%)"
            if r["paper"] is not None:
                cell += f" *{r['paper']}*"
            cells.append(cell)
        lines.append(f"| {N} | " + " | ".join(cells) + " |")
    lines += ["", "Share of the ideal ceiling (N uniform draws per level over the reachable cells):", "",
              "| N | " + " | ".join(methods) + " |", "|---:|" + "---:|" * len(methods)]
    for N in samples:
        lines.append(f"| {N} | " + " | ".join(f"{at[(m, N)]['pct_ceiling']:.0f}%" for m in methods) + " |")
    return "\n".join(lines)


def print_table(result: dict) -> None:
    rows = result["results"]
    print(f"\nreachable cells (exhaustive enumeration): {result['reachable']['total']}; "
          f"table level sets: {result['level_sets_total']}")
    print(f"{'method':<16} {'N':>6} {'cells':>15} {'% reach':>8} {'% ceiling':>9} {'paper':>6}")
    for r in rows:
        paper = "" if r["paper"] is None else str(r["paper"])
        print(f"{r['method']:<16} {r['samples']:>6} {r['cells_mean']:>8.0f} +- {r['cells_std']:<4.0f}"
              f" {r['pct_reachable']:>7.1f}% {r['pct_ceiling']:>8.1f}% {paper:>6}")


@cli_main()
def main(argv=None) -> int:
    p = ArgumentParser(prog="python -m eval.coverage", description=__doc__.split("\n\n")[0])
    p.add_argument("--methods", nargs="+", default=None, help="method keys (default: every open-loop method)")
    p.add_argument("--samples", type=int, nargs="+", default=None)
    p.add_argument("--seeds", type=int, default=5)
    p.add_argument("--merge-resolution", type=int, default=32)
    p.add_argument("--quick", action="store_true", help="N = 250 and 1000, 2 seeds")
    p.add_argument("--json", type=Path, default=None)
    add_source_args(p)
    args = p.parse_args(argv)
    cfg = CoverageConfig(methods=args.methods, seeds=2 if args.quick else args.seeds,
                         merge_resolution=args.merge_resolution)
    if args.samples:
        cfg.samples = args.samples
    elif args.quick:
        cfg.samples = [250, 1000]
    return run_experiment(run, cfg, args, print_table)


if __name__ == "__main__":
    sys.exit(main())
