"""Build a C-Uniform table:  python -m precompute.build --system dubins --out out/dubins.npz

Every parameter of the chosen system is a flag (``--horizon 15``, ``--num-actions 21``,
``--cell-size 0.1 0.1 0.1571``, ...). Prints a progress bar per level, per-stage times and the uniformity
report; writes the table (atomically) and ``<out stem>.report.json`` beside it. Each finished level is
checkpointed in ``<out>.partial/``; after an interrupt, ``--resume`` continues from there and writes a
byte-identical table.
"""

from __future__ import annotations

import argparse
import dataclasses
import shutil
import sys
import time
from pathlib import Path
from typing import Any, Sequence

from cuniform_torch.fileio import write_json
from cuniform_torch.systems import _REGISTRY, known_systems, make_system
from cuniform_torch.table import write_table

from .builder import BuildConfig, build_table
from .levels import PointMode
from .report import format_report, uniformity_report


def _system_fields() -> dict[str, dataclasses.Field]:
    """Constructor fields of every registered dataclass system (the union becomes CLI flags)."""
    out: dict[str, dataclasses.Field] = {}
    for factory in _REGISTRY.values():
        if dataclasses.is_dataclass(factory):
            for f in dataclasses.fields(factory):
                out.setdefault(f.name, f)
    return out


def _defaults_of(field: str) -> str:
    """``"dubins: 0.2; random_walk_1d: 1.0"``: the field's default in each system that has it."""
    parts = []
    for name, factory in sorted(_REGISTRY.items()):
        if dataclasses.is_dataclass(factory):
            for f in dataclasses.fields(factory):
                if f.name == field:
                    default = f.default if f.default is not dataclasses.MISSING else "required"
                    if isinstance(default, tuple):
                        default = " ".join(f"{v:.6g}" for v in default)
                    elif isinstance(default, float):
                        default = f"{default:.6g}"
                    parts.append(f"{name}: {default}")
    return "; ".join(parts)


def make_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m precompute.build",
        description="Build a C-Uniform action-probability table (level sets + exact max-flow) and report its uniformity.",
    )
    parser.add_argument("--system", default="dubins", help=f"system name (known: {', '.join(known_systems())})")
    parser.add_argument("--out", type=Path, default=None, help="table file to write (default: out/<system>.npz)")
    parser.add_argument("--horizon", type=int, default=None, help="number of steps T (default: 10)")
    parser.add_argument("--points", default=PointMode.CENTERS.value, choices=[m.value for m in PointMode],
                        help="sample points per cell: centers (level sets from cell centres, transitions from the 3^d "
                             "lattice), lattice (level sets from all lattice points), random (centre + K random points)")
    parser.add_argument("--points-per-cell", type=int, default=8, help="K random points per cell for --points random")
    parser.add_argument("--seed", type=int, default=0, help="seed of --points random and of the report's rollouts")
    parser.add_argument("--method", default="maxflow", choices=["maxflow", "coverage"],
                        help="maxflow: the paper's flow network (default); coverage: maximize the expected coverage "
                             "of real rollouts over the reachable states (see precompute/coverage_method.py)")
    parser.add_argument("--target-samples", type=int, default=2000,
                        help="coverage method: N whose expected coverage is maximized")
    parser.add_argument("--merge-resolution", type=int, default=32,
                        help="coverage method: sub-cell bins per cell and dimension for merging reachable states")
    parser.add_argument("--steps", type=int, default=300, help="coverage method: gradient-ascent iterations")
    parser.add_argument("--lr", type=float, default=0.2, help="coverage method: Adam learning rate")
    parser.add_argument("--resume", action="store_true", help="continue an interrupted build from its checkpoints (maxflow)")
    parser.add_argument("--rollouts", type=int, default=None, help="rollouts for the report (default: 10 x largest level)")
    parser.add_argument("--no-report", action="store_true", help="skip the uniformity report")
    parser.add_argument("--device", default="cpu", help="device for the report's rollouts (cpu, cuda)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    group = parser.add_argument_group("system parameters (each applies to the systems that have it)")
    for name, f in _system_fields().items():
        flag = "--" + name.replace("_", "-")
        default = f.default if f.default is not dataclasses.MISSING else None
        kwargs: dict[str, Any] = {"default": None, "dest": f"sys_{name}", "metavar": name.upper()}
        if isinstance(default, tuple):
            kwargs.update(nargs="+", type=float, metavar="X")
        elif isinstance(default, bool):
            kwargs.update(type=lambda s: s.lower() in ("1", "true", "yes"))
        elif isinstance(default, int):
            kwargs.update(type=int)
        else:
            kwargs.update(type=float)
        group.add_argument(flag, help=f"default {_defaults_of(name)}".replace("%", "%%"), **kwargs)
    return parser


def _check_output_path(out: Path) -> None:
    if out.is_dir():
        raise ValueError(f"--out {out} is a folder; give a file path such as {out / 'table.npz'}")
    for parent in out.parents:
        if parent.exists():
            if not parent.is_dir():
                raise ValueError(f"--out {out}: {parent} is a file, not a folder")
            break


def _check_device(device: str) -> None:
    import torch

    try:
        dev = torch.device(device)
    except RuntimeError:
        raise ValueError(f"--device {device!r} is not a torch device (cpu, cuda, cuda:1, ...)") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"--device {device}: CUDA is not available on this machine")


