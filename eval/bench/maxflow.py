"""Benchmark the max-flow solvers on the flow networks of a real table, side by side.

    python -m eval.bench maxflow --table out/paper.npz --levels 6 9 12 15 --networkx-max-nodes 30000

For each chosen step t -> t+1 of the table: the network size, scipy's Dinic (what the builder uses; median of
repeats), and networkx's preflow-push on the same network (once; skipped above ``--networkx-max-nodes``), the
flow values (they must agree) and the speed ratio. Prints a table and writes JSON (``--json``).
"""

from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path

from cuniform_torch.common.fileio import write_json
from cuniform_torch.tables.file import read_table
from eval.bench.cli import refuse_old_spelling
from eval.common.paths import DEFAULT
from precompute.cli import (
    ArgumentParser,
    CLIError,
    add_system_module_arg,
    check_output_file,
    cli_main,
    import_system_modules,
    non_negative_int,
    positive_int,
)
from precompute.flow.maxflow import maxflow_value_networkx, solve_maxflow


def make_parser() -> ArgumentParser:
    p = ArgumentParser(prog="python -m eval.bench maxflow", description=__doc__.split("\n\n")[0])
    p.add_argument("--table", type=Path, default=DEFAULT.table)
    p.add_argument("--levels", type=positive_int, nargs="+", default=None,
                   help="target levels t+1 (default: every level)")
    p.add_argument("--repeats", type=positive_int, default=3)
    p.add_argument("--networkx-max-nodes", type=non_negative_int, default=20000,
                   help="skip networkx on larger networks (0: always)")
    p.add_argument("--json", type=Path, default=None)
    add_system_module_arg(p)
    return p


@cli_main()
def main(argv=None) -> int:
    args = make_parser().parse_args(argv)
    import_system_modules(args.system_module)
    if args.json is not None:
        check_output_file(args.json, "--json", example="bench_maxflow.json")
    table = read_table(args.table)
    if table.arcs is None:
        raise CLIError(f"--table {args.table} holds no flow graph (a --method coverage table?); give a max-flow table")
    levels = args.levels or list(range(1, table.horizon + 1))
    bad = [lv for lv in levels if not 1 <= lv <= table.horizon]
    if bad:
        raise CLIError(f"--levels {' '.join(map(str, bad))}: not in 1..{table.horizon} (the table's levels)")
    rows = []
    print(f"{'step':>7} {'nodes':>7} {'arcs':>8} {'scipy s':>9} {'networkx s':>11} {'ratio':>8} {'flow/nm':>8}")
    for lv in levels:
        t = lv - 1
        sl = slice(table.arc_offsets[t], table.arc_offsets[t + 1])
        n, m = table.level_sizes[t], table.level_sizes[t + 1]
        src = table.arcs[sl, 0] - table.level_offsets[t]
        dst = table.arcs[sl, 1] - table.level_offsets[t + 1]
        times = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            value = solve_maxflow(n, m, src, dst).value
            times.append(time.perf_counter() - t0)
        scipy_s = statistics.median(times)
        nx_s = nx_value = None
        if n + m + 2 <= args.networkx_max_nodes:
            t0 = time.perf_counter()
            nx_value = maxflow_value_networkx(n, m, src, dst)
            nx_s = time.perf_counter() - t0
            if nx_value != value:
                print(f"error: solvers disagree at step {t}->{lv}: scipy {value}, networkx {nx_value}", file=sys.stderr)
                return 1
        ratio = f"{nx_s / scipy_s:8.1f}x" if nx_s else "       -"
        nx_txt = f"{nx_s:11.3f}" if nx_s else "    skipped"
        print(f"{t:>3}->{lv:<3} {n + m + 2:>7} {len(src):>8} {scipy_s:>9.4f} {nx_txt} {ratio} {value / (n * m):>8.4f}")
        rows.append({"step": [t, lv], "nodes": n + m + 2, "arcs": int(len(src)), "scipy_seconds": scipy_s,
                     "networkx_seconds": nx_s, "flow_value": value, "flow_target": n * m})
    if args.json:
        write_json(args.json, {"table": str(args.table), "steps": rows})
    return 0


refuse_old_spelling(__name__, "maxflow")  # run as the old module command: one line naming the new spelling, exit 2
