"""One table from the flags of ``python -m precompute.build`` (no ``--starts``): the build, its report, its files.

:func:`main_one` is the whole command for one table; :mod:`precompute.build` (the CLI, which also builds table
sets) and :mod:`precompute.table_set` (one call per member start) both run it, so neither imports the other.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from cuniform_torch.cli import OUT, CLIError, check_output_file, cli_main, dataclass_from_args
from cuniform_torch.common.fileio import exclusive_lock, write_json
from cuniform_torch.systems import resolve_system, system_horizon
from cuniform_torch.tables.file import write_table
from precompute.build_args import check_flags, make_parser
from precompute.flow.builder import BuildConfig, SizeGuide, available_memory_bytes, build_table, check_resume
from precompute.levels.safe_map import map_overrides
from precompute.report import format_report, uniformity_report
from precompute.system_args import load_user_systems, make_cli_system, parse_params

__all__ = ["main_one", "run_one", "parse_build_args", "with_threads", "system_of"]


def _check_device(device: str) -> None:
    import torch

    try:
        dev = torch.device(device)
    except RuntimeError:
        raise ValueError(f"--device {device!r} is not a torch device (cpu, cuda, cuda:1, ...)") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"--device {device}: CUDA is not available on this machine")


def _build_coverage(system, config, bar):
    """The coverage method (precompute/coverage/method.py), with the bar counting levels, then iterations."""
    from precompute.coverage.method import build_coverage_table
    from precompute.flow.builder import BuildStats

    if bar is not None:
        bar.reset(total=config.horizon + config.steps)
        bar.set_description("levels, then ascent")

    def progress(stage: str, i: int, value: float) -> None:
        if bar is not None:
            bar.set_postfix({"states" if stage == "enumerate" else "objective": f"{value:.0f}"})
            bar.update(1)

    table, facts = build_coverage_table(system, config, progress)
    if bar is not None and bar.n < bar.total:  # the ascent stopped early (--tol): the bar ends full, not short
        bar.total = bar.n
        bar.refresh()
    stats = BuildStats(seconds={**facts["seconds"], "write": 0.0})
    return table, stats, {"coverage_method": {k: v for k, v in facts.items() if k != "seconds"}}


def parse_build_args(argv: Sequence[str]) -> argparse.Namespace:
    """The flags ``argv`` of a build, user system modules imported first and combinations checked."""
    load_user_systems(argv)
    args = make_parser().parse_args(argv)
    check_flags(args)
    if args.threads < 0:
        raise CLIError(f"--threads must be >= 0 (0: torch's choice), got {args.threads}")
    return args


def with_threads(args: argparse.Namespace, run: Callable[[], int]) -> int:
    """``run()`` with ``--threads`` torch threads, the caller's setting restored after (eval.report keeps its own)."""
    import torch

    previous = torch.get_num_threads()
    if args.threads:
        torch.set_num_threads(args.threads)
    try:
        return run()
    finally:
        torch.set_num_threads(previous)


@cli_main(interrupted="interrupted: no table written")
def main_one(argv: Sequence[str] | None = None) -> int:
    """Build one table from the flags ``argv``: 0, or 2 after one ``error: ...`` line, or 130 on Ctrl-C."""
    argv = sys.argv[1:] if argv is None else list(argv)
    args = parse_build_args(argv)
    if args.starts is not None:
        raise ValueError("--starts builds a table set: run python -m precompute.build")
    return with_threads(args, lambda: run_one(args))


def run_one(args: argparse.Namespace) -> int:
    """Build the one table that the parsed flags ``args`` describe."""
    name, system = system_of(args)
    if args.workers != 1 or args.ray is not None:
        raise ValueError("--workers and --ray build a table set: give --starts too")
    horizon = system_horizon(system) if args.horizon is None else args.horizon
    map_fields = map_overrides(args, system)
    config = dataclass_from_args(BuildConfig, args, horizon=horizon, **map_fields)
    out: Path = args.out or OUT / f"{name}.npz"
    if args.max_memory is not None and not args.max_memory > 0:
        raise ValueError(f"--max-memory must be a positive number of GB, got {args.max_memory}")
    check_output_file(out, "--out", example="table.npz")
    if args.rollouts is not None and args.rollouts < 1:
        raise ValueError(f"--rollouts must be positive, got {args.rollouts}")
    _check_device(args.device)
    with exclusive_lock(out.with_name(out.name + ".lock"), what=f"--out {out}"):
        return _build(args, system, horizon, config, out)



def system_of(args: argparse.Namespace):
    """The registry name and the system the flags describe."""
    params = {k[4:]: v for k, v in vars(args).items() if k.startswith("sys_") and v is not None}
    for key, value in params.items():
        if isinstance(value, list):
            params[key] = tuple(value)
    extra_params = parse_params(args.param)
    both = sorted(set(params) & set(extra_params))
    if both:
        raise ValueError(f"parameter(s) {', '.join(both)} given both as a flag and as --param")
    params.update({k: tuple(v) if isinstance(v, list) else v for k, v in extra_params.items()})
    name = resolve_system(args.system)
    return name, make_cli_system(args.system, name, params)


