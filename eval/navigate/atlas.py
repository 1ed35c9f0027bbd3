"""The equal-compute atlas: per suite (its test split) and cycle budget, the best method against the best of every
other family, with success and the BARN score, from one command.

    python -m eval.navigate atlas --out out/atlas --tasks 10 --budgets 16 64 256 --workers 2
    python -m eval.navigate atlas --out out/atlas --report-only

For each suite of ``--suites`` (default :func:`default_suites`: barn, clutter, moving, sudden, narrow when the
benchmark has it, and ``barn:learned``, the costly-dynamics mode: BARN with ``--dynamics learned``) this runs the
benchmark on the suite's **test split** into ``OUT/<suite>/`` (:func:`eval.navigate.run.run`, in this process:
resumable, a rerun skips the episodes the folder holds; its ``results.md`` and ``budget.md`` written as
``python -m eval.navigate`` writes them), then judges every folder at equal compute
(:func:`eval.navigate.budget.judge_folder`) and writes:

* ``OUT/atlas.md``: one table, suite x cycle budget (default 2, 5, 10, 20 ms): the winner (the best method at its
  most successful K whose p95 cycle time fits, :func:`eval.navigate.budget.rank_key`), its success [95% CI], its
  BARN score [95% CI], and its paired test (wins / losses, Newcombe interval, exact McNemar p) against the best
  method of every *other* family (:data:`eval.navigate.budget.FAMILIES`); then per suite each method's success and
  BARN score at each budget, and the figure;
* ``OUT/atlas-<suite>.png``: success against cycle time per method (:func:`eval.navigate.budget.budget_figure`);
* ``OUT/atlas.json``: the judgements the page is drawn from.

``--report-only`` runs nothing and rebuilds the three files from the folders (every folder of ``--suites`` that
exists under ``OUT``). A method a suite cannot run (``cfu_mppi`` on moving and sudden: its map policy senses a still
world) is left out of that suite and the page says so. Cycle times are wall times of the machine and load of the
run that wrote each folder: compare methods within a suite, not across machines. On a machine so loaded that
commands are preempted, the p95 measures the scheduler and no K fits a few ms; ``--fit median`` then judges by the
median cycle time instead (:data:`eval.navigate.budget.FITS`), and the page says so in its first paragraph.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cuniform_torch.common.fileio import write_bytes, write_json
from eval.common.markdown import table
from eval.common.methods import NAVIGATE, methods_of, parse_methods
from eval.navigate.budget import (
    DEFAULT_BUDGETS_MS,
    FITS,
    PAIR_HEAD,
    family_of,
    judge_folder,
    pair_cells,
    winners,
    write_budget,
)
from eval.navigate.dynamics import DYNAMICS
from eval.navigate.records import fmt_rate, fmt_score
from precompute.cli import (
    MAX_COUNT,
    ArgumentParser,
    CLIError,
    add_no_limit_arg,
    check_output_folder,
    check_work,
    cli_main,
    int_in,
    positive_float,
    positive_int,
)
from precompute.worlds.robot import NAV_ROBOT, RobotPreset
from precompute.worlds.tasks import SUITES

__all__ = ["AtlasSuite", "DEFAULT_RUN_BUDGETS", "default_suites", "parse_suite", "suite_methods", "run_atlas",
           "judge_atlas", "render_atlas", "write_atlas", "make_parser", "main"]

DEFAULT_RUN_BUDGETS = (16, 64, 256)
"""K, trajectories per command, run by default (the budgets in ms then pick among them)"""
LEARNED = ":learned"
"""the suffix of a suite name that runs it in the costly-dynamics mode (``--dynamics learned``)"""


@dataclass(frozen=True)
class AtlasSuite:
    """One column of the atlas: a benchmark suite (test split) with the dynamics its controllers plan with."""

    name: str
    """as typed: a suite of ``python -m eval.navigate`` (``barn``), or one with ``:learned`` (``barn:learned``)"""
    suite: str
    dynamics: str = "true"

    @property
    def folder(self) -> str:
        """Its folder under ``--out`` (``barn``, ``barn-learned``)."""
        return self.name.replace(":", "-")


def default_suites() -> list[str]:
    """The atlas's suites by default: barn, clutter, moving, sudden, narrow (when the benchmark has that suite) and
    ``barn:learned`` (costly dynamics)."""
    return [s for s in ("barn", "clutter", "moving", "sudden", "narrow") if s in SUITES] + ["barn" + LEARNED]


def parse_suite(name: str) -> AtlasSuite:
    """An atlas suite from its name (:class:`AtlasSuite`); an unknown suite names the known ones."""
    suite, learned = (name[: -len(LEARNED)], True) if name.endswith(LEARNED) else (name, False)
    if suite not in SUITES:
        raise ValueError(f"unknown suite {name!r}; choose from {', '.join(SUITES)}, each optionally with "
                         f"{LEARNED} (its costly-dynamics mode)")
    dynamics = "learned" if learned else "true"
    assert dynamics in DYNAMICS  # the benchmark's own list (eval.navigate.dynamics)
    return AtlasSuite(name, suite, dynamics)


def suite_methods(entry: AtlasSuite, methods: Sequence[str] | None) -> tuple[tuple[str, ...] | None, list[str]]:
    """``(the methods entry runs, the ones left out)``: each of ``methods`` that the benchmark accepts on this suite
    (:func:`eval.navigate.run.check_config`, the benchmark's own rule); None: the benchmark's default methods."""
    from eval.navigate.run import NavConfig, check_config

    if methods is None:
        return None, []
    keep, dropped = [], []
    for m in methods:
        try:
            check_config(NavConfig(suite=entry.suite, methods=(m,), dynamics=entry.dynamics))
            keep.append(m)
        except ValueError:
            dropped.append(m)
    return tuple(keep), dropped


def _check_suites(names: Sequence[str]) -> list[AtlasSuite]:
    entries = [parse_suite(n) for n in names]
    if not entries:
        raise ValueError("give at least one suite (--suites)")
    folders = [e.folder for e in entries]
    if len(set(folders)) != len(folders):
        raise ValueError(f"a suite is named twice in --suites {' '.join(names)}")
    return entries


def run_atlas(out: str | Path, suites: Sequence[str] | None = None, tasks: int | None = None,
              budgets: Sequence[int] = DEFAULT_RUN_BUDGETS, methods: Sequence[str] | None = None, workers: int = 1,
              ray_address: str | None = None, robot: RobotPreset = NAV_ROBOT,
              cache: str | Path = Path("out/navigate/cache"), progress: bool = True) -> dict[str, dict]:
    """Run (or resume) each suite's test split into ``out/<folder>`` (:func:`eval.navigate.run.run`, then its
    ``results.*`` and ``budget.*`` files as ``python -m eval.navigate`` writes them); ``{folder: the run's
    result}``. Every suite and method list is checked before the first episode of any suite."""
    from eval.navigate.results import write_outputs
    from eval.navigate.run import NavConfig, check_config, run

    entries = _check_suites(default_suites() if suites is None else suites)
    if methods is not None:
        parse_methods(methods, benchmark=NAVIGATE, closed_loop=True)  # an unknown key: one error, before any run
    cfgs = {}
    for e in entries:
        kept, _ = suite_methods(e, methods)
        if kept == ():
            raise ValueError(f"no method of {', '.join(methods or [])} can run the {e.suite} suite")
        cfgs[e.folder] = NavConfig(suite=e.suite, split="test", tasks=tasks, budgets=tuple(budgets), methods=kept,
                                   workers=workers, horizon=robot.horizon, dynamics=e.dynamics)
        check_config(cfgs[e.folder])
    out, results = Path(out), {}
    for folder, cfg in cfgs.items():
        res = run(cfg, out / folder, robot, Path(cache), ray_address=ray_address, progress=progress)
        write_outputs(res, out / folder)
        write_budget(judge_folder(out / folder, cache=cache), out / folder / "budget.md", out / folder / "budget.png")
        results[folder] = res
    return results


def judge_atlas(out: str | Path, suites: Sequence[str] | None = None,
                budgets_ms: Sequence[float] = DEFAULT_BUDGETS_MS, cache: str | Path | None = None,
                methods: Sequence[str] | None = None, fit: str = "p95") -> dict:
    """The atlas of the folders under ``out``: ``suites`` (one entry per folder, in order: ``name``, ``folder``,
    ``judgement`` (:func:`eval.navigate.budget.judge_folder`), ``winners`` (:func:`eval.navigate.budget.winners`),
    ``run`` (the facts of its ``results.json``, None without one) and ``left_out`` (methods of ``methods`` the suite
    cannot run)), ``budgets_ms``, ``fit`` (:data:`eval.navigate.budget.FITS`: what a K keeps within a budget),
    ``missing`` (suites without a folder). With ``suites`` None: every default suite
    that has a folder; named suites must all have one."""
    out = Path(out)
    named = suites is not None
    entries = _check_suites(default_suites() if suites is None else suites)
    have = [e for e in entries if (out / e.folder / "settings.json").is_file()]
    missing = [e.name for e in entries if e not in have]
    if named and missing:
        raise ValueError(f"no benchmark folder for {', '.join(missing)} under {out} (run the atlas without "
                         "--report-only first)")
    if not have:
        raise ValueError(f"no suite folder under {out} (run python -m eval.navigate atlas --out {out} first)")
    rows = []
    for e in have:
        res = judge_folder(out / e.folder, budgets_ms, cache=cache, fit=fit)
        facts = None
        results_file = out / e.folder / "results.json"
        if results_file.is_file():
            facts = json.loads(results_file.read_text()).get("run")
        rows.append(dict(name=e.name, folder=e.folder, judgement=res, winners=winners(res), run=facts,
                         left_out=suite_methods(e, methods)[1]))
    return dict(suites=rows, budgets_ms=sorted({float(b) for b in budgets_ms}), fit=fit, missing=missing)


# ------------------------------------------------------------------------------------------------ markdown

def _ms(x: float | None) -> str:
    return "-" if x is None else f"{x:.3g}"


def _winner_line(name: str, w: Mapping, fit: str) -> list[Any]:
    b = f"{w['budget_ms']:g} ms"
    cell = w["cell"]
    if cell is None:
        return [name, b, "no method fits", "-", "-", "-", "-", *pair_cells(None)]
    against = w["rival_comparison"]
    return [name, b, f"**{w['method']}** @ {cell['budget']}", w["family"], fmt_rate(cell, "success"),
            fmt_score(cell), _ms(cell[FITS[fit]]), *pair_cells(against, w["rival_note"])]


def _method_table(res: Mapping) -> str:
    """Rows: methods; columns: budgets; a cell: ``success / BARN score @ K`` at the method's K that fits."""
    budgets = res["budgets_ms"]
    methods = list(dict.fromkeys(c["method"] for c in res["cells"]))
    by = {(r["method"], r["budget_ms"]): r for r in res["budgets"]}
    body = []
    for m in methods:
        line = [m, family_of(m)]
        for b in budgets:
            cell = by[(m, b)]["cell"]
            line.append("-" if cell is None else
                        f"{cell['success_rate']:.2f} / {'-' if cell.get('score_mean') is None else format(cell['score_mean'], '.3f')} @ {cell['budget']}")
        body.append(line)
    return table(["method", "family", *[f"{b:g} ms" for b in budgets]], body, align="ll" + "l" * len(budgets))


