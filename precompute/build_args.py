"""The flags of ``python -m precompute.build`` (:mod:`precompute.build`) and the checks of their combination:
the parser (the table's settings are fields of :class:`~precompute.flow.builder.BuildConfig` and
:class:`~precompute.coverage.method.CoverageConfig`, every parameter of a registered dataclass system a flag)
and :func:`check_flags`, which refuses a flag the chosen method or points mode would ignore.
"""

from __future__ import annotations

import argparse
import dataclasses
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from cuniform_torch.cli import (
    OUT,
    ArgumentParser,
    CLIError,
    add_dataclass_args,
    dataclass_from_args,
    device_arg,
    field_docs,
    flag_name,
    horizon_arg,
    int_in,
    non_negative_int,
    positive_int,
    threads_arg,
)
from cuniform_torch.systems import _REGISTRY, DEFAULT_HORIZON, System, known_systems, resolve_system, system_horizon
from precompute.flow.builder import BuildConfig
from precompute.levels.safe_map import map_overrides
from precompute.levels.sets import PointMode
from precompute.one_table import TableJob
from precompute.system_args import load_user_systems, make_cli_system, parse_params

__all__ = ["make_parser", "check_flags", "parse_build_args", "system_of", "table_job", "MAXFLOW_ONLY",
           "COVERAGE_ONLY"]


def _system_fields() -> dict[str, dataclasses.Field]:
    """Constructor fields of every registered dataclass system (the union becomes CLI flags)."""
    out: dict[str, dataclasses.Field] = {}
    for factory in _REGISTRY.values():
        if dataclasses.is_dataclass(factory):
            for f in dataclasses.fields(factory):
                if f.init:
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


MAXFLOW_ONLY = ("points", "points_per_cell", "resume", "max_memory", "ties")
"""flags of --method maxflow only (given with --method coverage they are refused)"""
COVERAGE_ONLY = ("target_samples", "merge_resolution", "steps", "lr", "state_budget", "tol")
"""flags of --method coverage only: fields of :class:`~precompute.coverage.method.CoverageConfig`"""


def make_parser() -> argparse.ArgumentParser:
    """The build's flags; the settings of the table (``--points``, ``--steps``, ...) are fields of
    :class:`BuildConfig` and :class:`CoverageConfig`, whose defaults they show (the only copy of each)."""
    from precompute.coverage.method import CoverageConfig

    parser = ArgumentParser(
        prog="python -m precompute.build",
        description="Build a C-Uniform action-probability table (level sets + exact max-flow) and report its uniformity.",
    )
    parser.add_argument("--system", default="dubins",
                        help=f"system name (known: {', '.join(known_systems())}) or module:factory of a user system")
    parser.add_argument("--system-module", action="append", default=[], metavar="MODULE",
                        help="import MODULE first (repeatable); it registers user systems with register_system")
    parser.add_argument("--param", action="append", default=[], metavar="KEY=VALUE",
                        help="a system parameter as JSON (repeatable), e.g. --param speed=0.5 --param 'cell_size=[0.1, 0.1, 0.2]'")
    parser.add_argument("--max-memory", type=float, default=None, metavar="GB",
                        help="memory budget of the size guidance (default: the available memory)")
    parser.add_argument("--out", type=Path, default=None, help=f"table file to write (default: {OUT}/<system>.npz)")
    parser.add_argument("--horizon", type=horizon_arg, default=None,
                        help=f"number of steps T (default: the system's default_horizon, else {DEFAULT_HORIZON})")
    add_dataclass_args(parser, BuildConfig, only=("points", "points_per_cell", "seed", "ties", "start"),
                       arg_types={"seed": non_negative_int, "points_per_cell": positive_int}, help={
        "start": "the state to build from, one number per state dimension (default: the zero state); an "
                 "SE(2)-invariant system's x, y, theta must be 0 (its table serves every pose), e.g. --system ks_speed "
                 "--start 0 0 0 0.5",
        "points": "sample points per cell: centers (level sets from cell centres, transitions from the 3^d "
                  "lattice), lattice (level sets from all lattice points), random (centre + K random points)",
        "points_per_cell": "K random points per cell for --points random",
        "seed": "seed of --points random and of the report's rollouts",
        "ties": "symmetric: a step onto a cell boundary rounds away from its source cell (mirror-symmetric level "
                "sets, the authors' sizes); grid: the state's own cell (the grid offset decides)",
    })
    parser.add_argument("--map", dest="map_file", type=Path, default=None, metavar="FILE",
                        help="a local map in the start frame (precompute/levels/safe_map.py): safe level sets, without the "
                             "cells within --radius of its obstacles (SE(2)-invariant systems)")
    parser.add_argument("--radius", dest="map_radius", type=float, default=None, metavar="R",
                        help="with --map: the robot's radius (m) its obstacles are inflated by (default 0)")
    parser.add_argument("--threads", type=threads_arg, default=1,
                        help="torch CPU threads (0: torch's choice, one per core). 1 by default: the build's tensors "
                             "are small, and on a busy machine extra threads only wait for each other")
    parser.add_argument("--method", default="maxflow", choices=["maxflow", "coverage"],
                        help="maxflow: the paper's flow network (default); coverage: maximize the expected coverage "
                             "of real rollouts over the reachable states (see precompute/coverage/method.py)")
    docs = field_docs(CoverageConfig)
    add_dataclass_args(parser, CoverageConfig, only=COVERAGE_ONLY,
                       help={name: f"coverage method: {docs[name]}" for name in COVERAGE_ONLY})
    parser.add_argument("--starts", default=None, metavar="SPEC",
                        help="build a table set, one table per start, into the folder --out: a grid 'DIM=LO:HI:N ...' "
                             "or a seeded sample 'random:N DIM=LO:HI ...' over the non-pose dimensions "
                             "(precompute/table_set.py)")
    parser.add_argument("--no-limit", action="store_true",
                        help="with --starts: allow a set of more than 10,000 tables (MAX_SET_MEMBERS)")
    parser.add_argument("--workers", type=int_in(1, 1024), default=1, help="with --starts: tables built in parallel processes")
    parser.add_argument("--ray", nargs="?", const="local", default=None, metavar="ADDRESS",
                        help="with --starts: tables as Ray tasks (a local runtime, or the cluster at ADDRESS)")
    parser.add_argument("--resume", action="store_true", help="continue an interrupted build from its checkpoints (maxflow)")
    parser.add_argument("--rollouts", type=positive_int, default=None, help="rollouts for the report (default: 10 x largest level)")
    parser.add_argument("--no-report", action="store_true", help="skip the uniformity report")
    parser.add_argument("--device", type=device_arg, default="cpu", help="device for the report's rollouts (cpu, cuda)")
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
            kwargs.update(type=positive_int)  # the systems' integer parameters are counts (actions, repeats)
        elif isinstance(default, str):
            kwargs.update(type=str)
        else:
            kwargs.update(type=float)
        group.add_argument(flag, help=f"default {_defaults_of(name)}".replace("%", "%%"), **kwargs)
    return parser


