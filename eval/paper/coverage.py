"""Coverage experiment (the paper's Table I): distinct cells visited by N trajectories of each method, mean +- std over seeds.

    python -m eval.paper.coverage                # every open-loop method, N = 250 ... 10000, 5 seeds
    python -m eval.paper.coverage --methods cu_table cu_coverage --samples 1000 --seeds 3 --json out/coverage.json

(``python -m eval.paper.coverage`` still runs it.) The metric is :func:`cuniform_torch.metrics.coverage`; the
coverage *build method* is :mod:`precompute.coverage.method` (``cu_coverage`` here).

N trajectories of the table's horizon (10 steps = 2 s on the default preset) from the start pose (0, 0, 0);
baselines sample around a zero nominal (a first solve). Coverage = distinct (x, y, theta) cells visited by any
trajectory at any step, start included (the reference release's definition), on the default table's grid. It
is reported as a count, as % of the cells real rollouts can reach (exhaustive enumeration of every action
sequence, :mod:`eval.paper.reachable`), as % of the union of the table's level sets, and as % of the ideal ceiling:
N perfectly uniform draws over the reachable cells of every level, ``sum_t n_t (1 - (1 - 1/n_t)^N)``. Per-level
coverage is kept in the JSON. The paper's Table I counts are printed beside ours (its C-Uniform column is
graph sampling, ``cu_graph`` here).
"""

from __future__ import annotations

import statistics
import sys
import time
from dataclasses import asdict, dataclass, replace

import torch

from cuniform_torch.metrics import coverage, uniform_ceiling
from eval.common import config
from eval.common.markdown import table as md_table
from eval.common.methods import PAPER, Sources, parse_methods, sample_states
from eval.paper import cli
from eval.paper.reachable import reachable

__all__ = ["CoverageConfig", "CONFIG", "QUICK", "run", "markdown", "print_table", "make_parser", "config_from_args",
           "main"]


@dataclass(frozen=True)
class CoverageConfig:
    """What the coverage experiment runs; the defaults are the paper's Table I."""

    methods: tuple[str, ...] | None = None
    """method keys (default: every open-loop method)"""
    samples: tuple[int, ...] = (250, 500, 1000, 2500, 5000, 10000)
    """N, trajectories per method"""
    seeds: int = 5
    """seeds per method and N (mean +- std over them)"""
    merge_resolution: int = 32
    """sub-cell merging of the reachable-set enumeration"""


CONFIG = CoverageConfig
QUICK = replace(CoverageConfig(), samples=(250, 1000), seeds=2)
"""--quick (and the quick report): N = 250 and 1000, 2 seeds"""


def run(cfg: CoverageConfig, sources: Sources, progress: bool = True) -> dict:
    """Run the experiment; returns ``{"config", "reachable", "results": [row per method and N]}``."""
    methods = parse_methods(cfg.methods, benchmark=PAPER, closed_loop=False)
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
    """The coverage table: one row per N, one column per method, the paper's counts in italics."""
    rows = result["results"]
    methods = list(dict.fromkeys(r["method"] for r in rows))
    samples = list(dict.fromkeys(r["samples"] for r in rows))
    at = {(r["method"], r["samples"]): r for r in rows}

    def cell(r: dict) -> str:
        text = f"{r['cells_mean']:.0f} +- {r['cells_std']:.0f} ({r['pct_reachable']:.0f}%)"
        return text if r["paper"] is None else f"{text} *{r['paper']}*"

    head, align = ["N", *methods], "r" * (len(methods) + 1)
    return "\n".join([
        f"Distinct cells visited (mean +- std over {rows[0]['seeds']} seeds; % of the {result['reachable']['total']} "
        f"cells real rollouts can reach; *paper's Table I in italics*). Horizon {result['horizon']} steps.", "",
        md_table(head, [[N, *(cell(at[(m, N)]) for m in methods)] for N in samples], align), "",
        "Share of the ideal ceiling (N uniform draws per level over the reachable cells):", "",
        md_table(head, [[N, *(f"{at[(m, N)]['pct_ceiling']:.0f}%" for m in methods)] for N in samples], align),
    ])


def print_table(result: dict) -> None:
    rows = result["results"]
    print(f"\nreachable cells (exhaustive enumeration): {result['reachable']['total']}; "
          f"table level sets: {result['level_sets_total']}")
    print(f"{'method':<16} {'N':>6} {'cells':>15} {'% reach':>8} {'% ceiling':>9} {'paper':>6}")
    for r in rows:
        paper = "" if r["paper"] is None else str(r["paper"])
        print(f"{r['method']:<16} {r['samples']:>6} {r['cells_mean']:>8.0f} +- {r['cells_std']:<4.0f}"
              f" {r['pct_reachable']:>7.1f}% {r['pct_ceiling']:>8.1f}% {paper:>6}")


make_parser, config_from_args, main = cli.entry_points(
    __name__, cli.open_loop_flags(CoverageConfig, "N = 250 and 1000, 2 seeds"), show=print_table)


if __name__ == "__main__":
    sys.exit(main())
