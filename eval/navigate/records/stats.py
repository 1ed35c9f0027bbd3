"""Statistics of the navigation benchmark's episode records: cycle-time histograms, per-group summaries with
Wilson intervals, paired comparisons against the best baseline (Newcombe interval + exact McNemar test). Their markdown tables are
a report's (:func:`eval.navigate.results.markdown`).

A record is one closed-loop episode (``python -m eval.navigate``), plain JSON::

    {"suite": "barn", "task_id": 12, "method": "mppi_1.0", "budget": 256, "seed": 123,
     "outcome": "goal" | "collision" | "timeout", "success": true, "time": 23.4, "path_length": 11.2,
     "steps": 117, "wall_s": 0.83, "cycle_hist": {"57": 3, "58": 40}, "cycles": 117}

Per-cycle wall times are kept as fixed log-spaced histograms (:mod:`eval.navigate.records.cycle_hist`, whose names
are importable from here too) so that episodes, seeds and runs merge by adding counts. One bin spans a factor
``10**(1/40)`` (about 5.9%), so a quantile read from a histogram is within about 3% (half a bin, geometric) of a time inside
the bin that holds it.
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Mapping, Sequence
from typing import Any

from eval.common.stats import mean_or_none, wilson_interval
from eval.navigate.records.cycle_hist import (
    BINS_PER_DECADE,
    NUM_BINS,
    T_MIN,
    bin_centre,
    cycle_histogram,
    histogram_quantile,
    merge_histograms,
)

__all__ = ["T_MIN", "BINS_PER_DECADE", "NUM_BINS", "OUTCOMES", "cycle_histogram", "merge_histograms",
           "histogram_quantile", "bin_centre", "summarize", "newcombe_paired_interval", "mcnemar_exact_p",
           "require_fields", "best_baseline", "by_episode", "compare_pair", "paired_comparisons", "fmt_rate", "fmt_score"]

OUTCOMES = ("goal", "collision", "timeout")
"""the possible ``outcome`` values of a record"""

_SUMMARY_FIELDS = ("outcome", "success", "time", "path_length")
_PAIR_FIELDS = ("suite", "budget", "method", "task_id", "seed", "success")


# ------------------------------------------------------------------------------------------------ summaries

def require_fields(r: Any, fields: Sequence[str], i: int) -> None:
    """A ValueError naming record (or row) ``i`` and its first missing field of ``fields``, or an outcome that
    is not one of :data:`OUTCOMES` or contradicts its ``success``; None when it is fine."""
    if not isinstance(r, Mapping):
        raise ValueError(f"record {i} is a {type(r).__name__}, not a mapping")
    missing = [f for f in fields if f not in r]
    if missing:
        raise ValueError(f"record {i} lacks the field(s) {', '.join(missing)}: {dict(r)!r}")
    if "outcome" in r and r["outcome"] not in OUTCOMES:
        raise ValueError(f"record {i} has outcome {r['outcome']!r}, not one of {', '.join(OUTCOMES)}")
    if "outcome" in r and "success" in r and bool(r["success"]) != (r["outcome"] == "goal"):
        raise ValueError(f"record {i}: success={r['success']!r} contradicts outcome={r['outcome']!r}")


def _group(records: Sequence[Mapping], keys: Sequence[str]) -> dict[tuple, list[Mapping]]:
    """Records grouped by the values of ``keys``, groups in first-appearance order."""
    groups: dict[tuple, list[Mapping]] = {}
    for r in records:
        groups.setdefault(tuple(r[k] for k in keys), []).append(r)
    return groups


def _rate(row: dict, name: str, count: int, n: int) -> None:
    """Set ``<name>_rate`` and its 95% Wilson ``_low`` / ``_high`` in ``row``."""
    lo, hi = wilson_interval(count, n)
    row[f"{name}_rate"] = count / n
    row[f"{name}_rate_low"] = lo
    row[f"{name}_rate_high"] = hi


def _median_or_none(values: Sequence[float]) -> float | None:
    return statistics.median(values) if values else None


def _ms(seconds: float | None) -> float | None:
    return None if seconds is None else 1000.0 * seconds


def _summary_row(key: tuple, keys: Sequence[str], recs: Sequence[Mapping],
                 scores: Mapping[str, float] | None = None) -> dict:
    """One summary row of a group (see :func:`summarize`)."""
    n = len(recs)
    good = [r for r in recs if r["success"]]
    row: dict[str, Any] = dict(zip(keys, key))
    row.update(n=n, successes=len(good), collisions=sum(r["outcome"] == "collision" for r in recs),
               timeouts=sum(r["outcome"] == "timeout" for r in recs))
    for name, count in (("success", row["successes"]), ("collision", row["collisions"]),
                        ("timeout", row["timeouts"])):
        _rate(row, name, count, n)
    for field in ("path_length", "time"):
        vals = [float(r[field]) for r in good]
        row[f"{field}_mean"] = mean_or_none(vals)
        row[f"{field}_median"] = _median_or_none(vals)
    hist = merge_histograms(r.get("cycle_hist") or {} for r in recs)
    row["cycle_ms_median"] = _ms(histogram_quantile(hist, 0.5))
    row["cycle_ms_p95"] = _ms(histogram_quantile(hist, 0.95))
    row["wall_s"] = float(sum(r.get("wall_s", 0.0) for r in recs))
    if scores is not None:
        from eval.navigate.records.score import score_summary

        mine = [scores[r["key"]] for r in recs if r.get("key") in scores]
        row.update(score_summary(mine if len(mine) == n else []))
    return row


def summarize(records: Sequence[Mapping], keys: Sequence[str] = ("suite", "method", "budget"),
              scores: Mapping[str, float] | None = None) -> list[dict]:
    """One row per group of ``keys`` (first-appearance order).

    Row: the key values, ``n``, ``successes``, ``collisions``, ``timeouts``; ``success_rate``,
    ``collision_rate``, ``timeout_rate`` each with 95% Wilson ``<name>_rate_low`` / ``_high``;
    ``path_length_mean`` / ``_median`` (m) and ``time_mean`` / ``_median`` (s) over successful episodes (None
    without one); ``cycle_ms_median`` / ``cycle_ms_p95`` (ms, from the merged cycle histograms, None without
    any); ``wall_s`` (sum of episode compute seconds); with ``scores`` (each record's BARN score by its ``key``,
    :func:`eval.navigate.score.episode_scores`), ``score_mean`` / ``score_low`` / ``score_high`` (None unless
    every record of the group has a score).
    """
    records = list(records)
    for i, r in enumerate(records):
        require_fields(r, (*keys, *_SUMMARY_FIELDS), i)
    return [_summary_row(key, keys, recs, scores) for key, recs in _group(records, keys).items()]


# ------------------------------------------------------------------------------------------------ paired tests

def _paired_phi(a: int, b: int, c: int, d: int) -> float:
    """Newcombe's continuity-corrected correlation phi* of a paired 2x2 table (0 with an empty margin)."""
    n = a + b + c + d
    margins = (a + b) * (c + d) * (a + c) * (b + d)
    if margins == 0:
        return 0.0
    cross = a * d - b * c
    if cross > n / 2:
        return (cross - n / 2) / math.sqrt(margins)
    if cross >= 0:
        return 0.0
    return cross / math.sqrt(margins)


