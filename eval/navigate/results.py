"""The results of a benchmark run (:mod:`eval.navigate.run`): its summary rows, paired comparisons and facts; their
markdown (the success table per budget, then :func:`markdown`'s tables); the files under ``--out``."""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from cuniform_torch.common.fileio import write_bytes, write_json
from eval.common.markdown import table
from eval.common.methods import NAVIGATE, gaussian_baselines, methods_of
from eval.navigate.records.stats import fmt_rate, fmt_score, paired_comparisons, require_fields, summarize
from precompute.worlds.suites import NavTask
from precompute.worlds.tasks import task_summary

__all__ = ["result", "write_outputs", "render", "success_pivot", "markdown"]


def result(cfg: Any, records: list[dict], tasks: Sequence[NavTask], methods: Sequence[str], wall: float,
           load0: float, ray_address: str | None, ran: int | None = None) -> dict:
    """Summary rows, paired comparisons and the run's facts."""
    summary = summarize(records)
    baselines = [b for b in gaussian_baselines(NAVIGATE) if b in methods]
    nav = methods_of(NAVIGATE)
    comparisons = paired_comparisons(records, baselines) if baselines else []
    return dict(config=dataclasses.asdict(cfg), tasks=task_summary(tasks), summary=summary, comparisons=comparisons,
                run=dict(wall_s=round(wall, 1), load_before=round(load0, 2), load_after=round(os.getloadavg()[0], 2),
                         cpus=os.cpu_count(), workers=cfg.workers, ray=ray_address, episodes=len(records),
                         ran=len(records) if ran is None else ran,
                         episode_compute_s=round(sum(r.get("wall_s", 0.0) for r in records), 1)),
                labels={m: nav[m].label_in(NAVIGATE) for m in methods})


def write_outputs(res: dict, out: Path) -> list[Path]:
    """``results.json``, ``results.md``, ``success.png`` and TensorBoard scalars under ``out``."""
    from eval.navigate.figures import success_figure, write_tensorboard

    md = render(res)
    write_json(out / "results.json", res)
    write_bytes(out / "results.md", md.encode())
    nav = methods_of(NAVIGATE)
    colors = {m: nav[m].color for m in res["labels"]}
    fig = success_figure(res["summary"], out / "success.png", labels=res["labels"], colors=colors)
    write_tensorboard(res["summary"], out / "tb")
    return [out / "results.json", out / "results.md", fig, out / "tb"]


def render(res: dict) -> str:
    """The markdown of a result: the run's facts, then :func:`markdown`'s tables."""
    r, c = res["run"], res["config"]
    ran = r.get("ran", r["episodes"])
    earlier = f", {r['episodes'] - ran} from earlier runs" if ran < r["episodes"] else ""
    head = (f"# Navigation benchmark: {c['suite']}\n\n{res['tasks']['count']} tasks, budgets "
            f"{', '.join(map(str, c['budgets']))}, {r['episodes']} episodes ({ran} run now{earlier}; "
            f"{r.get('episode_compute_s', 0):.0f} s of episode compute in all); this run took {r['wall_s']:.0f} s "
            f"wall on {r['cpus']} CPUs with {r['workers']} worker(s){' on Ray' if r['ray'] else ''} (1-min load "
            f"{r['load_before']} before, {r['load_after']} after)\n\n")
    return head + success_pivot(res["summary"], res["comparisons"]) + "\n\n" + markdown(res["summary"], res["comparisons"])


