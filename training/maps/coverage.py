"""Free-space coverage of a map policy's rollouts against the blind table's:
python -m training.maps.coverage --checkpoint FILE --maps DATASET --table BLIND.npz --samples 256 1024

For every entry of the data set (its patch, robot at the origin of the start frame, as in
:mod:`training.maps.evaluate`) and every N of ``--samples``: N rollouts of the map policy (map set once) and of the
blind table, one seed. Per level t = 1..T, a rollout's state at step t is in the grid cell ``Grid.cells`` gives
it (the cells the tables hold); the entry's *safe cells* at level t are its table rows' cells there (free,
reachable, viable). Two shares per level, averaged over the levels:

* *coverage*: of the safe cells at level t, the share that at least one rollout's state at step t falls into;
* *in free*: of the N states at step t, the share that lands in a safe cell of level t.

Printed per entry, then a table: method x N -> mean over the entries with a 95% t-interval, and the map
policy's ratio to the blind table.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor

from cuniform_torch.envs import OccupancyGrid
from cuniform_torch.grid.cells import CellSet, Grid
from cuniform_torch.policies.table import TablePolicy
from cuniform_torch.sampling.rollout import rollout
from precompute.cli import (
    ArgumentParser,
    add_system_module_arg,
    check_output_file,
    cli_main,
    import_system_modules,
    int_in,
    non_negative_int,
    positive_int,
)
from training.maps.evaluate import add_input_args, check_entries, load_inputs

__all__ = ["free_coverage", "mean_interval", "make_parser", "main"]

METHODS = ("map_policy", "blind_table")


def free_coverage(states: Tensor, cells: np.ndarray | Tensor, level_offsets: np.ndarray | Tensor,
                  grid: Grid) -> tuple[np.ndarray, np.ndarray]:
    """Per level t = 1..T: ``(coverage [T], in_free [T])`` of rollouts ``states [N, T+1, d]`` (start frame)
    over the safe cells ``cells [R, d]`` (int, a table's rows: level t is rows
    ``level_offsets[t]:level_offsets[t+1]``, ``level_offsets [T+2]``).

    ``coverage[t-1]``: the share of level t's safe cells that some state at step t lies in (NaN for a level
    without cells); ``in_free[t-1]``: the share of the N states at step t that lie in a safe cell of level t.
    One sorted-key lookup of all (step, cell) pairs at once, no loop.
    """
    if states.ndim != 3 or states.shape[2] != grid.dim:
        raise ValueError(f"states must have shape [N, T+1, {grid.dim}], got {list(states.shape)}")
    N, T1, _ = states.shape
    offsets = torch.as_tensor(np.asarray(level_offsets), dtype=torch.int64)
    cells = torch.as_tensor(np.asarray(cells), dtype=torch.int64)
    if offsets.shape != (T1 + 1,) or int(offsets[0]) != 0 or int(offsets[-1]) != cells.shape[0]:
        raise ValueError(f"level_offsets must be [T+2] = [{T1 + 1}] from 0 to the {cells.shape[0]} rows, got "
                         f"{offsets.tolist()}")
    sizes = offsets[1:] - offsets[:-1]  # [T+1] safe cells per level 0..T
    level = torch.repeat_interleave(torch.arange(T1), sizes)  # [R] level of each row
    # a (level, cell) key per row and per (rollout, step): a state counts only against its own level's cells
    safe = CellSet.build(torch.cat((level[:, None], cells), dim=1))
    steps = torch.arange(T1).expand(N, T1)[:, 1:, None]  # [N, T, 1]
    visited = grid.cells(states[:, 1:].cpu())  # [N, T, d]
    rows = safe.lookup(torch.cat((steps, visited), dim=2))  # [N, T], -1 outside the safe cells
    hit = rows >= 0
    covered = torch.bincount(level[torch.unique(rows[hit])], minlength=T1)[1:]  # [T] distinct safe cells hit
    with np.errstate(invalid="ignore", divide="ignore"):
        coverage = covered.double().numpy() / sizes[1:].double().numpy()
    coverage[sizes[1:].numpy() == 0] = math.nan
    return coverage, hit.double().mean(dim=0).numpy()


def mean_interval(values: Sequence[float]) -> tuple[float, float]:
    """``(mean, half width of the 95% t-interval)`` over ``values`` (NaN half width for fewer than two)."""
    arr = np.asarray(values, dtype=np.float64)
    if arr.size < 2:
        return float(arr.mean()) if arr.size else math.nan, math.nan
    from scipy.stats import t as student_t
    half = float(student_t.ppf(0.975, arr.size - 1) * arr.std(ddof=1) / math.sqrt(arr.size))
    return float(arr.mean()), half


def _pm(mean: float, half: float) -> str:
    return f"{mean:.3f} +- {half:.3f}" if math.isfinite(half) else f"{mean:.3f}"


def make_parser() -> ArgumentParser:
    parser = ArgumentParser(prog="python -m training.maps.coverage", description=__doc__.splitlines()[0])
    add_input_args(parser)
    parser.add_argument("--samples", type=positive_int, nargs="+", default=[256, 1024], metavar="N",
                        help="rollouts per entry and method, one run per N")
    parser.add_argument("--entries", type=non_negative_int, default=0, help="first entries only (0: all)")
    parser.add_argument("--seed", type=int_in(0, 2**63 - 1), default=0)
    parser.add_argument("--json", default=None, help="also write the per-entry shares and the summary here")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    add_system_module_arg(parser)
    return parser


@cli_main()
def main(argv: Sequence[str] | None = None) -> int:
    args = make_parser().parse_args(argv)
    import_system_modules(args.system_module)
    if args.json:
        check_output_file(args.json, "--json", "coverage.json")
    policy, ds, blind = load_inputs(args.checkpoint, args.maps, args.table, deep_checks=not args.skip_deep_checks)
    spec, system, T = policy.patch_spec, policy.system, policy.horizon
    grid, x0 = Grid.of(system), torch.zeros(len(system.periodic))
    policies = {"map_policy": policy, "blind_table": TablePolicy(blind)}
    # shares[method][N] = {"coverage": [per entry], "in_free": [per entry]}
    shares = {m: {n: {"coverage": [], "in_free": []} for n in args.samples} for m in METHODS}
    total = check_entries(args.entries, ds, args.maps)
    from tqdm import tqdm
    bar = tqdm(total=total, desc="map_coverage", unit="entry", disable=args.quiet)
    sources = []
    for k, entry in enumerate(ds):
        if k >= total:
            break
        policy.set_map(OccupancyGrid(torch.from_numpy(entry.patch.astype(bool)), spec.origin, spec.resolution))
        sources.append(entry.source)
        for n in args.samples:
            row = []
            for name, p in policies.items():
                states, _ = rollout(system, p, x0, n, T, torch.Generator().manual_seed(args.seed))
                cov, free = free_coverage(states, entry.cells, entry.level_offsets, grid)
                shares[name][n]["coverage"].append(float(np.nanmean(cov)))
                shares[name][n]["in_free"].append(float(free.mean()))
                row.append(f"{name} coverage {shares[name][n]['coverage'][-1]:.3f} in free "
                           f"{shares[name][n]['in_free'][-1]:.3f}")
            bar.write(f"entry {k:3d} ({entry.source}) N {n:5d}: " + ", ".join(row), file=sys.stdout)
        bar.update(1)
    bar.close()
    summary = {m: {n: {key: mean_interval(v) for key, v in shares[m][n].items()} for n in args.samples}
               for m in METHODS}
    print(f"free-space coverage over {len(sources)} entries (mean +- 95% t-interval over the entries; per entry "
          f"averaged over levels 1..{T})")
    print(f"{'method':<12} {'N':>6}  {'coverage':<16} {'in free':<16}")
    for m in METHODS:
        for n in args.samples:
            s = summary[m][n]
            print(f"{m:<12} {n:6d}  {_pm(*s['coverage']):<16} {_pm(*s['in_free']):<16}")
    ratios = {n: {key: summary["map_policy"][n][key][0] / summary["blind_table"][n][key][0]
                  if summary["blind_table"][n][key][0] > 0 else math.inf for key in ("coverage", "in_free")}
              for n in args.samples}
    print("map policy / blind table: " + "; ".join(
        f"N {n}: coverage x{r['coverage']:.2f}, in free x{r['in_free']:.2f}" for n, r in ratios.items())
        + f"; map policy miss rate {policy.miss_rate:.3f}")
    if args.json:
        from cuniform_torch.common.fileio import write_json
        write_json(args.json, {
            "samples": args.samples, "seed": args.seed, "entries": sources,
            "shares": {m: {str(n): v for n, v in shares[m].items()} for m in METHODS},
            "summary": {m: {str(n): {key: {"mean": mh[0], "ci95": mh[1] if math.isfinite(mh[1]) else None}
                                     for key, mh in s.items()} for n, s in summary[m].items()} for m in METHODS},
            "ratio": {str(n): {key: v if math.isfinite(v) else None for key, v in r.items()}
                      for n, r in ratios.items()}})
    return 0


if __name__ == "__main__":
    sys.exit(main())
