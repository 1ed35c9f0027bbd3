"""Uniformity per level: how close each method's visited-cell histogram at step t is to uniform.

    python -m eval.uniformity                       # every open-loop method, N = 10000, 3 seeds
    python -m eval.uniformity --methods cu_table cu_coverage --samples 1000

For each method and level t, N trajectories from the origin give a histogram p over the cells visited at step
t. Against a reference set S_t of cells:

* ``tv``: total-variation distance from uniform over S_t, ``1/2 sum_{c in S_t} |p_c - 1/|S_t|| + 1/2 p(outside)``;
* ``floor``: the same distance for N perfectly uniform draws over S_t (finite-sample noise; no sampler can
  do better on average);
* ``entropy``: ``H(p) / log |S_t|`` (1 = uniform over S_t);
* ``outside``: share of the N states at step t whose cell is not in S_t.

Two reference sets: the cells real rollouts can reach (exhaustive enumeration, :mod:`eval.reachable`; the
main one) and the max-flow table's level sets L_t (the paper's). Values are means over seeds.
"""

from __future__ import annotations

import math
import statistics
import sys
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
from torch import Tensor

from cuniform_torch.cli import ArgumentParser, cli_main
from cuniform_torch.grid import CellKeys

from .cli import add_source_args, run_experiment
from .methods import Sources, parse_methods, sample_states
from .reachable import reachable


@dataclass
class UniformityConfig:
    methods: list[str] | None = None
    samples: int = 10000
    seeds: int = 3
    merge_resolution: int = 32


def level_stats(cells: Tensor, reference: Tensor, floor_generator: torch.Generator | None = None) -> dict[str, float]:
    """Uniformity of ``cells [N, d]`` (one level's visited cells) against the set ``reference [n, d]``."""
    N, n = cells.shape[0], reference.shape[0]
    keys = CellKeys.covering(torch.cat((cells, reference)))
    ref = torch.sort(keys.pack(reference)).values  # [n]
    uniq, counts = torch.unique(keys.pack(cells), return_counts=True)
    pos = torch.searchsorted(ref, uniq).clamp(max=n - 1)
    inside = ref[pos] == uniq
    p = counts.double() / N
    hist = torch.zeros(n, dtype=torch.float64)
    hist[pos[inside]] = p[inside]
    outside = float(p[~inside].sum())
    tv = 0.5 * float((hist - 1.0 / n).abs().sum()) + 0.5 * outside
    entropy = float(-(p * p.log()).sum()) / math.log(n) if n > 1 else 1.0
    draws = torch.randint(n, (N,), generator=floor_generator)
    floor = 0.5 * float((torch.bincount(draws, minlength=n).double() / N - 1.0 / n).abs().sum())
    return {"tv": tv, "floor": floor, "entropy": entropy, "outside": outside}


def run(cfg: UniformityConfig, sources: Sources, progress: bool = True) -> dict:
    """Per method: per-level ``tv``, ``floor``, ``entropy``, ``outside`` against both reference sets."""
    methods = parse_methods(cfg.methods)
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
            per_seed.append({name: [level_stats(cells[:, t], ref[t], floor_gen) for t in range(T + 1)]
                             for name, ref in references.items()})
        row = {"method": method.key, "label": method.label, "samples": cfg.samples, "seeds": cfg.seeds}
        for name in references:
            row[name] = {k: [statistics.mean(s[name][t][k] for s in per_seed) for t in range(T + 1)]
                         for k in ("tv", "floor", "entropy", "outside")}
        results.append(row)
        if progress:
            r = row["reachable"]
            print(f"  {method.key:<16} mean TV {statistics.mean(r['tv'][1:]):.3f} (floor "
                  f"{statistics.mean(r['floor'][1:]):.3f})  entropy {statistics.mean(r['entropy'][1:]):.3f}", flush=True)
    return {"config": asdict(cfg), "table": str(sources.table), "horizon": T,
            "reachable_sizes": reach.level_sizes,
            "level_set_sizes": [table.level_size(t) for t in range(T + 1)], "results": results}


def _mean(values: list[float]) -> float:
    return statistics.mean(values[1:]) if len(values) > 1 else values[0]


def markdown(result: dict) -> str:
    """Mean over levels 1..T of each measure, per method, against both reference sets."""
    r0 = result["results"][0]
    lines = [
        f"Uniformity per level, N = {r0['samples']} trajectories, mean over levels 1..{result['horizon']} and "
        f"{r0['seeds']} seeds. *Reachable*: the cells real rollouts can reach; *L_t*: the max-flow table's "
        "level sets. TV floor = the TV of N perfectly uniform draws.",
        "",
        "| method | TV (reachable) | TV floor | entropy ratio | outside reachable | TV (L_t) | outside L_t |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r in result["results"]:
        a, b = r["reachable"], r["level_sets"]
        lines.append(f"| {r['method']} | {_mean(a['tv']):.3f} | {_mean(a['floor']):.3f} | {_mean(a['entropy']):.3f} "
                     f"| {_mean(a['outside']):.1%} | {_mean(b['tv']):.3f} | {_mean(b['outside']):.1%} |")
    return "\n".join(lines)


def print_table(result: dict) -> None:
    print()
    print(markdown(result))


@cli_main()
def main(argv=None) -> int:
    p = ArgumentParser(prog="python -m eval.uniformity", description=__doc__.split("\n\n")[0])
    p.add_argument("--methods", nargs="+", default=None)
    p.add_argument("--samples", type=int, default=10000)
    p.add_argument("--seeds", type=int, default=3)
    p.add_argument("--merge-resolution", type=int, default=32)
    p.add_argument("--quick", action="store_true", help="N = 1000, 1 seed")
    p.add_argument("--json", type=Path, default=None)
    add_source_args(p)
    args = p.parse_args(argv)
    cfg = UniformityConfig(args.methods, 1000 if args.quick else args.samples, 1 if args.quick else args.seeds,
                           args.merge_resolution)
    return run_experiment(run, cfg, args, print_table)


if __name__ == "__main__":
    sys.exit(main())
