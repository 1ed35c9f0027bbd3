"""Paired comparison of any two (method, budget) cells of a benchmark folder, across budgets too.

    python -m eval.navigate compare --out out/navigate/clutter-test-100 --method cfu_mppi@256 \
        --against cumppi@256 mppi_1.0@1024 --margin 0.1

The benchmark's own table compares each method with the best Gaussian baseline *at the same budget*. A question
like "is CFU-MPPI at K = 256 at least MPPI at K = 1024?" pairs cells of different budgets; every method and
budget of a task runs under the same controller seed (:func:`eval.navigate.run.controller_seed`), so the episodes
pair on (task, seed) across budgets as well. For each ``--against`` cell: the pairs, both success rates with
95% Wilson intervals, wins / losses, the success-rate difference with its 95% Newcombe interval, the exact
McNemar p, and, with ``--margin m``, whether the difference reaches ``m`` by its point estimate and by its
interval's lower end.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from eval.common.stats import wilson_interval
from eval.navigate.records import by_episode, compare_pair, load_folder
from precompute.cli import ArgumentParser, cli_main

__all__ = ["parse_cell", "compare_cells", "main"]


def parse_cell(text: str) -> tuple[str, int]:
    """``"cfu_mppi@256"`` -> ``("cfu_mppi", 256)``; a ValueError naming the form otherwise."""
    method, sep, budget = text.rpartition("@")
    if not sep or not method or not budget.isdigit():
        raise ValueError(f"a cell is METHOD@BUDGET (e.g. cfu_mppi@256), got {text!r}")
    return method, int(budget)


def compare_cells(records: Sequence[dict], method: tuple[str, int], against: tuple[str, int]) -> dict:
    """``method`` against ``against`` (each ``(method, budget)``) over their common (task, seed) episodes: the
    :func:`eval.navigate.records.stats.paired_comparisons` row (``wins``, ``losses``, ``diff`` and its interval, ``p_value``,
    ``verdict``) plus both cells' success rates with Wilson intervals."""
    cells = {}
    for cell in (method, against):
        recs = [r for r in records if (r["method"], r["budget"]) == cell]
        if not recs:
            held = sorted({f"{r['method']}@{r['budget']}" for r in records})
            raise ValueError(f"no episode of {cell[0]}@{cell[1]} in the folder (it holds {', '.join(held)})")
        cells[cell] = by_episode(recs, f"{cell[0]}@{cell[1]}")
    row = compare_pair(None, None, f"{method[0]}@{method[1]}", f"{against[0]}@{against[1]}", cells[method],
                       cells[against])
    if row is None:
        raise ValueError(f"{method[0]}@{method[1]} and {against[0]}@{against[1]} share no (task, seed) episode")
    for side, n_succ in (("method", row["method_successes"]), ("baseline", row["baseline_successes"])):
        low, high = wilson_interval(n_succ, row["n"])
        row.update({f"{side}_rate": n_succ / row["n"], f"{side}_rate_low": low, f"{side}_rate_high": high})
    return row


def _line(row: dict, margin: float | None) -> str:
    def rate(side: str) -> str:
        return f"{row[f'{side}_rate']:.2f} [{row[f'{side}_rate_low']:.2f}, {row[f'{side}_rate_high']:.2f}]"

    out = (f"| {row['method']} | {rate('method')} | {row['baseline']} | {rate('baseline')} | {row['n']} | "
           f"{row['wins']} | {row['losses']} | {row['diff']:+.2f} [{row['diff_low']:+.2f}, {row['diff_high']:+.2f}] | "
           f"{row['p_value']:.3g} |")
    if margin is not None:
        out += f" {'yes' if row['diff'] >= margin - 1e-12 else 'no'} | {'yes' if row['diff_low'] >= margin else 'no'} |"
    return out


def make_parser() -> ArgumentParser:
    p = ArgumentParser(prog="python -m eval.navigate compare", description=(__doc__ or "").split("\n\n")[0])
    p.add_argument("--out", type=Path, required=True, help="the benchmark folder (python -m eval.navigate --out)")
    p.add_argument("--method", required=True, metavar="METHOD@BUDGET", help="the cell under test, e.g. cfu_mppi@256")
    p.add_argument("--against", nargs="+", required=True, metavar="METHOD@BUDGET",
                   help="the cells to compare it with, e.g. cumppi@256 mppi_1.0@1024")
    p.add_argument("--margin", type=float, default=None,
                   help="also say whether the difference reaches this (e.g. 0.1 for 10 points)")
    return p


@cli_main()
def main(argv: Sequence[str] | None = None) -> int:
    args = make_parser().parse_args(argv)
    mine = parse_cell(args.method)
    others = [parse_cell(c) for c in args.against]
    if args.margin is not None and not -1 <= args.margin <= 1:
        raise ValueError(f"--margin is a success-rate difference in [-1, 1], got {args.margin}")
    _, by_key = load_folder(args.out)
    records = list(by_key.values())
    rows = [compare_cells(records, mine, other) for other in others]
    head = "| method | success | against | success | pairs | wins | losses | diff [95% CI] | McNemar p |"
    rule = "|---|---|---|---|---|---|---|---|---|"
    if args.margin is not None:
        head += f" diff >= {args.margin:+.2f} | CI low >= {args.margin:+.2f} |"
        rule += "---|---|"
    print(f"paired on (task, seed) in {args.out}")
    print("\n".join([head, rule] + [_line(r, args.margin) for r in rows]))
    return 0