def _build(args: argparse.Namespace, system, horizon: int, config: BuildConfig, out: Path) -> int:
    """Build, write and report, holding the lock of ``out``."""
    ckpt = out.with_name(out.name + ".partial")
    if ckpt.exists() and not args.resume:
        shutil.rmtree(ckpt)
    if args.method == "maxflow":
        if args.resume and ckpt.is_dir():
            check_resume(ckpt, system, config)
        ckpt.mkdir(parents=True, exist_ok=True)
    say = (lambda *a: None) if args.quiet else (lambda *a: print(*a, flush=True))
    coverage_config = None
    if args.method == "coverage":
        from precompute.coverage.method import CoverageConfig

        coverage_config = dataclass_from_args(CoverageConfig, args, horizon=horizon, local_map=config.local_map,
                                              radius=config.radius)
    detail = (f"points={config.points.value}" if coverage_config is None
              else f"target N={coverage_config.target_samples}")
    say(f"building {system.name} table ({args.method}): {system.params()} horizon={horizon} {detail}")

    bar = None
    if not args.quiet:
        from tqdm import tqdm

        bar = tqdm(total=horizon, desc="levels", unit="level", file=sys.stdout)

    budget = args.max_memory * 1e9 if args.max_memory is not None else available_memory_bytes()
    guide = SizeGuide(horizon, system.action_set().shape[0], len(system.periodic), budget, report=not args.no_report)

    def progress(t: int, step) -> None:
        for line in guide.update(step):
            loud = line.startswith(("warning", "the projection now fits"))
            stream = sys.stderr if loud else sys.stdout
            if loud or not args.quiet:
                (bar.write(line, file=stream) if bar is not None else print(line, file=stream, flush=True))
        if bar is not None:
            bar.set_postfix(cells=len(step.next_cells), flow=f"{step.flow_value / (len(step.probs) * len(step.next_cells)):.4f}")
            bar.update(1)

    t_start = time.perf_counter()
    extra: dict[str, Any] = {}
    try:
        if args.method == "coverage":
            table, stats, extra = _build_coverage(system, coverage_config, bar)
        else:
            table, stats = build_table(system, config, checkpoint_dir=ckpt, resume=args.resume, progress=progress)
    except KeyboardInterrupt:
        if args.method == "coverage":
            raise
        raise KeyboardInterrupt("interrupted: no table written; rerun with --resume to continue from the last "
                                "finished level") from None
    finally:
        if bar is not None:
            bar.close()
    t0 = time.perf_counter()
    try:
        write_table(out, table)
    except OSError as exc:
        kept = f"; the finished levels stay in {ckpt} (rerun with --resume)" if args.method == "maxflow" else ""
        raise CLIError(f"cannot write the table {out}: {exc.strerror or exc}{kept}") from None
    stats.seconds["write"] = time.perf_counter() - t0
    shutil.rmtree(ckpt, ignore_errors=True)
    total = time.perf_counter() - t_start
    if stats.resumed_steps:
        say(f"resumed {stats.resumed_steps} of {horizon} levels from checkpoints")
    graph = f"{len(table.arcs)} arcs" if table.arcs is not None else f"{len(table.transitions)} transitions"
    say(f"level sizes: {table.level_sizes}  ({len(table.cells)} cells, {graph})")
    say("stage times: " + ", ".join(f"{k} {v:.2f}s" for k, v in stats.seconds.items()) + f"; total {total:.2f}s")
    say(f"wrote {out}")

    report_path = out.with_name(out.stem + ".report.json")
    summary: dict[str, Any] = {
        "table": str(out),
        "system": system.name,
        "params": system.params(),
        "horizon": horizon,
        "points": config.points.value,
        "level_sizes": table.level_sizes,
        "flow_ratio": (table.flow_value / table.flow_target).tolist() if args.method == "maxflow" else None,
        "seconds": {**stats.seconds, "total": total},
        "method": args.method,
        "zero_outflow_cells": stats.zero_outflow,
        "kept_point_fraction": stats.kept_fraction,
        "size_guide": {"projected_level_sizes": guide.projection, "estimated_peak_bytes": guide.estimate_bytes,
                       "budget_bytes": budget, "warned": guide.warned},
        **extra,
    }
    if not args.no_report:
        t0 = time.perf_counter()
        report = uniformity_report(table, num_rollouts=args.rollouts, seed=config.seed, device=args.device)
        summary["report_seconds"] = time.perf_counter() - t0
        summary["uniformity"] = report.to_dict()
        say(format_report(report))
        say(f"report: {report.num_rollouts} rollouts in {summary['report_seconds']:.2f}s")
    write_json(report_path, summary)
    say(f"wrote {report_path}")
    return 0

