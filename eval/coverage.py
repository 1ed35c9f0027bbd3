"""Coverage of real rollouts of C-Uniform tables: distinct cells visited, mean +- std over seeds.

    python -m eval.coverage --tables out/dubins.npz out/dubins_cov.npz --samples 250 1000 10000 --seeds 5

For each table and N: N rollouts of the table policy from the origin (real dynamics, seeded), the number of
distinct (x, y, theta) cells visited at any step, start included (the reference release's definition), the
cells of the level sets reached at the last step, and the share of states outside the level sets. The last
column is the ceiling of N perfectly uniform draws over the cells of the largest table's levels.
Writes JSON with ``--json``.
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

import torch

from cuniform_torch import TableError, load_table, rollout
from cuniform_torch.coverage import coverage, uniform_ceiling
from cuniform_torch.fileio import write_json


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m eval.coverage", description=__doc__.split("\n\n")[0])
    p.add_argument("--tables", type=Path, nargs="+", default=[Path("out/dubins.npz")])
    p.add_argument("--samples", type=int, nargs="+", default=[250, 1000, 10000])
    p.add_argument("--seeds", type=int, default=5)
    p.add_argument("--device", default="cpu")
    p.add_argument("--json", type=Path, default=None)
    args = p.parse_args(argv)
    try:
        policies = {str(t): load_table(t, device=args.device) for t in args.tables}
    except (TableError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    results = []
    print(f"{'table':<28} {'method':<9} {'N':>6} {'cells visited':>16} {'last level':>14} {'outside':>8}")
    for name, policy in policies.items():
        T = policy.horizon
        for N in args.samples:
            totals, last, outside = [], [], []
            for seed in range(args.seeds):
                gen = torch.Generator(device=policy.device).manual_seed(seed)
                states, _ = rollout(policy.system, policy, torch.zeros(policy.grid.dim, device=policy.device), N, T, gen)
                cov = coverage(states, policy.grid, policy)
                totals.append(cov.total)
                last.append(cov.in_level_set[-1])
                outside.append(float((policy.rows(states[:, -1], T) < 0).float().mean()))
            row = {"table": name, "method": policy.table.method, "samples": N, "seeds": args.seeds,
                   "cells_mean": statistics.mean(totals), "cells_std": statistics.stdev(totals) if args.seeds > 1 else 0.0,
                   "last_level_mean": statistics.mean(last), "last_level_size": policy.level_size(T),
                   "last_level_ceiling": uniform_ceiling(policy.level_size(T), N),
                   "outside_last_level": statistics.mean(outside)}
            results.append(row)
            print(f"{Path(name).name:<28} {str(row['method']):<9} {N:>6} {row['cells_mean']:>9.0f} +- {row['cells_std']:<4.0f}"
                  f" {row['last_level_mean']:>6.0f}/{row['last_level_size']:<6} {row['outside_last_level']:>8.2%}")
    if args.json:
        write_json(args.json, {"results": results})
    return 0


if __name__ == "__main__":
    sys.exit(main())
