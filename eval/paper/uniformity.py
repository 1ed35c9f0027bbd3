"""Uniformity per level: how close each method's visited-cell histogram at step t is to uniform.

    python -m eval.paper.uniformity                       # every open-loop method, N = 10000, 3 seeds
    python -m eval.paper.uniformity --methods cu_table cu_coverage --samples 1000

For each method and level t, N trajectories from the origin give a histogram p over the cells visited at step
t. Against a reference set S_t of cells:

* ``tv``: total-variation distance from uniform over S_t, ``1/2 sum_{c in S_t} |p_c - 1/|S_t|| + 1/2 p(outside)``;
* ``floor``: the same distance for N perfectly uniform draws over S_t (finite-sample noise; no sampler can
  do better on average);
* ``entropy``: ``H(p) / log |S_t|`` (1 = uniform over S_t);
* ``outside``: share of the N states at step t whose cell is not in S_t.

Two reference sets: the cells real rollouts can reach (exhaustive enumeration, :mod:`eval.paper.reachable`; the
main one) and the max-flow table's level sets L_t (the paper's). Values are means over seeds. The measures are
:func:`cuniform_torch.metrics.level_uniformity` (the same TV and noise floor as the build's report).
"""

from __future__ import annotations

import statistics
import sys
from dataclasses import asdict, dataclass, replace

import torch

from cuniform_torch.metrics import level_uniformity
from eval.common.markdown import table as md_table
from eval.common.methods import PAPER, Sources, parse_methods, sample_states
from eval.common.stats import mean_over_levels
from eval.paper import cli
from eval.paper.reachable import reachable

__all__ = ["UniformityConfig", "CONFIG", "QUICK", "MEASURES", "run", "markdown", "make_parser", "config_from_args",
           "main"]

MEASURES = ("tv", "floor", "entropy", "outside")
"""the per-level measures (:func:`cuniform_torch.metrics.level_uniformity`)"""


@dataclass(frozen=True)
class UniformityConfig:
    """What the uniformity experiment runs."""

    methods: tuple[str, ...] | None = None
    """method keys (default: every open-loop method)"""
    samples: int = 10000
    """N, trajectories per method and seed"""
    seeds: int = 3
    """seeds per method (values are means over them)"""
    merge_resolution: int = 32
    """sub-cell merging of the reachable-set enumeration"""


CONFIG = UniformityConfig
QUICK = replace(UniformityConfig(), samples=1000, seeds=1)
"""--quick (and the quick report): N = 1000, 1 seed"""


def run(cfg: UniformityConfig, sources: Sources, progress: bool = True) -> dict:
    """Per method: per-level ``tv``, ``floor``, ``entropy``, ``outside`` against both reference sets."""
    methods = parse_methods(cfg.methods, benchmark=PAPER, closed_loop=False)
    table = sources.table_policy()
    grid, T = table.grid, table.horizon
    reach = reachable(table.system, T, cfg.merge_resolution)
    offsets = table.table.level_offsets
    table_cells = torch.from_numpy(table.table.cells)
    references = {"reachable": list(reach.level_cells),
                  "level_sets": [table_cells[offsets[t]:offsets[t + 1]] for t in range(T + 1)]}
    results = []
    for method in methods:
        per_seed = []
        for seed in range(cfg.seeds):
            gen = torch.Generator(device=sources.device).manual_seed(seed)
            cells = grid.cells(sample_states(method, sources, cfg.samples, T, gen)).cpu()  # [N, T+1, d]
            floor_gen = torch.Generator().manual_seed(1000 + seed)
            per_seed.append({name: [level_uniformity(cells[:, t], ref[t], floor_gen) for t in range(T + 1)]
                             for name, ref in references.items()})
        row = {"method": method.key, "label": method.label, "samples": cfg.samples, "seeds": cfg.seeds}
        for name in references:
            row[name] = {k: [statistics.mean(s[name][t][k] for s in per_seed) for t in range(T + 1)]
                         for k in MEASURES}
        results.append(row)
        if progress:
            r = row["reachable"]
            print(f"  {method.key:<16} mean TV {mean_over_levels(r['tv']):.3f} (floor "
                  f"{mean_over_levels(r['floor']):.3f})  entropy {mean_over_levels(r['entropy']):.3f}", flush=True)
    return {"config": asdict(cfg), "table": str(sources.table), "horizon": T,
            "reachable_sizes": reach.level_sizes,
            "level_set_sizes": [table.level_size(t) for t in range(T + 1)], "results": results}


def markdown(result: dict) -> str:
    """Mean over levels 1..T of each measure, per method, against both reference sets."""
    r0, m = result["results"][0], mean_over_levels
    body = [[r["method"], f"{m(r['reachable']['tv']):.3f}", f"{m(r['reachable']['floor']):.3f}",
             f"{m(r['reachable']['entropy']):.3f}", f"{m(r['reachable']['outside']):.1%}",
             f"{m(r['level_sets']['tv']):.3f}", f"{m(r['level_sets']['outside']):.1%}"] for r in result["results"]]
    return "\n".join([
        f"Uniformity per level, N = {r0['samples']} trajectories, mean over levels 1..{result['horizon']} and "
        f"{r0['seeds']} seeds. *Reachable*: the cells real rollouts can reach; *L_t*: the max-flow table's "
        "level sets. TV floor = the TV of N perfectly uniform draws.", "",
        md_table(["method", "TV (reachable)", "TV floor", "entropy ratio", "outside reachable", "TV (L_t)",
                  "outside L_t"], body, "lrrrrrr"),
    ])


make_parser, config_from_args, main = cli.entry_points(
    __name__, cli.open_loop_flags(UniformityConfig, "N = 1000, 1 seed"), show=lambda r: print("\n" + markdown(r)))


if __name__ == "__main__":
    sys.exit(main())