def _facts(row: Mapping) -> str:
    r = row["run"]
    res = row["judgement"]
    head = f"{res['episodes']} episodes"
    if r:
        head += (f"; its last run: {r.get('ran', r['episodes'])} episodes run in {r['wall_s']:.0f} s wall on "
                 f"{r['cpus']} CPUs with {r['workers']} worker(s), 1-min load {r['load_before']} before and "
                 f"{r['load_after']} after")
    if row["left_out"]:
        head += f"; left out (this suite cannot run them): {', '.join(row['left_out'])}"
    if res.get("score_note"):
        head += f"; BARN score: {res['score_note']}"
    return head


def render_atlas(atlas: Mapping, command: str | None = None) -> str:
    """The markdown of :func:`judge_atlas`'s result (``command``: the line that made it, shown on the page)."""
    fit = atlas.get("fit", "p95")
    loaded = ("" if fit == "p95" else " **Judged by the median cycle time** (`--fit median`), not the p95: for "
              "folders written on a machine so loaded that the p95 measures the scheduler's preemptions, not the "
              "method; a loop sized to a median misses half its deadlines, so this is no real-time claim.")
    parts = ["# Equal-compute atlas",
             "Per suite (its test split) and cycle budget: the winner (the best method at its most successful K "
             f"whose {fit} cycle time fits the budget; a tie in success goes to the higher mean BARN score, then the "
             f"lower {fit}), its success [95% Wilson CI], its BARN score (the Challenge's success x OT / clip(time, "
             "2 OT, 8 OT), mean [95% CI]), and its paired test against the best method of every other family at "
             "that family's own K that fits (paired on (task, seed): wins / losses, the success difference with its "
             "95% Newcombe interval, exact McNemar p; better / worse at p < 0.05). Both sides are picked by success "
             "on the episodes the test then uses, so each pick is a little optimistic. Cycle times are wall times "
             "of the machine and load of the run that wrote each folder (below)." + loaded]
    if command:
        parts.append(f"```\n$ {command}\n```")
    if atlas["missing"]:
        parts.append(f"No folder yet for: {', '.join(atlas['missing'])}.")
    lines = [_winner_line(row["name"], w, fit) for row in atlas["suites"] for w in row["winners"]]
    parts.append(table(["suite", "budget", "winner @ K", "family", "success [95% CI]", "BARN score [95% CI]",
                        f"{fit} ms", *[f"{h} (best other family)" if h == "against" else h for h in PAIR_HEAD]],
                       lines, align="lrllllrlrrlrl"))
    for row in atlas["suites"]:
        res = row["judgement"]
        parts.append(f"## {row['name']}\n\n{_facts(row)}.\n\nEach method at its most successful K that fits each "
                     f"budget: success / mean BARN score @ K (`-`: no K fits).\n\n{_method_table(res)}\n\n"
                     f"![success against cycle time: {row['name']}](atlas-{row['folder']}.png)")
    return "\n\n".join(parts) + "\n"


