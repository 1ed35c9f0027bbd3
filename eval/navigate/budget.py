"""Judge the navigation benchmark's methods at equal compute: per cycle-time budget, not per sample count.

    python -m eval.navigate budget out/navigate/barn --budgets-ms 2 5 10 20 --out budget.md --figure budget.png

A controller runs under a cycle budget in milliseconds, and methods cost different times per sample (a table
lookup, an MLP, Gaussian noise), so "which method for a 5 ms cycle?" is not answered by the benchmark's tables,
which compare methods at the same sample count K. From a benchmark folder (read through
:class:`eval.navigate.records.store.EpisodeStore`, the folder's one parser) this says:

* per (method, K): success with its 95% Wilson interval, the BARN Challenge's score (mean with its 95% interval;
  :mod:`eval.navigate.score`: ``success * OT / clip(time, 2 OT, 8 OT)``, OT the task's reference length over
  2 m/s), and the median and p95 cycle time (ms) over **all commands** of its episodes (:func:`eval.navigate.records.stats.summarize`, from the merged cycle histograms). All
  commands, not the median of per-episode medians: a real-time loop misses its deadline per command, so the
  share of commands over the budget is what matters, and per-episode medians would hide the slow tail and count
  a 10-command episode as much as a 500-command one. The histograms bin times by 5.9%, so a quantile is exact
  to about 3% (:mod:`eval.navigate.records.cycle_hist`);
* per budget B: for each method the best K that **fits**, i.e. whose **p95** cycle time is <= B (a loop that
  meets its deadline 95% of the time; a median that fits still misses half the deadlines of a loop sized to
  it). Best: the highest success rate among the K that fit; a tie goes to the faster (lower p95), then the
  smaller K. A method with no K that fits says so, with its fastest p95;
* each method at its K against the best Gaussian baseline (the registry's, :func:`eval.common.methods
  .gaussian_baselines`) at the baseline's own K that fits the same B: the exact McNemar test and the Newcombe
  interval of the difference, paired on (task, seed) over the episodes both ran (as ``python -m eval.navigate compare``
  pairs cells of different K). The best baseline is the one with the highest success rate at its fitting K (a
  tie: the earlier in the registry), chosen like the benchmark's own per-K comparison;
* each method at its K against the **best method of every other family** (:data:`FAMILIES`: Gaussian MPPI,
  log-normal, colored / smooth noise, mixtures, C-Uniform table, CU-MPPI, CFU-MPPI, uniform) at that method's own K
  that fits the same B, paired the same way; and per budget the **winner**, the best method of all. "Best" here
  (:func:`rank_key`): the highest success rate, a tie to the higher mean BARN score, then the lower p95, then the
  earlier in the registry (success ties are common on easy suites, where the score still tells methods apart).

Both sides' K are chosen by success on the same episodes the test then uses, so the pick is a little
optimistic for each; the table lists every K that fits so a reader can see what was chosen from.

Cycle times are wall times measured on the machine, with the workers and load of the run that wrote the
episodes: compare methods within one folder, not across machines. The CPU threads per episode are reported
when the records or settings carry them, else as unknown.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from cuniform_torch.common.fileio import write_bytes
from eval.common.markdown import table
from eval.common.methods import NAVIGATE, gaussian_baselines, methods_of
from eval.navigate.records import (
    EpisodeStore,
    best_baseline,
    by_episode,
    compare_pair,
    fmt_rate,
    fmt_score,
    score_summary,
    summarize,
)
from eval.navigate.score import episode_scores
from precompute.cli import ArgumentParser, check_output_file, cli_main, positive_float

__all__ = ["DEFAULT_BUDGETS_MS", "FIT_QUANTILE", "FITS", "FAMILIES", "family_of", "rank_key", "cells", "pick_k",
           "budget_rows", "winners", "pareto_front", "threads_note", "judge", "judge_folder", "render",
           "budget_figure", "main"]

DEFAULT_BUDGETS_MS = (2.0, 5.0, 10.0, 20.0)
"""cycle budgets (ms) judged when none are given"""
FIT_QUANTILE = "cycle_ms_p95"
"""the summary field a K must keep within a budget to fit it (module docstring: p95, not the median)"""
FITS = {"p95": "cycle_ms_p95", "median": "cycle_ms_median"}
"""what a K may be asked to keep within a budget (``fit=``): the p95 (the default, :data:`FIT_QUANTILE`), or the
median, only for folders written on a machine so loaded that the p95 measures the scheduler's preemptions rather
than the method (each command's time is wall time): a median that fits still misses half the deadlines of a loop
sized to it, so a page judged by it says so"""
FAMILIES: dict[str, tuple[str, ...]] = {
    "Gaussian MPPI": ("mppi_0.1", "mppi_0.3", "mppi_1.0"),
    "log-normal": ("log_mppi_0.3",),
    "colored / smooth noise": ("mppi_pink_1.0", "mppi_lowpass_1.0", "smppi_2.0", "kmppi_1.0"),
    "mixture": ("mix_cu_mppi_0.5",),
    "C-Uniform table": ("cu_table", "cu_coverage", "cu_mlp"),
    "CU-MPPI": ("cumppi", "cumppi_pipe"),
    "CFU-MPPI": ("cfu_mppi",),
    "uniform": ("uniform",),
}
"""the navigation benchmark's method families (issue 36): a method is paired with the best method of every other
family, so a noise level or a table variant is never its own rival; a key no family names is a family of its own
(:func:`family_of`). A test checks that every method of the registry has a family."""
_FAMILY_OF = {k: f for f, keys in FAMILIES.items() for k in keys}


def _field(fit: str) -> str:
    """The summary field of ``fit`` (:data:`FITS`); an unknown one names the known ones."""
    if fit not in FITS:
        raise ValueError(f"unknown fit {fit!r}; choose from {', '.join(FITS)}")
    return FITS[fit]


_UNKNOWN_THREADS = ("unknown: not recorded in settings.json or the records (this version's episodes run torch with "
                    "1 thread each, eval.navigate.episode; --workers, the CPU and the load are not recorded either)")


def _method_order(methods: Sequence[str]) -> list[str]:
    """Registry order first (the benchmark's tables' order), then methods the registry does not know."""
    known = [m for m in methods_of(NAVIGATE) if m in methods]
    return known + sorted(m for m in set(methods) if m not in known)


def family_of(method: str) -> str:
    """The family of ``method`` (:data:`FAMILIES`); a method no family names is its own family (its key)."""
    return _FAMILY_OF.get(method, method)


def rank_key(cell: Mapping, order: Mapping[str, int], field: str = FIT_QUANTILE) -> tuple:
    """Sort key of a chosen cell, best first: the highest success rate, then the higher mean BARN score (a cell
    without one after every scored cell), then the lower p95 cycle time (``field``), then the method earlier in
    ``order``."""
    score = cell.get("score_mean")
    return (-cell["success_rate"], score is None, -(score or 0.0), cell[field],
            order.get(cell["method"], len(order)))


def cells(records: Sequence[Mapping], scores: Mapping[str, float] | None = None) -> list[dict]:
    """One row per (method, K) of ``records`` (one suite): :func:`eval.navigate.records.stats.summarize`'s row (success
    with its Wilson interval, ``cycle_ms_median`` / ``cycle_ms_p95`` over all commands, None without any) plus
    ``commands`` (timed cycles), ``threads`` (the sorted distinct ``threads`` of its records when every record
    has one, else None) and the BARN score of ``scores`` (by record key; :func:`eval.navigate.score.score_summary`'s
    ``score_mean``, ``score_low``, ``score_high``, all None unless every episode of the cell has a score). Rows by
    method (registry order), then K."""
    records = list(records)
    if not records:
        raise ValueError("no episode records to judge")
    shared = [r["key"] for r in records if r.get("clock") == "lockstep"]
    if shared:  # their cycle times are a batched command's share, not a control cycle (eval.navigate.lockstep)
        raise ValueError(f"{len(shared)} record(s) (e.g. {shared[0]}) ran with --lockstep: their cycle times are a "
                         "batched command's share, not a control cycle; judge a folder run without --lockstep")
    rows = summarize(records, keys=("method", "budget"))
    by_cell: dict[tuple, list[Mapping]] = {}
    for r in records:
        by_cell.setdefault((r["method"], r["budget"]), []).append(r)
    for row in rows:
        mine = by_cell[(row["method"], row["budget"])]
        row["commands"] = int(sum(r.get("cycles", 0) for r in mine))
        threads = [r.get("threads") for r in mine]
        row["threads"] = sorted(set(threads)) if all(isinstance(t, int) for t in threads) else None
        mine_scores = [scores[r["key"]] for r in mine if r.get("key") in scores] if scores else []
        row.update(score_summary(mine_scores if len(mine_scores) == len(mine) else []))
    order = {m: i for i, m in enumerate(_method_order([r["method"] for r in rows]))}
    return sorted(rows, key=lambda r: (order[r["method"]], r["budget"]))


def pick_k(method_cells: Sequence[Mapping], budget_ms: float,
           field: str = FIT_QUANTILE) -> tuple[dict | None, list[int]]:
    """``(the chosen cell, every K that fits)`` of one method at ``budget_ms``: a cell fits when its
    ``field`` (:data:`FIT_QUANTILE`) is <= ``budget_ms``; chosen is the highest success, a tie to the lower p95, then the
    smaller K (module docstring). ``(None, [])`` when no K fits."""
    fit = [c for c in method_cells if c[field] is not None and c[field] <= budget_ms]
    if not fit:
        return None, []
    best = min(fit, key=lambda c: (-c["success_rate"], c[field], c["budget"]))
    return dict(best), sorted(c["budget"] for c in fit)


def _fastest(method_cells: Sequence[Mapping], field: str = FIT_QUANTILE) -> Mapping | None:
    timed = [c for c in method_cells if c[field] is not None]
    return min(timed, key=lambda c: (c[field], c["budget"])) if timed else None


def _pair(records: Sequence[Mapping], mine: tuple[str, int], base: tuple[str, int]) -> dict | None:
    """``mine`` against ``base`` (each ``(method, K)``), paired on (task, seed): the benchmark's comparison row
    (:func:`eval.navigate.records.stats.paired_comparisons`' fields), None without a common episode."""
    sides = [by_episode([r for r in records if (r["method"], r["budget"]) == cell], f"{cell[0]}@{cell[1]}")
             for cell in (mine, base)]
    return compare_pair(None, None, f"{mine[0]}@{mine[1]}", f"{base[0]}@{base[1]}", *sides)


def budget_rows(records: Sequence[Mapping], cell_rows: Sequence[Mapping], budgets_ms: Sequence[float],
                baselines: Sequence[str], fit: str = "p95") -> list[dict]:
    """One row per (budget, method): ``budget_ms``, ``method``, ``cell`` (the chosen (method, K) cell of
    :func:`cells`, None when no K fits), ``fits`` (every K that fits), ``fastest`` (its fastest cell, for the
    note when none fits), ``baseline`` / ``baseline_k`` (the best Gaussian baseline at its own fitting K, None
    when none fits), ``is_baseline`` (this row is that baseline) and ``comparison`` (the benchmark's paired
    comparison row against it, :func:`eval.navigate.records.stats.paired_comparisons`' fields; None for the baseline
    itself, without a fitting K or without a common (task, seed) episode, and ``pairs_note`` says which);
    ``family``, and ``rival`` / ``rival_k`` / ``rival_family`` (the best method of all other families at its own
    fitting K, :func:`rank_key`; None when none fits), ``rival_comparison`` against it and ``rival_note`` (why
    there is none), as for the baseline. ``fit``: what a K keeps within the budget (:data:`FITS`)."""
    field = _field(fit)
    for b in budgets_ms:
        if isinstance(b, bool) or not isinstance(b, (int, float)) or not math.isfinite(b) or b <= 0:
            raise ValueError(f"cycle budgets are finite numbers of ms > 0, got {b!r}")
    by_method: dict[str, list[Mapping]] = {}
    for c in cell_rows:
        by_method.setdefault(c["method"], []).append(c)
    present = [m for m in baselines if m in by_method]
    order = {m: i for i, m in enumerate(_method_order(list(by_method)))}
    out = []
    for budget in budgets_ms:
        picks = {m: pick_k(cs, budget, field) for m, cs in by_method.items()}
        chosen = {m: (r["method"], r["budget"]) for m, (r, _) in picks.items() if r is not None}
        # the best baseline, as the benchmark's per-K comparison picks it, among the baselines' chosen cells
        base_recs = {m: [r for r in records if (r["method"], r["budget"]) == chosen[m]] for m in present if m in chosen}
        best = best_baseline(base_recs, present) if base_recs else None
        ranked = sorted((c for c, _ in picks.values() if c is not None), key=lambda c: rank_key(c, order, field))
        for method, (cell, fits) in picks.items():
            row = dict(budget_ms=float(budget), method=method, cell=cell, fits=fits,
                       fastest=_fastest(by_method[method], field), baseline=best,
                       baseline_k=chosen[best][1] if best else None, is_baseline=method == best,
                       comparison=None, pairs_note="")
            if cell is None:
                row["pairs_note"] = "no K fits"
            elif best is None:
                row["pairs_note"] = ("no Gaussian baseline fits" if present else
                                     "no Gaussian baseline in the folder")
            elif method != best:
                row["comparison"] = _pair(records, chosen[method], chosen[best])
                if row["comparison"] is None:  # said in the table, not a failure of the other rows
                    row["pairs_note"] = "no common (task, seed) episode"
            row.update(_rival(records, method, cell, ranked))
            out.append(row)
    return out


def _rival(records: Sequence[Mapping], method: str, cell: Mapping | None, ranked: Sequence[Mapping]) -> dict:
    """``method``'s row fields against the best chosen cell of ``ranked`` (best first) of another family."""
    family = family_of(method)
    rival = next((c for c in ranked if family_of(c["method"]) != family), None)
    out = dict(family=family, rival=None if rival is None else rival["method"],
               rival_k=None if rival is None else rival["budget"],
               rival_family=None if rival is None else family_of(rival["method"]), rival_comparison=None, rival_note="")
    if cell is None:
        out["rival_note"] = "no K fits"
    elif rival is None:
        out["rival_note"] = "no method of another family fits"
    else:
        out["rival_comparison"] = _pair(records, (method, cell["budget"]), (rival["method"], rival["budget"]))
        if out["rival_comparison"] is None:
            out["rival_note"] = "no common (task, seed) episode"
    return out


def winners(res: Mapping) -> list[dict]:
    """Per budget of :func:`judge`'s ``res``: its winner's :func:`budget_rows` row (the best chosen cell of all
    methods, :func:`rank_key`, with its pairing against the best other family), or a row with ``cell`` None and
    ``method`` None when no method fits that budget."""
    order = {m: i for i, m in enumerate(_method_order([c["method"] for c in res["cells"]]))}
    field = _field(res.get("fit", "p95"))
    out = []
    for budget in res["budgets_ms"]:
        rows = [r for r in res["budgets"] if r["budget_ms"] == budget and r["cell"] is not None]
        if rows:
            out.append(min(rows, key=lambda r: rank_key(r["cell"], order, field)))
        else:
            out.append(dict(budget_ms=budget, method=None, cell=None, rival=None, rival_comparison=None,
                            rival_note="no method fits"))
    return out


def pareto_front(points: Sequence[tuple[float, float]]) -> list[bool]:
    """For ``(time, success)`` points: whether each is on the Pareto front (no other point is at most as slow and
    at least as successful, and strictly better in one)."""
    front = []
    for i, (t, s) in enumerate(points):
        front.append(not any((t2 <= t and s2 >= s and (t2 < t or s2 > s))
                             for j, (t2, s2) in enumerate(points) if j != i))
    return front


def threads_note(settings: Mapping[str, Any], cell_rows: Sequence[Mapping]) -> str:
    """What the folder says about the CPU threads per episode: the records' ``threads``, else settings', else
    unknown (with what the code of this version does)."""
    seen = {t for c in cell_rows if c.get("threads") for t in c["threads"]}
    if seen and all(c.get("threads") for c in cell_rows):
        return f"{', '.join(map(str, sorted(seen)))} (from the records)"
    if isinstance(settings.get("threads"), int):
        return f"{settings['threads']} (from settings.json)"
    return _UNKNOWN_THREADS


def judge(settings: Mapping[str, Any], records: Sequence[Mapping], budgets_ms: Sequence[float] = DEFAULT_BUDGETS_MS,
          baselines: Sequence[str] | None = None, scores: Mapping[str, float] | None = None,
          score_note: str = "", fit: str = "p95") -> dict:
    """The judgement of one folder's ``settings`` and ``records``: ``suite``, ``episodes``, ``threads`` (a note),
    ``baselines`` (the Gaussian baselines present), ``budgets_ms``, ``cells`` (:func:`cells`, with the BARN score of
    ``scores``, by record key) and ``budgets`` (:func:`budget_rows`), ``score_note`` (what lacks a score, and why).
    ``baselines``: default the registry's Gaussian baselines of the navigation benchmark; ``fit`` (kept in the
    result): what a K keeps within a budget (:data:`FITS`)."""
    _field(fit)
    budgets = sorted({float(b) for b in budgets_ms})
    if not budgets:
        raise ValueError("give at least one cycle budget (ms)")
    records = list(records)
    cell_rows = cells(records, scores)
    base = list(gaussian_baselines(NAVIGATE) if baselines is None else baselines)
    present = [m for m in base if any(c["method"] == m for c in cell_rows)]
    return dict(suite=settings.get("suite"), episodes=len(records), threads=threads_note(settings, cell_rows),
                baselines=present, budgets_ms=budgets, cells=cell_rows,
                budgets=budget_rows(records, cell_rows, budgets, base, fit), score_note=score_note, fit=fit)


def judge_folder(folder: str | Path, budgets_ms: Sequence[float] = DEFAULT_BUDGETS_MS,
                 barn_file: str | Path | None = None, cache: str | Path | None = None, fit: str = "p95") -> dict:
    """:func:`judge` of a benchmark folder, read through :meth:`EpisodeStore.load` (checked; read only), with each
    episode's BARN score (:func:`eval.navigate.score.episode_scores`: ``barn_file`` when the run used another than
    the shipped one; the geodesic reference lengths cached under ``cache`` when given); ``fit``: :data:`FITS`."""
    _field(fit)  # before the folder is read
    settings, by_key = EpisodeStore(folder).load()
    if not by_key:
        raise ValueError(f"{folder} holds no episode yet (python -m eval.navigate --out {folder})")
    records = list(by_key.values())
    scores, note = episode_scores(settings, records, barn_file, cache)
    return {**judge(settings, records, budgets_ms, scores=scores, score_note=note, fit=fit), "folder": str(folder)}


# ------------------------------------------------------------------------------------------------ markdown

def _ms(x: float | None) -> str:
    return "-" if x is None else f"{x:.3g}"




def _budget_line(row: Mapping, fit: str = "p95") -> list[Any]:
    b = f"{row['budget_ms']:g} ms"
    cell = row["cell"]
    if cell is None:
        fast = row["fastest"]
        why = ("no cycle times recorded" if fast is None else
               f"no K fits (fastest: {fit} {_ms(fast[FITS[fit]])} ms at K = {fast['budget']})")
        return [b, row["method"], "-", "-", why, "-", "-", "-", "-", "-", "-", "-", "-"]
    head = [b, row["method"], cell["budget"], ", ".join(map(str, row["fits"])), fmt_rate(cell, "success"),
            fmt_score(cell), _ms(cell[FITS[fit]])]
    c = row["comparison"]
    if row["is_baseline"]:
        return head + ["(best baseline)", "-", "-", "-", "-", "-"]
    if c is None:
        return head + [row["pairs_note"], "-", "-", "-", "-", "-"]
    return head + [c["baseline"], c["n"], f"{c['wins']} / {c['losses']}",
                   f"{c['diff']:+.2f} [{c['diff_low']:+.2f}, {c['diff_high']:+.2f}]", f"{c['p_value']:.3g}",
                   c["verdict"]]


def pair_cells(c: Mapping | None, note: str = "") -> list[Any]:
    """The paired-test columns of a comparison row: against, pairs, wins / losses, diff [95% CI], McNemar p,
    verdict (``note`` and dashes without one)."""
    if c is None:
        return [note or "-", "-", "-", "-", "-", "-"]
    return [c["baseline"], c["n"], f"{c['wins']} / {c['losses']}",
            f"{c['diff']:+.2f} [{c['diff_low']:+.2f}, {c['diff_high']:+.2f}]", f"{c['p_value']:.3g}", c["verdict"]]


PAIR_HEAD = ["against", "pairs", "wins / losses", "diff [95% CI]", "McNemar p", "verdict"]
"""the columns of :func:`pair_cells`"""


def _rival_line(row: Mapping, fit: str = "p95") -> list[Any]:
    cell = row["cell"]
    head = [f"{row['budget_ms']:g} ms", row["method"], row["family"]]
    if cell is None:
        return head + ["-", "-", "-", "-"] + pair_cells(None, row["rival_note"])
    return head + [cell["budget"], fmt_rate(cell, "success"), fmt_score(cell), _ms(cell[FITS[fit]])] + pair_cells(
        row["rival_comparison"], row["rival_note"])


def render(res: Mapping) -> str:
    """The markdown of :func:`judge`'s result: the facts, the per-(method, K) table, the time-budget table."""
    where = f" ({res['folder']})" if res.get("folder") else ""
    base = ", ".join(res["baselines"]) or "none in the folder"
    parts = [f"# Equal compute: {res['suite']}{where}",
             f"{res['episodes']} episodes. Cycle times: wall time of each controller command, over all commands of "
             f"a cell's episodes, on the machine and under the load of the run that wrote them. CPU threads per "
             f"episode: {res['threads']}. Gaussian baselines: {base}. BARN score: the BARN Challenge's "
             f"success x OT / clip(time, 2 OT, 8 OT), OT the task's reference length / 2 m/s (max 0.5; "
             f"eval.navigate.score), mean [95% CI] over a cell's episodes"
             + (f" ({res['score_note']})" if res.get("score_note") else "") + "."]
    body = [[c["method"], c["budget"], c["n"], fmt_rate(c, "success"), fmt_score(c), c["commands"],
             _ms(c["cycle_ms_median"]), _ms(c["cycle_ms_p95"]),
             ", ".join(map(str, c["threads"])) if c["threads"] else "unknown"]
            for c in res["cells"]]
    parts.append("## Per method and K\n\n" + table(
        ["method", "K", "episodes", "success [95% CI]", "BARN score [95% CI]", "commands", "cycle ms median",
         "cycle ms p95", "threads"], body, align="lrrllrrrl"))
    fit = res.get("fit", "p95")
    lines = [_budget_line(r, fit) for r in res["budgets"]]
    loaded = ("" if fit == "p95" else " (**judged by the median**, not the p95: for a machine so loaded that the "
              "p95 measures the scheduler, not the method; a loop sized to a median misses half its deadlines)")
    parts.append(
        f"## Time budgets\n\nA K fits a budget when its {fit} cycle time is within it{loaded}; each method at its most "
        "successful K that fits, against the best Gaussian baseline at its own K that fits (paired on (task, "
        "seed): wins / losses, success difference with its 95% Newcombe interval, exact McNemar p; better / "
        "worse at p < 0.05).\n\n" + table(
            ["budget", "method", "K", "K that fit", "success [95% CI]", "BARN score", f"{fit} ms", "against", "pairs",
             "wins / losses", "diff [95% CI]", "McNemar p", "verdict"], lines, align="rlrlllrlrrlrl"))
    win = [f"{w['budget_ms']:g} ms: " + ("no method fits" if w["cell"] is None else
                                         f"**{w['method']}** @ K = {w['cell']['budget']}") for w in winners(res)]
    parts.append(
        "## Against the best of the other families\n\nEach method at its K that fits, against the best method of "
        "every other family at its own K that fits (best: the highest success, a tie to the higher mean BARN score, "
        f"then the lower {fit}; paired as above). The winner per budget (the best of all): " + "; ".join(win) + ".\n\n"
        + table(["budget", "method", "family", "K", "success [95% CI]", "BARN score", f"{fit} ms", *PAIR_HEAD],
                [_rival_line(r, fit) for r in res["budgets"]], align="rllrllrlrrlrl"))
    return "\n\n".join(parts) + "\n"


# ------------------------------------------------------------------------------------------------ figure

def budget_figure(res: Mapping, path: str | Path, labels: Mapping[str, str] | None = None,
                  colors: Mapping[str, str] | None = None) -> Path:
    """Success against median cycle time (log x) per method, one line through its K (labelled), Wilson error
    bars, a thin bar from the median to the p95; the method's Pareto front (median time, success) filled, the
    rest hollow; a vertical line at each budget. Written atomically as a PNG to ``path``, which is returned."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    from eval.common.figures import plt, save_figure
    from eval.navigate.figures import method_color

    timed = [c for c in res["cells"] if c["cycle_ms_median"] is not None]
    if not timed:
        raise ValueError("no cell has cycle times: nothing to draw")
    fig, ax = plt.subplots(figsize=(7.2, 4.4))
    try:
        methods = list(dict.fromkeys(c["method"] for c in timed))
        for i, m in enumerate(methods):
            mine = sorted((c for c in timed if c["method"] == m), key=lambda c: c["budget"])
            x = [c["cycle_ms_median"] for c in mine]
            y = [c["success_rate"] for c in mine]
            color = method_color(m, i, colors)
            ax.plot(x, y, color=color, linewidth=1.2, label=(labels or {}).get(m, m))
            ax.errorbar(x, y, yerr=[[c["success_rate"] - c["success_rate_low"] for c in mine],
                                    [c["success_rate_high"] - c["success_rate"] for c in mine]],
                        xerr=[[0.0] * len(mine), [c["cycle_ms_p95"] - c["cycle_ms_median"] for c in mine]],
                        fmt="none", ecolor=color, elinewidth=0.7, capsize=2, alpha=0.6)
            front = pareto_front(list(zip(x, y)))
            for c, xi, yi, on in zip(mine, x, y, front):
                ax.plot(xi, yi, marker="o", markersize=6 if on else 5, color=color,
                        markerfacecolor=color if on else "white", linestyle="none", zorder=3)
                ax.annotate(f"{c['budget']}", (xi, yi), textcoords="offset points", xytext=(4, 4), fontsize=7,
                            color=color)
        for b in res["budgets_ms"]:
            ax.axvline(b, color="0.4", linestyle="--", linewidth=0.8)
            ax.annotate(f"{b:g} ms", (b, 1.03), fontsize=7, ha="center", va="bottom", color="0.3",
                        annotation_clip=False)
        ax.set_xscale("log")
        ax.xaxis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
        ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))  # 2, 5, 10, not 2x10^0
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_ylim(-0.03, 1.03)
        ax.set_xlabel("median cycle time (ms, log); bars to the right reach the p95")
        ax.set_ylabel("success rate")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0))
        fig.suptitle(f"{res['suite']}: success vs cycle time (numbers: K; filled: each method's Pareto front)",
                     fontsize=10)
        return save_figure(fig, Path(path))
    finally:
        plt.close(fig)


# ------------------------------------------------------------------------------------------------ command

def make_parser() -> ArgumentParser:
    """The command's flags (checked as they parse)."""
    p = ArgumentParser(prog="python -m eval.navigate budget", description=(__doc__ or "").split("\n\n")[0])
    p.add_argument("folder", type=Path, help="the benchmark folder (python -m eval.navigate --out)")
    p.add_argument("--budgets-ms", nargs="+", type=positive_float, default=list(DEFAULT_BUDGETS_MS),
                   metavar="MS", help="cycle budgets in ms (default: 2 5 10 20)")
    p.add_argument("--out", type=Path, default=None, help="also write the markdown here")
    p.add_argument("--figure", type=Path, default=None, help="draw success vs cycle time to this PNG")
    p.add_argument("--barn-file", type=Path, default=None,
                   help="the BARN file the run used, when not the shipped one (for the BARN score)")
    p.add_argument("--cache", type=Path, default=Path("out/navigate/cache"),
                   help="where the geodesic reference lengths of forest and clutter tasks are cached")
    return p


def write_budget(res: Mapping, md_path: str | Path | None, figure_path: str | Path | None) -> list[Path]:
    """The judgement ``res`` as markdown and as the figure (each when its path is given); the paths written."""
    written = []
    if md_path is not None:
        write_bytes(md_path, render(res).encode())
        written.append(Path(md_path))
    if figure_path is not None:
        nav = methods_of(NAVIGATE)
        known = [c["method"] for c in res["cells"] if c["method"] in nav]
        written.append(Path(budget_figure(res, figure_path, labels={m: nav[m].label_in(NAVIGATE) for m in known},
                                          colors={m: nav[m].color for m in known})))
    return written


@cli_main()
def main(argv: Sequence[str] | None = None) -> int:
    args = make_parser().parse_args(argv)
    for flag, path, example in (("--out", args.out, "budget.md"), ("--figure", args.figure, "budget.png")):
        if path is not None:
            check_output_file(path, flag, example)
    res = judge_folder(args.folder, args.budgets_ms, args.barn_file, args.cache)
    print(render(res), end="")
    for path in write_budget(res, args.out, args.figure):
        print(f"wrote {path}")
    return 0