def _given(args: argparse.Namespace, name: str) -> bool:
    """Whether the flag of ``name`` was given (a config flag leaves no attribute when it was not)."""
    return getattr(args, name, None) not in (None, False)


def check_flags(args: argparse.Namespace) -> None:
    """Refuse flags that the chosen method or points mode would ignore (naming both)."""
    other, foreign = ("coverage", COVERAGE_ONLY) if args.method == "maxflow" else ("maxflow", MAXFLOW_ONLY)
    for name in foreign:
        if _given(args, name):
            raise CLIError(f"{flag_name(name)} applies to --method {other} only, not to --method {args.method}")
    points = getattr(args, "points", BuildConfig().points.value)
    if _given(args, "points_per_cell") and points != PointMode.RANDOM.value:
        raise CLIError(f"--points-per-cell applies to --points random only, not to --points {points}")
    if _given(args, "rollouts") and args.no_report:
        raise CLIError("--rollouts sets the report's rollouts, but --no-report skips the report")


def parse_build_args(argv: Sequence[str]) -> argparse.Namespace:
    """The flags ``argv`` of a build, user system modules imported first and combinations checked."""
    load_user_systems(argv)
    args = make_parser().parse_args(argv)
    check_flags(args)
    if args.threads < 0:
        raise CLIError(f"--threads must be >= 0 (0: torch's choice), got {args.threads}")
    return args


def system_of(args: argparse.Namespace) -> tuple[str, System]:
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


def table_job(args: argparse.Namespace, system: System, out: Path) -> TableJob:
    """The :class:`TableJob` that the parsed flags ``args`` describe (the one path from flags to a job, so each
    default lives in its dataclass only)."""
    from precompute.coverage.method import CoverageConfig

    horizon = system_horizon(system) if args.horizon is None else args.horizon
    map_fields = map_overrides(args, system)
    build = dataclass_from_args(BuildConfig, args, horizon=horizon, **map_fields)
    coverage = None
    if args.method == "coverage":
        coverage = dataclass_from_args(CoverageConfig, args, horizon=horizon, local_map=build.local_map,
                                       radius=build.radius)
    return TableJob(system=system, out=out, build=build, coverage=coverage, report=not args.no_report,
                    rollouts=args.rollouts, device=args.device, resume=args.resume, max_memory_gb=args.max_memory,
                    quiet=args.quiet)
