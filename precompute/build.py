"""Build a C-Uniform table:  python -m precompute.build maxflow --system dubins --out out/dubins.npz

Four subcommands, each with only its own flags (``python -m precompute.build SUB --help``): ``maxflow`` (the
paper's flow network), ``coverage`` (the coverage method), ``set`` (a table set: ``--starts SPEC``, one table per
start, into a folder) and ``safe`` (C-Free-Uniform: ``--map FILE --radius R`` removes from every level the cells
within R of the local map's obstacles; :mod:`precompute.levels.safe_map`). ``--param KEY=VALUE`` (a JSON value)
sets any parameter of the system (``--param num_actions=7``). ``--print-config`` prints the job as JSON and builds
nothing; ``--config FILE`` builds from such a file (flags beside it win). The flags, the config file and the old
spelling (no subcommand, translated with a one-line note) are :mod:`precompute.build_args`.

Prints a progress bar per level, per-stage times and the uniformity report; writes the table (atomically) and
``<out stem>.report.json`` beside it. Each finished level is checkpointed in ``<out>.partial/``; after an
interrupt, ``--resume`` continues from there and writes a byte-identical table (and refuses, naming them, when
the settings changed). ``<out>.lock`` keeps a second build to the same ``--out`` from starting.

Errors (bad or conflicting flags, a bad config key, an unusable ``--out``, a full disk, ...) are one line
``error: ...`` and exit code 2; Ctrl-C is one line and exit code 130 (see :mod:`precompute.cli`).

User systems: ``--system-module my_robots`` imports a module that calls ``register_system``, and
``--system my_robots:Unicycle`` imports and registers a factory directly; their parameters are ``--param`` too.

Size guidance (maxflow): from level 5 on, the build prints the projected size of the remaining levels and its
projected peak memory, and warns (naming ``--horizon`` and the cell size) when that exceeds the available
memory (``--max-memory GB`` sets the budget).
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TypeVar

from precompute.build_args import (
    COMMANDS,
    COVERAGE_ONLY,
    MAXFLOW_ONLY,
    SetOptions,
    job_config,
    legacy_argv,
    make_parser,
    parse_build_args,
    system_of,
    table_job,
)
from precompute.cli import OUT, cli_main
from precompute.one_table import TableJob, build_table_file
from precompute.system_args import parse_params
from precompute.table_set import MAX_SET_MEMBERS, build_table_set, ensure_table_set, parse_starts

__all__ = ["main", "parse_job", "with_threads", "TableJob", "build_table_file", "build_table_set", "ensure_table_set",
           "make_parser", "MAXFLOW_ONLY", "COVERAGE_ONLY", "parse_params", "COMMANDS", "SetOptions", "job_config",
           "legacy_argv"]

T = TypeVar("T")


@cli_main(interrupted="interrupted: no table written")
def main(argv: Sequence[str] | None = None) -> int:
    """Build a table (or a table set) from the flags ``argv`` (default: the command line): 0, or 2 after one
    ``error: ...`` line, or 130 on Ctrl-C. The old spelling on the command line prints its new one first (a note on
    stderr); called with ``argv``, it is translated quietly."""
    command_line = argv is None
    argv = sys.argv[1:] if argv is None else list(argv)
    args = parse_build_args(argv)
    _, note = legacy_argv(argv)
    if note is not None and command_line:
        print(note, file=sys.stderr)
    if args.print_config:
        job, table_set = _job_of(args)
        print(json.dumps(job_config(args, job, table_set), indent=2))
        return 0
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
    if args.command != "set":
        return table_job(args, system, getattr(args, "out", None) or OUT / f"{name}.npz"), {}
    no_limit = getattr(args, "no_limit", False)
    starts = parse_starts(args.starts, system, seed=getattr(args, "seed", 0),
                          limit=None if no_limit else MAX_SET_MEMBERS)
    out: Path = getattr(args, "out", None) or OUT / f"{name}_set"  # build_table_set refuses a folder named like a file
    template = table_job(args, system, out / "start_0000.npz")
    return template, {"starts": starts, "out": out, "workers": getattr(args, "workers", 1),
                      "ray_address": getattr(args, "ray", None)}


def _run(args: argparse.Namespace) -> int:
    """The job of ``args`` through the library functions a Python user calls (:mod:`precompute.api`)."""
    from precompute.api import SetConfig, build_table
    from precompute.api import build_table_set as build_set

    job, table_set = _job_of(args)
    if table_set:
        config = SetConfig(starts=table_set["starts"], workers=table_set["workers"], ray=table_set["ray_address"],
                           no_limit=True)  # the flags' limit was checked when --starts was parsed
        build_set(job.system, config, job.build, coverage=job.coverage, out=table_set["out"], progress=not job.quiet)
    else:
        build_table(job.system, job.build, coverage=job.coverage, out=job.out, report=job.report,
                    rollouts=job.rollouts, device=job.device, resume=job.resume, max_memory_gb=job.max_memory_gb,
                    progress=not job.quiet)
    return 0


if __name__ == "__main__":
    sys.exit(main())
