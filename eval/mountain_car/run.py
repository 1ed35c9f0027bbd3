"""Closed-loop MountainCarContinuous-v0 (gymnasium, the ground truth): MPPI, pytorch_mppi, C-Uniform MPPI and
CU-MPPI at the same sample budget and horizon, the C-Uniform ones on a start-aware table set.

    python -m eval.mountain_car                                # 20 seeds, K = 256, all four controllers
    python -m eval.mountain_car --budget 64 --methods mppi,cuniform --workers 2

Every controller plans with the model ``mountain_car`` (``repeat`` env steps per model step, the force held)
and the one cost of :mod:`eval.mountain_car.episode`; the env's reset seed is the controller's seed. The table
set (:mod:`eval.mountain_car.table_set`) is built on first use into ``--cache``. Per controller: success rate (the
env terminated at the goal within ``--max-steps`` env steps) with a 95% Wilson interval, mean +- std return
(gymnasium's reward), median env steps to the goal (successes), the median over episodes of each episode's
median command time, and for the table-set controllers the miss rate of their lookups. Writes
``OUT/results.json`` (atomic, after every episode; a rerun with the same configuration resumes).
"""

from __future__ import annotations

import json
import statistics
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from cuniform_torch.common.fileio import MAX_JSON_BYTES, read_capped_text, write_json
from eval.common.stats import wilson_interval
from eval.mountain_car.episode import (
    GYM_MISSING,
    LAMBDA,
    METHODS,
    NOISE_STD,
    SET_METHODS,
    episode_job,
    have_gymnasium,
    have_pytorch_mppi,
)
from eval.mountain_car.table_set import ensure_set, parse_grid
from precompute.cli import (
    MAX_COUNT,
    OUT,
    ArgumentParser,
    CLIError,
    add_no_limit_arg,
    check_output_folder,
    check_work,
    cli_main,
    horizon_arg,
    int_in,
    positive_int,
    refuse_flags,
)
from precompute.parallel import run_jobs

__all__ = ["main", "make_parser", "summarize"]


def make_parser() -> ArgumentParser:
    p = ArgumentParser(prog="python -m eval.mountain_car", description=(__doc__ or "").split("\n\n")[0])
    p.add_argument("--seeds", type=positive_int, default=20, help="episodes per controller, seeds 0..N-1 (default 20)")
    p.add_argument("--budget", type=int_in(2, MAX_COUNT), default=256,
                   help="samples K per command, every controller (default 256)")
    p.add_argument("--methods", default=",".join(METHODS), help=f"comma-separated, from {', '.join(METHODS)}")
    p.add_argument("--horizon", type=horizon_arg, default=30, help="model steps T per plan (default 30)")
    p.add_argument("--repeat", type=int_in(1, 1000), default=5, help="env steps per model step (default 5)")
    p.add_argument("--max-steps", type=positive_int, default=999,
                   help="env steps per episode (default 999, the env's limit)")
    p.add_argument("--set-grid", default="13x9",
                   help="table-set starts: P positions x V velocities (default 13x9; methods "
                        f"{', '.join(SET_METHODS)})")
    p.add_argument("--workers", type=int_in(1, 1024), default=1,
                   help="processes for the episodes and the set build (default 1)")
    p.add_argument("--out", default=str(OUT / "mountain_car"), help="folder of results.json")
    p.add_argument("--cache", default=None,
                   help="folder of cached table sets (default out/mountain_car/sets; methods "
                        f"{', '.join(SET_METHODS)})")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    add_no_limit_arg(p)
    return p


def _check(args: Any, parser: ArgumentParser | None = None) -> list[str]:
    """The methods to run; a CLIError naming the first bad flag (the counts are checked as they parse)."""
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    unknown = [m for m in methods if m not in METHODS]
    if unknown or not methods:
        raise CLIError(f"--methods: unknown method(s) {', '.join(unknown) or '(none given)'}; choose from "
                       f"{', '.join(METHODS)}")
    if len(set(methods)) != len(methods):
        raise CLIError(f"--methods names a method twice: {args.methods}")
    if parser is not None and not any(m in SET_METHODS for m in methods):
        refuse_flags(parser, args, ["set_grid", "cache"], f"without a table-set method ({', '.join(SET_METHODS)}) "
                                                          "in --methods")
    parse_grid(args.set_grid)
    check_work({"seeds": args.seeds, "methods": len(methods)}, "episodes", getattr(args, "no_limit", False))
    if not have_gymnasium():
        raise CLIError(GYM_MISSING)
    if "pytorch_mppi" in methods and not have_pytorch_mppi():
        print("pytorch_mppi is not installed (pip install pytorch-mppi, the [bench] extra): skipped", flush=True)
        methods.remove("pytorch_mppi")
        if not methods:
            raise CLIError("--methods: nothing left to run without pytorch_mppi")
    return methods


