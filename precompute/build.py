"""Build a C-Uniform table:  python -m precompute.build --system dubins --out out/dubins.npz

Every parameter of a registered dataclass system is a flag (``--horizon 15``, ``--num-actions 21``,
``--cell-size 0.1 0.1 0.1571``, ...); ``--param KEY=VALUE`` (a JSON value) sets any parameter of any system.
Prints a progress bar per level, per-stage times and the uniformity report; writes the table (atomically) and
``<out stem>.report.json`` beside it. Each finished level is checkpointed in ``<out>.partial/``; after an
interrupt, ``--resume`` continues from there and writes a byte-identical table (and refuses, naming them, when
the settings changed). ``<out>.lock`` keeps a second build to the same ``--out`` from starting.

Errors (bad or conflicting flags, an unusable ``--out``, a full disk, ...) are one line ``error: ...`` and exit
code 2; Ctrl-C is one line and exit code 130 (see :mod:`cuniform_torch.cli`).

Safe level sets (C-Free-Uniform): ``--map FILE --radius R`` removes from every level the cells within R of the
local map's obstacles before the flow / coverage step (:mod:`precompute.levels.safe_map`: the map file and the rule).

User systems: ``--system-module my_robots`` imports a module that calls ``register_system`` (its dataclass
fields then become flags too), and ``--system my_robots:Unicycle`` imports and registers a factory directly.

The flags and the checks of their combination are :mod:`precompute.build_args`.

Size guidance (maxflow): from level 5 on, the build prints the projected size of the remaining levels and its
projected peak memory, and warns (naming ``--horizon`` and ``--cell-size``) when that exceeds the available
memory (``--max-memory GB`` sets the budget).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TypeVar

from cuniform_torch.cli import OUT, cli_main
from precompute.build_args import COVERAGE_ONLY, MAXFLOW_ONLY, make_parser, parse_build_args, system_of, table_job
from precompute.one_table import TableJob, build_table_file
from precompute.system_args import parse_params
from precompute.table_set import MAX_SET_MEMBERS, build_table_set, ensure_table_set, parse_starts

__all__ = ["main", "parse_job", "with_threads", "TableJob", "build_table_file", "build_table_set", "ensure_table_set",
           "make_parser", "MAXFLOW_ONLY", "COVERAGE_ONLY", "parse_params"]

T = TypeVar("T")


@cli_main(interrupted="interrupted: no table written")
def main(argv: Sequence[str] | None = None) -> int:
    """Build a table (or, with ``--starts``, a table set) from the flags ``argv``: 0, or 2 after one
    ``error: ...`` line, or 130 on Ctrl-C."""
    argv = sys.argv[1:] if argv is None else list(argv)
    args = parse_build_args(argv)
    return with_threads(args.threads, lambda: _run(args))


def with_threads(threads: int, run: Callable[[], T]) -> T:
    """``run()`` with ``threads`` torch threads (0: unchanged), the caller's setting restored after. The builds of
    ``eval.report`` and the navigation benchmark's robot use it with ``--threads``' default (1), as the command
    does: on 2 busy cores torch's default of one thread per core made the coverage build of the default preset
    5-10x slower (17-40 s against 2-3.5 s, load 5-6)."""
    import torch

    previous = torch.get_num_threads()
    if threads:
        torch.set_num_threads(threads)
    try:
        return run()
    finally:
        torch.set_num_threads(previous)


def parse_job(argv: Sequence[str]) -> tuple[TableJob, dict]:
    """The flags ``argv`` of ``python -m precompute.build`` as a job: ``(job, set)`` where ``set`` is ``{}`` for
    one table, else ``{"starts": [S, d], "out": folder, "workers": N, "ray_address": ...}`` for a table set
    (the job is then the members' template). A clear error for bad or conflicting flags."""
    return _job_of(parse_build_args(argv))


def _job_of(args: argparse.Namespace) -> tuple[TableJob, dict]:
    name, system = system_of(args)
    if args.starts is None:
        if args.workers != 1 or args.ray is not None or getattr(args, "no_limit", False):
            raise ValueError("--workers, --ray and --no-limit build a table set: give --starts too")
        return table_job(args, system, args.out or OUT / f"{name}.npz"), {}
    if getattr(args, "start", None) is not None:
        raise ValueError("give --start (one table) or --starts (a table set), not both")
    if args.map_file is not None:
        raise ValueError("--map builds one safe table; a table set (--starts) takes no map (see precompute.maps.farm)")
    if args.workers < 1:
        raise ValueError(f"--workers must be >= 1, got {args.workers}")
    starts = parse_starts(args.starts, system, seed=getattr(args, "seed", 0),
                          limit=None if getattr(args, "no_limit", False) else MAX_SET_MEMBERS)
    out: Path = args.out or OUT / f"{name}_set"  # build_table_set refuses a folder named like a file
    template = table_job(args, system, out / "start_0000.npz")
    return template, {"starts": starts, "out": out, "workers": args.workers, "ray_address": args.ray}


def _run(args: argparse.Namespace) -> int:
    job, table_set = _job_of(args)
    if table_set:
        build_table_set(job, **table_set)
    else:
        build_table_file(job)
    return 0


if __name__ == "__main__":
    sys.exit(main())