def write_atlas(atlas: Mapping, out: str | Path, command: str | None = None) -> list[Path]:
    """``atlas.md``, ``atlas.json`` and one ``atlas-<folder>.png`` per suite under ``out``; the paths written."""
    out = Path(out)
    write_bytes(out / "atlas.md", render_atlas(atlas, command).encode())
    write_json(out / "atlas.json", atlas)
    written = [out / "atlas.md", out / "atlas.json"]
    for row in atlas["suites"]:
        written += write_budget(row["judgement"], None, out / f"atlas-{row['folder']}.png")
    return written


# ------------------------------------------------------------------------------------------------ command

def make_parser() -> ArgumentParser:
    """The command's flags (checked as they parse)."""
    p = ArgumentParser(prog="python -m eval.navigate atlas", description=(__doc__ or "").split("\n\n")[0])
    p.add_argument("--out", type=Path, required=True, help="the atlas folder: one benchmark folder per suite in it")
    p.add_argument("--suites", nargs="+", default=None, metavar="SUITE",
                   help=f"suites of {', '.join(SUITES)}, each optionally with {LEARNED} (costly dynamics); "
                        f"default: {' '.join(default_suites())}")
    p.add_argument("--tasks", type=positive_int, default=None,
                   help="test-split tasks per suite (default: the benchmark's count for the suite)")
    p.add_argument("--budgets", nargs="+", type=int_in(2, MAX_COUNT, note=" (CU-MPPI splits it in two)"),
                   default=list(DEFAULT_RUN_BUDGETS), metavar="K",
                   help=f"K, trajectories per command (default: {' '.join(map(str, DEFAULT_RUN_BUDGETS))})")
    p.add_argument("--budgets-ms", nargs="+", type=positive_float, default=list(DEFAULT_BUDGETS_MS), metavar="MS",
                   help="cycle budgets in ms (default: 2 5 10 20)")
    p.add_argument("--fit", choices=list(FITS), default="p95",
                   help="what a K keeps within a budget: its p95 cycle time (default), or its median (only for a "
                        "machine so loaded that the p95 measures the scheduler; the page says so)")
    p.add_argument("--methods", nargs="+", default=None, metavar="KEY",
                   help=f"method keys, of {', '.join(methods_of(NAVIGATE))} (default: the benchmark's defaults)")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--workers", type=int_in(1, 1024), default=1, help="local processes running episodes")
    where.add_argument("--ray", nargs="?", const="local", default=None, metavar="ADDRESS",
                       help="run episodes as Ray tasks: a local Ray runtime, or the cluster at ADDRESS")
    p.add_argument("--cache", type=Path, default=Path("out/navigate/cache"),
                   help="where the robot's tables and the BARN score's reference lengths are kept")
    p.add_argument("--report-only", action="store_true", help="run nothing: rebuild the atlas from the folders")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    add_no_limit_arg(p)
    return p


