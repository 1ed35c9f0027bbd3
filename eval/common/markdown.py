"""Markdown tables of the experiments: a plain table builder and the closed-loop success-rate table.

:func:`success_markdown` renders :func:`eval.common.stats.aggregate` rows, one row per method and one column per
scenario value, with the paper's values alongside. The paper's columns are MPPI, log-MPPI and C-Uniform without
a noise level for the baselines (its Sigma list names low/medium/high only for the tables that show them), so
all three of our levels appear for each baseline family and the paper's number sits on its own row. The paper's
C-Uniform column is the method marked ``paper`` in :data:`eval.common.methods.METHODS` (``cu_table``, the max-flow
table on real rollouts); the other C-Uniform methods are ours and have no paper number.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from eval.common.methods import METHODS

__all__ = ["PAPER_FAMILY_OF", "table", "paper_label", "fmt_rate", "success_markdown"]

PAPER_FAMILY_OF = {"mppi": "MPPI", "log_mppi": "log-MPPI", "cuniform": "C-Uniform"}
"""the paper's column names, keyed by ``Method.family``"""


def table(head: Sequence[str], rows: Sequence[Sequence[Any]], align: str | None = None) -> str:
    """A markdown table; ``align``: one character per column, ``l`` or ``r`` (default: all left)."""
    rule = "|" + "".join("---:|" if a == "r" else "---|" for a in (align or "l" * len(head)))
    lines = ["| " + " | ".join(str(h) for h in head) + " |", rule]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


def paper_label(method_key: str) -> str:
    """How an our-method row relates to the paper's columns (for the tables' second column)."""
    m = METHODS[method_key]
    if m.family in ("mppi", "log_mppi"):
        return f"{PAPER_FAMILY_OF[m.family]} (one of our noise levels)"
    if m.paper:
        return f"{PAPER_FAMILY_OF[m.family]} (the paper's method)"
    return "ours, no paper column"


def fmt_rate(row: dict | None, with_ci: bool = True) -> str:
    if row is None:
        return "-"
    s = f"{row['success_rate']:.2f}"
    if with_ci:
        s += f" [{row['ci_low']:.2f}, {row['ci_high']:.2f}]"
    return s


def success_markdown(rows: list[dict], methods: Sequence[str], column_key: str, columns: Sequence[Any],
                     column_labels: Sequence[str], paper: dict | None, where: dict | None = None,
                     with_ci: bool = True) -> str:
    """A markdown table: one row per method, one column per value of ``column_key``, cells = success rate
    with its 95% Wilson interval; then one row per paper family with the paper's value in that column.

    ``rows``: :func:`eval.common.stats.aggregate` output; ``where``: other keys every used row must match (e.g.
    ``{"num_samples": 500}``); ``paper``: ``{column value: {family: rate}}`` (None or missing entries: "-").
    """
    where = where or {}

    def find(method: str, col: Any) -> dict | None:
        for r in rows:
            if r["method"] == method and r[column_key] == col and all(r.get(k) == v for k, v in where.items()):
                return r
        return None

    body = [[METHODS[m].label, paper_label(m), *(fmt_rate(find(m, c), with_ci) for c in columns)] for m in methods]
    if paper:
        for fam, name in PAPER_FAMILY_OF.items():
            vals = [(paper.get(c) or {}).get(fam) for c in columns]
            body.append([f"**paper: {name}**", name, *("-" if v is None else f"{v:.2f}" for v in vals)])
    return table(["method", "paper column", *column_labels], body)