def newcombe_paired_interval(a: int, b: int, c: int, d: int, z: float = 1.96) -> tuple[float, float]:
    """Newcombe's (1998, method 10) hybrid score interval ``(low, high)`` for ``p1 - p2`` of paired outcomes.

    Counts: ``a`` both succeed, ``b`` only the first, ``c`` only the second, ``d`` neither; ``p1 = (a+b)/n``,
    ``p2 = (a+c)/n``. The Wilson intervals ``(l1, u1)``, ``(l2, u2)`` of the margins are combined with the
    correlation phi* (:func:`_paired_phi`)::

        low  = D - sqrt((p1-l1)^2 - 2 phi (p1-l1)(u2-p2) + (u2-p2)^2)
        high = D + sqrt((p2-l2)^2 - 2 phi (p2-l2)(u1-p1) + (u1-p1)^2)
    """
    counts = (a, b, c, d)
    if any(isinstance(x, bool) or not isinstance(x, int) or x < 0 for x in counts):
        raise ValueError(f"paired counts must be non-negative integers, got {counts}")
    n = a + b + c + d
    if n == 0:
        raise ValueError("no pairs: the paired interval needs at least one pair")
    p1, p2 = (a + b) / n, (a + c) / n
    l1, u1 = wilson_interval(a + b, n, z)
    l2, u2 = wilson_interval(a + c, n, z)
    phi = _paired_phi(a, b, c, d)
    diff = p1 - p2
    # max(0, .): the radicand is a sum of squares minus a cross term with |phi| <= 1, >= 0 up to rounding
    low = diff - math.sqrt(max(0.0, (p1 - l1) ** 2 - 2 * phi * (p1 - l1) * (u2 - p2) + (u2 - p2) ** 2))
    high = diff + math.sqrt(max(0.0, (p2 - l2) ** 2 - 2 * phi * (p2 - l2) * (u1 - p1) + (u1 - p1) ** 2))
    return max(-1.0, low), min(1.0, high)


def mcnemar_exact_p(wins: int, losses: int) -> float:
    """Exact two-sided McNemar p-value: binomial test of ``wins`` of ``wins + losses`` at p = 0.5 (1 if none)."""
    if wins < 0 or losses < 0:
        raise ValueError(f"wins and losses must be non-negative, got {wins}, {losses}")
    if wins + losses == 0:
        return 1.0
    from scipy.stats import binomtest  # scipy only here: the rest of the module needs none

    return float(binomtest(wins, wins + losses, 0.5).pvalue)