def success_pivot(summary: Sequence[dict], comparisons: Sequence[dict]) -> str:
    """Success rate [95% CI] per method (rows) and budget (columns), each marked against the best Gaussian
    baseline at that budget: ``+`` better, ``-`` worse (exact McNemar p < 0.05), nothing for a tie; ``(best)``
    on the baseline itself."""
    budgets = sorted({r["budget"] for r in summary})
    verdict = {(c["suite"], c["budget"], c["method"]): c["verdict"] for c in comparisons}
    best = {(c["suite"], c["budget"]): c["baseline"] for c in comparisons}
    mark = {"better": " +", "worse": " -", "tie": ""}
    out = []
    for suite in dict.fromkeys(r["suite"] for r in summary):
        rows = {(r["method"], r["budget"]): r for r in summary if r["suite"] == suite}
        lines = [f"Success on {suite} (+ / -: better / worse than the best Gaussian baseline, McNemar p < 0.05):", "",
                 "| method | " + " | ".join(f"K = {k}" for k in budgets) + " |",
                 "|---|" + "---|" * len(budgets)]
        for m in dict.fromkeys(r["method"] for r in summary if r["suite"] == suite):
            cells = []
            for k in budgets:
                r = rows.get((m, k))
                if r is None:
                    cells.append("")
                    continue
                tag = " (best)" if best.get((suite, k)) == m else mark.get(verdict.get((suite, k, m), "tie"), "")
                cells.append(fmt_rate(r, "success") + tag)
            lines.append(f"| {m} | " + " | ".join(cells) + " |")
        out.append("\n".join(lines))
    return "\n\n".join(out)


def _fmt(x: float | None, digits: int = 2) -> str:
    return "-" if x is None else f"{x:.{digits}f}"


def _summary_table(rows: Sequence[Mapping]) -> str:
    scored = any("score_mean" in r for r in rows)  # a BARN score column only when the rows carry one
    body = [[r["budget"], r["method"], r["n"], fmt_rate(r, "success"),
             *([fmt_score(r)] if scored else []), fmt_rate(r, "collision"),
             fmt_rate(r, "timeout"), _fmt(r["path_length_mean"]), _fmt(r["time_mean"]),
             f"{_fmt(r['cycle_ms_median'])} / {_fmt(r['cycle_ms_p95'])}"] for r in rows]
    head = ["budget", "method", "n", "success [95% CI]", *(["BARN score [95% CI]"] if scored else []), "collision",
            "timeout", "path length (m)", "time (s)", "cycle ms median / p95"]
    return table(head, body, align="rlrl" + ("l" if scored else "") + "llrrr")


def _comparison_table(rows: Sequence[Mapping]) -> str:
    body = [[r["budget"], r["method"], r["baseline"], r["n"], r["wins"], r["losses"],
             f"{r['diff']:+.2f} [{r['diff_low']:+.2f}, {r['diff_high']:+.2f}]", f"{r['p_value']:.3g}",
             r["verdict"]] for r in rows]
    head = ["budget", "method", "best baseline", "pairs", "wins", "losses", "diff [95% CI]", "McNemar p",
            "verdict"]
    return table(head, body, align="rllrrrlrl")


def markdown(summary_rows: Sequence[Mapping], comparison_rows: Sequence[Mapping]) -> str:
    """Per suite: a summary table (one row per budget and method; success / collision / timeout rates with
    95% Wilson intervals, mean path length and time of successes, cycle ms median / p95), then the paired
    comparisons with their verdicts. Rows need ``suite``, ``method`` and ``budget`` (:func:`eval.navigate.records.stats.summarize`)."""
    for i, r in enumerate(summary_rows):
        require_fields(r, ("suite", "method", "budget", "n", "success_rate"), i)
    suites = list(dict.fromkeys([r["suite"] for r in summary_rows] + [r["suite"] for r in comparison_rows]))
    parts = []
    for suite in suites:
        parts.append(f"## {suite}")
        mine = sorted((r for r in summary_rows if r["suite"] == suite), key=lambda r: r["budget"])
        if mine:
            parts.append(_summary_table(mine))
        comp = sorted((r for r in comparison_rows if r["suite"] == suite), key=lambda r: r["budget"])
        if comp:
            parts.append(f"Paired comparisons with the best baseline per budget (exact McNemar test, "
                         f"Newcombe 95% interval of the success-rate difference):\n\n{_comparison_table(comp)}")
    return "\n\n".join(parts) + "\n"
