"""Figures and TensorBoard scalars of the navigation benchmark's summary rows (:func:`eval.navigate.records.stats.summarize`).

:func:`success_figure` draws success rate against the sample budget (log2 axis) per method with 95% Wilson
error bars, one panel per suite, and writes it atomically as a PNG (:func:`eval.common.figures.save_figure`).
:func:`write_tensorboard` logs ``navigate/<suite>/<method>/<metric>`` scalars with the budget as global step.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path

from cuniform_torch.common.fileio import MAX_JSON_BYTES, read_capped_text
from eval.common.figures import method_style, plt, save_figure
from precompute.cli import ArgumentParser, check_output_file, cli_main

__all__ = ["TB_METRICS", "method_color", "success_figure", "write_tensorboard", "make_parser", "main"]

TB_METRICS = ("success_rate", "collision_rate", "timeout_rate", "cycle_ms_median")
"""the summary-row fields logged to TensorBoard, one scalar per (suite, method) against the budget"""

_ROW_FIELDS = ("suite", "method", "budget", "success_rate", "success_rate_low", "success_rate_high")


def _check_rows(rows: Sequence[Mapping], fields: Sequence[str]) -> None:
    """ValueError naming the first row that lacks a field or has a budget that is not a positive number."""
    if not rows:
        raise ValueError("no summary rows to draw or log")
    for i, r in enumerate(rows):
        missing = [f for f in fields if f not in r]
        if missing:
            raise ValueError(f"summary row {i} lacks the field(s) {', '.join(missing)}")
        b = r["budget"]
        if isinstance(b, bool) or not isinstance(b, (int, float)) or not b > 0:
            raise ValueError(f"summary row {i} has budget {b!r}; budgets must be positive numbers (log2 axis)")


def method_color(method: str, index: int, colors: Mapping[str, str] | None) -> str:
    """The caller's colour, else the method's registered colour, else the default colour cycle."""
    if colors and method in colors:
        return colors[method]
    color, _ = method_style(method)
    # method_style answers black for keys it does not know; the cycle keeps such methods apart
    return color if color != "black" else f"C{index % 10}"


def _panel(ax, rows: Sequence[Mapping], suite: str, methods: Sequence[str], labels: Mapping[str, str],
           colors: Mapping[str, str] | None) -> None:
    """One suite's panel: a line with Wilson error bars per method."""
    budgets = sorted({r["budget"] for r in rows})
    for i, m in enumerate(methods):
        mine = sorted((r for r in rows if r["method"] == m), key=lambda r: r["budget"])
        if not mine:
            continue
        dodge = 2.0 ** (0.06 * (i - (len(methods) - 1) / 2))  # side by side, so the bars do not hide each other
        x = [r["budget"] * dodge for r in mine]
        y = [r["success_rate"] for r in mine]
        yerr = [[r["success_rate"] - r["success_rate_low"] for r in mine],
                [r["success_rate_high"] - r["success_rate"] for r in mine]]
        ax.errorbar(x, y, yerr=yerr, marker="o", markersize=4, capsize=2, color=method_color(m, i, colors),
                    label=labels.get(m, m), linewidth=1.2, elinewidth=0.8)
    ax.set_xscale("log", base=2)
    ax.set_xticks(budgets)
    ax.set_xticklabels([f"{b:g}" for b in budgets])
    ax.minorticks_off()  # log2 minor ticks between budgets would only clutter
    ax.set_ylim(-0.03, 1.03)
    ax.set_xlabel("sample budget (trajectories per cycle)")
    ax.set_title(str(suite), fontsize=10)
    ax.grid(alpha=0.3)


def success_figure(summary_rows: Sequence[Mapping], path: str | Path, labels: Mapping[str, str] | None = None,
                   colors: Mapping[str, str] | None = None) -> Path:
    """Success rate vs budget (log2 x, ticks at the budgets) per method with 95% Wilson error bars, one panel
    per suite; written atomically as a PNG to ``path``, which is returned."""
    rows = list(summary_rows)
    _check_rows(rows, _ROW_FIELDS)
    suites = list(dict.fromkeys(r["suite"] for r in rows))
    methods = list(dict.fromkeys(r["method"] for r in rows))
    cols = min(3, len(suites))
    nrows = math.ceil(len(suites) / cols)
    fig, axes = plt.subplots(nrows, cols, figsize=(4.6 * cols, 3.6 * nrows), squeeze=False, sharey=True)
    try:
        for ax, suite in zip(axes.flat, suites):
            _panel(ax, [r for r in rows if r["suite"] == suite], suite, methods, labels or {}, colors)
        for ax in list(axes.flat)[len(suites):]:
            ax.axis("off")
        for ax in axes[:, 0]:
            ax.set_ylabel("success rate")
        axes.flat[len(suites) - 1].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0))  # off the data
        fig.suptitle("Navigation success vs sample budget (bars: 95% Wilson intervals)", fontsize=10)
        return save_figure(fig, Path(path))
    finally:
        plt.close(fig)  # many figures in one process would otherwise pile up in pyplot


def write_tensorboard(summary_rows: Sequence[Mapping], logdir: str | Path) -> None:
    """Scalars ``navigate/<suite>/<method>/<metric>`` (:data:`TB_METRICS`) with global step = budget; metrics
    that are None (e.g. no cycle times) are skipped."""
    from torch.utils.tensorboard import SummaryWriter  # torch only where TensorBoard is written

    rows = list(summary_rows)
    _check_rows(rows, ("suite", "method", "budget"))
    # one writer: the method is part of the tag, so one run holds every curve
    writer = SummaryWriter(str(Path(logdir)))
    try:
        for r in sorted(rows, key=lambda r: r["budget"]):
            for metric in TB_METRICS:
                value = r.get(metric)
                if value is not None:
                    writer.add_scalar(f"navigate/{r['suite']}/{r['method']}/{metric}", float(value),
                                      int(r["budget"]))
    finally:
        writer.close()


def make_parser() -> ArgumentParser:
    p = ArgumentParser(prog="python -m eval.navigate figures",
                       description="One success-vs-budget figure from several benchmark runs' results.json files")
    p.add_argument("results", type=Path, nargs="+", help="results.json files written by python -m eval.navigate")
    p.add_argument("--out", type=Path, required=True, help="PNG to write")
    return p


@cli_main()
def main(argv: Sequence[str] | None = None) -> int:
    """``python -m eval.navigate figures RESULTS.json ... --out FIGURE.png``: one success figure over several runs'
    ``results.json`` (one panel per suite)."""
    args = make_parser().parse_args(argv)
    check_output_file(args.out, "--out", "success.png")
    rows: list = []
    labels: dict = {}
    for path in args.results:
        try:
            res = json.loads(read_capped_text(path, MAX_JSON_BYTES, "a result file"))
            rows += res["summary"]
            labels.update(res["labels"])
        except (OSError, ValueError, KeyError, TypeError) as err:
            raise ValueError(f"{path}: not a results.json of python -m eval.navigate ({err})") from None
    from eval.common.methods import NAVIGATE, methods_of

    nav = methods_of(NAVIGATE)
    colors = {m: nav[m].color for m in labels if m in nav}
    print(f"wrote {success_figure(rows, args.out, labels=labels, colors=colors)}")
    return 0