def best_baseline(by_method: Mapping[str, Sequence[Mapping]], baselines: Sequence[str]) -> str | None:
    """The baseline with the highest success rate among ``by_method``; ties go to the earlier in ``baselines``."""
    best, best_rate = None, -1.0
    for m in baselines:  # strict '>' keeps the earlier baseline on a tie
        recs = by_method.get(m)
        if recs:
            rate = sum(bool(r["success"]) for r in recs) / len(recs)
            if rate > best_rate:
                best, best_rate = m, rate
    return best


def by_episode(recs: Sequence[Mapping], where: str) -> dict[tuple, bool]:
    """``{(task_id, seed): success}``; ValueError on a repeated episode (pairs would be ambiguous)."""
    out: dict[tuple, bool] = {}
    for r in recs:
        key = (r["task_id"], r["seed"])
        if key in out:
            raise ValueError(f"{where}: episode task_id={key[0]!r}, seed={key[1]!r} appears twice")
        out[key] = bool(r["success"])
    return out


def _verdict(p: float, diff: float) -> str:
    if p < 0.05 and diff > 0:
        return "better"
    if p < 0.05 and diff < 0:
        return "worse"
    return "tie"


def compare_pair(suite: Any, budget: Any, method: str, baseline: str, mine: dict[tuple, bool],
                 base: dict[tuple, bool]) -> dict | None:
    """One :func:`paired_comparisons` row of ``method`` against ``baseline`` over the episodes both ran (``mine``
    and ``base`` from :func:`by_episode`); None without a common episode."""
    common = [k for k in mine if k in base]
    if not common:
        return None
    a = sum(mine[k] and base[k] for k in common)
    wins = sum(mine[k] and not base[k] for k in common)
    losses = sum(base[k] and not mine[k] for k in common)
    d = len(common) - a - wins - losses
    n = len(common)
    diff = (wins - losses) / n
    low, high = newcombe_paired_interval(a, wins, losses, d)
    p = mcnemar_exact_p(wins, losses)
    return dict(suite=suite, budget=budget, method=method, baseline=baseline, n=n, method_successes=a + wins,
                baseline_successes=a + losses, wins=wins, losses=losses, diff=diff, diff_low=low, diff_high=high,
                p_value=p, verdict=_verdict(p, diff))


def paired_comparisons(records: Sequence[Mapping], baselines: Sequence[str]) -> list[dict]:
    """Each method against the best baseline of its (suite, budget), paired on (task_id, seed).

    The best baseline of a (suite, budget) is the one of ``baselines`` with the highest success rate there (a
    tie goes to the earlier in ``baselines``); a (suite, budget) without any baseline is skipped, and so is a
    method sharing no episode with it. Row: ``suite``, ``budget``, ``method``, ``baseline``, ``n`` (pairs),
    ``method_successes``, ``baseline_successes``, ``wins`` (method succeeded, baseline failed), ``losses``,
    ``diff`` (success-rate difference over the pairs) with its 95% Newcombe interval ``diff_low`` /
    ``diff_high``, the exact McNemar ``p_value`` and ``verdict`` ("better" / "worse" at p < 0.05, else "tie").
    """
    records = list(records)
    baselines = list(baselines)
    if not baselines:
        raise ValueError("no baselines given")
    for i, r in enumerate(records):
        require_fields(r, _PAIR_FIELDS, i)
    present = {r["method"] for r in records}
    absent = [m for m in baselines if m not in present]
    if absent:
        raise ValueError(f"baseline(s) {', '.join(map(repr, absent))} have no records "
                         f"(methods present: {', '.join(map(repr, sorted(present)))})")
    rows = []
    for (suite, budget), recs in _group(records, ("suite", "budget")).items():
        by_method = {m[0]: rs for m, rs in _group(recs, ("method",)).items()}
        best = best_baseline(by_method, baselines)
        if best is None:
            continue
        base = by_episode(by_method[best], f"suite={suite!r}, budget={budget!r}, method={best!r}")
        for method, mrecs in by_method.items():
            if method == best:
                continue
            mine = by_episode(mrecs, f"suite={suite!r}, budget={budget!r}, method={method!r}")
            row = compare_pair(suite, budget, method, best, mine, base)
            if row is not None:
                rows.append(row)
    return rows


# ------------------------------------------------------------------------------------------------ formatting

def fmt_rate(row: Mapping, name: str) -> str:
    """``0.93 [0.88, 0.96]``: the ``<name>_rate`` of a summary row with its Wilson interval."""
    return f"{row[f'{name}_rate']:.2f} [{row[f'{name}_rate_low']:.2f}, {row[f'{name}_rate_high']:.2f}]"


def fmt_score(row: Mapping) -> str:
    """``0.27 [0.24, 0.30]``: a row's mean BARN score with its 95% interval ("-" without one)."""
    if row.get("score_mean") is None:
        return "-"
    return f"{row['score_mean']:.2f} [{row['score_low']:.2f}, {row['score_high']:.2f}]"