def summarize(records: Sequence[dict], methods: Sequence[str]) -> list[dict]:
    """One row per method (in ``methods`` order) from episode records (:func:`eval.mountain_car.episode.run_episode`)."""
    rows = []
    for method in methods:
        recs = [r for r in records if r["method"] == method]
        if not recs:
            continue
        wins = [r for r in recs if r["success"]]
        lo, hi = wilson_interval(len(wins), len(recs))
        returns = [r["return"] for r in recs]
        row: dict[str, Any] = {
            "method": method, "episodes": len(recs), "successes": len(wins), "success_rate": len(wins) / len(recs),
            "success_ci95": [lo, hi], "return_mean": statistics.mean(returns),
            "return_std": statistics.stdev(returns) if len(returns) > 1 else 0.0,
            "steps_to_goal_median": statistics.median(r["steps"] for r in wins) if wins else None,
            "command_ms_median": statistics.median(r["command_ms_median"] for r in recs),
            "miss_rate": None}
        if method in SET_METHODS:
            queries = sum(r["queries"] for r in recs)
            row["miss_rate"] = sum(r["misses"] for r in recs) / queries if queries else 0.0
        rows.append(row)
    return rows


def format_rows(rows: Sequence[dict]) -> str:
    """The printed table."""
    lines = [f"{'method':<13} {'success':>7} {'95% CI':>13} {'return':>15} {'steps':>6} {'ms/cmd':>7} {'miss':>7}"]
    for r in rows:
        lo, hi = r["success_ci95"]
        steps = "-" if r["steps_to_goal_median"] is None else f"{r['steps_to_goal_median']:.0f}"
        miss = "-" if r["miss_rate"] is None else f"{100 * r['miss_rate']:.2f}%"
        lines.append(f"{r['method']:<13} {r['successes']:>3}/{r['episodes']:<3} [{lo:.2f}, {hi:.2f}] "
                     f"{r['return_mean']:>7.1f} +- {r['return_std']:<5.1f} {steps:>6} {r['command_ms_median']:>7.2f} "
                     f"{miss:>7}")
    return "\n".join(lines)


def _resumed(path: Path, config: dict[str, Any]) -> list[dict]:
    """The records of an earlier run with the same configuration (none when it differs or is absent)."""
    try:
        old = json.loads(read_capped_text(path, MAX_JSON_BYTES, "a result file"))
    except (OSError, ValueError):
        return []
    if not isinstance(old, dict) or old.get("config") != config or not isinstance(old.get("records"), list):
        return []
    return old["records"]


@cli_main(interrupted="interrupted: the finished episodes are in results.json; rerun the same command to resume")
def main(argv: Sequence[str] | None = None) -> int:
    """Run the experiment from the flags ``argv``: 0, or 2 after one ``error: ...`` line."""
    parser = make_parser()
    args = parser.parse_args(sys.argv[1:] if argv is None else list(argv))
    methods = _check(args, parser)
    out = Path(args.out)
    check_output_folder(out, "--out")
    out.mkdir(parents=True, exist_ok=True)
    cache = Path(args.cache) if args.cache else OUT / "mountain_car" / "sets"
    config: dict[str, Any] = {"env": "MountainCarContinuous-v0", "budget": args.budget, "horizon": args.horizon,
                              "repeat": args.repeat, "max_steps": args.max_steps, "seeds": args.seeds,
                              "noise_std": NOISE_STD, "lambda": LAMBDA, "set_grid": args.set_grid}
    if any(m in SET_METHODS for m in methods):
        folder = ensure_set(cache, args.repeat, args.horizon, parse_grid(args.set_grid), args.workers, args.quiet)
        config["set_dir"] = str(folder)
    path = out / "results.json"
    records = [r for r in _resumed(path, config) if r.get("method") in methods]
    done = {(r["method"], r["seed"]) for r in records}
    jobs = [(m, s, {**config, "threads": 1 if args.workers > 1 else 0})
            for s in range(args.seeds) for m in methods if (m, s) not in done]
    if done:
        print(f"resuming: {len(done)} episode(s) already in {path}, {len(jobs)} to run", flush=True)

    def save() -> None:
        rows = summarize(records, methods)
        write_json(path, {"config": config, "methods": methods, "summary": rows,
                          "records": sorted(records, key=lambda r: (r["method"], r["seed"]))})

    from tqdm import tqdm

    with tqdm(total=len(jobs), desc="episodes", unit="ep", disable=args.quiet) as bar:
        def on_done(_i: int, record: dict) -> None:
            records.append(record)
            save()
            bar.update(1)

        run_jobs(episode_job, jobs, workers=args.workers, on_done=on_done)
    save()
    print(f"MountainCarContinuous-v0, {args.seeds} seeds, K = {args.budget}, horizon {args.horizon} x {args.repeat} "
          f"env steps, max {args.max_steps} env steps")
    print(format_rows(summarize(records, methods)))
    print(f"wrote {path}")
    return 0