def _build_coverage(system, horizon: int, args: argparse.Namespace, bar):
    """The coverage method (precompute/coverage_method.py), with the bar counting levels, then iterations."""
    from .builder import BuildStats
    from .coverage_method import CoverageConfig, build_coverage_table

    config = CoverageConfig(horizon=horizon, target_samples=args.target_samples,
                            merge_resolution=args.merge_resolution, steps=args.steps, lr=args.lr)
    if bar is not None:
        bar.reset(total=horizon + config.steps)
        bar.set_description("levels, then ascent")

    def progress(stage: str, i: int, value: float) -> None:
        if bar is not None:
            bar.set_postfix({"states" if stage == "enumerate" else "objective": f"{value:.0f}"})
            bar.update(1)

    table, facts = build_coverage_table(system, config, progress)
    stats = BuildStats(seconds={**facts["seconds"], "write": 0.0})
    return table, stats, {"coverage_method": {k: v for k, v in facts.items() if k != "seconds"}}


def main(argv: Sequence[str] | None = None) -> int:
    parser = make_parser()
    args = parser.parse_args(argv)
    try:
        return _run(args)
    except KeyboardInterrupt:
        print("\ninterrupted: no table written; rerun with --resume to continue from the last finished level",
              file=sys.stderr)
        return 130
    except ValueError as exc:  # bad input: unknown system, bad sizes, corrupt table, ...
        print(f"error: {exc}", file=sys.stderr)
        return 2


def _run(args: argparse.Namespace) -> int:
    params = {k[4:]: v for k, v in vars(args).items() if k.startswith("sys_") and v is not None}
    for key in ("cell_size", "cell_offset"):
        if key in params:
            params[key] = tuple(params[key])
    system = make_system(args.system, **params)
    horizon = 10 if args.horizon is None else args.horizon
    config = BuildConfig(horizon=horizon, points=args.points, points_per_cell=args.points_per_cell, seed=args.seed)
    out: Path = args.out or Path("out") / f"{args.system}.npz"
    _check_output_path(out)
    if args.rollouts is not None and args.rollouts < 1:
        raise ValueError(f"--rollouts must be positive, got {args.rollouts}")
    _check_device(args.device)
    ckpt = out.with_name(out.name + ".partial")
    if ckpt.exists() and not args.resume:
        shutil.rmtree(ckpt)
    ckpt.mkdir(parents=True, exist_ok=True)
    say = (lambda *a: None) if args.quiet else (lambda *a: print(*a, flush=True))
    detail = f"points={config.points.value}" if args.method == "maxflow" else f"target N={args.target_samples}"
    say(f"building {system.name} table ({args.method}): {system.params()} horizon={horizon} {detail}")

    bar = None
    if not args.quiet:
        from tqdm import tqdm

        bar = tqdm(total=horizon, desc="levels", unit="level", file=sys.stdout)

    def progress(t: int, step) -> None:
        if bar is not None:
            bar.set_postfix(cells=len(step.next_cells), flow=f"{step.flow_value / (len(step.probs) * len(step.next_cells)):.4f}")
            bar.update(1)

    t_start = time.perf_counter()
    extra: dict[str, Any] = {}
    try:
        if args.method == "coverage":
            table, stats, extra = _build_coverage(system, horizon, args, bar)
        else:
            table, stats = build_table(system, config, checkpoint_dir=ckpt, resume=args.resume, progress=progress)
    finally:
        if bar is not None:
            bar.close()
    t0 = time.perf_counter()
    write_table(out, table)
    stats.seconds["write"] = time.perf_counter() - t0
    shutil.rmtree(ckpt, ignore_errors=True)
    total = time.perf_counter() - t_start
    if stats.resumed_steps:
        say(f"resumed {stats.resumed_steps} of {horizon} levels from checkpoints")
    graph = f"{len(table.arcs)} arcs" if table.arcs is not None else f"{len(table.transitions)} transitions"
    say(f"level sizes: {table.level_sizes}  ({len(table.cells)} cells, {graph})")
    say("stage times: " + ", ".join(f"{k} {v:.2f}s" for k, v in stats.seconds.items()) + f"; total {total:.2f}s")
    say(f"wrote {out}")

    report_path = out.with_name(out.name[: -len(out.suffix)] + ".report.json" if out.suffix else out.name + ".report.json")
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
        **extra,
    }
    if not args.no_report:
        t0 = time.perf_counter()
        report = uniformity_report(table, num_rollouts=args.rollouts, seed=args.seed, device=args.device)
        summary["report_seconds"] = time.perf_counter() - t0
        summary["uniformity"] = report.to_dict()
        say(format_report(report))
        say(f"report: {report.num_rollouts} rollouts in {summary['report_seconds']:.2f}s")
    write_json(report_path, summary)
    say(f"wrote {report_path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