@cli_main()
def main(argv: Sequence[str] | None = None) -> int:
    p = make_parser()
    args = p.parse_args(argv)
    if args.report_only:
        given = [f for f, v in (("--tasks", args.tasks), ("--ray", args.ray)) if v is not None]
        given += ["--workers"] if args.workers != 1 else []
        given += ["--budgets"] if args.budgets != list(DEFAULT_RUN_BUDGETS) else []
        if given:
            raise CLIError(f"{', '.join(given)} does not apply with --report-only (it runs nothing)")
    suites = _check_suites(default_suites() if args.suites is None else args.suites)  # before any work
    if not args.report_only:  # every suite together: a product of counts too large is refused before any work
        counts = {"--tasks": args.tasks, "budgets": len(args.budgets),
                  "methods": len(args.methods) if args.methods else None, "suites": len(suites)}
        check_work({k: v for k, v in counts.items() if v is not None}, "episodes", args.no_limit)
    check_output_folder(args.out, "--out")
    argv_line = " ".join(sys.argv[1:] if argv is None else argv)
    if not args.report_only:
        run_atlas(args.out, args.suites, args.tasks, args.budgets, args.methods, args.workers, args.ray,
                  cache=args.cache, progress=not args.quiet)
    atlas = judge_atlas(args.out, args.suites, args.budgets_ms, args.cache, args.methods, args.fit)
    text = render_atlas(atlas, f"python -m eval.navigate atlas {argv_line}")
    print(text, end="")
    for path in write_atlas(atlas, args.out, f"python -m eval.navigate atlas {argv_line}"):
        print(f"wrote {path}")
    return 0
