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
from collections.abc import Sequence
from pathlib import Path

from cuniform_torch.cli import OUT, cli_main
from cuniform_torch.common.fileio import exclusive_lock
from cuniform_torch.systems import System
from precompute.build_args import COVERAGE_ONLY, MAXFLOW_ONLY, make_parser
from precompute.one_table import parse_build_args, run_one, system_of, with_threads
from precompute.system_args import parse_params
from precompute.table_set import build_set, parse_starts, set_complete

__all__ = ["main", "ensure_set", "make_parser", "MAXFLOW_ONLY", "COVERAGE_ONLY", "parse_params"]


@cli_main(interrupted="interrupted: no table written")
def main(argv: Sequence[str] | None = None) -> int:
    """Build a table (or, with ``--starts``, a table set) from the flags ``argv``: 0, or 2 after one
    ``error: ...`` line, or 130 on Ctrl-C."""
    argv = sys.argv[1:] if argv is None else list(argv)
    args = parse_build_args(argv)
    return with_threads(args, lambda: _run(args, argv))


def _run(args: argparse.Namespace, argv: Sequence[str] = ()) -> int:
    if args.starts is not None:
        name, system = system_of(args)
        return _run_set(args, argv, name, system)
    return run_one(args)


def _run_set(args: argparse.Namespace, argv: Sequence[str], name: str, system: System) -> int:
    """``--starts``: every start's table into the folder ``--out`` (:mod:`precompute.table_set`)."""
    if getattr(args, "start", None) is not None:
        raise ValueError("give --start (one table) or --starts (a table set), not both")
    if args.map_file is not None:
        raise ValueError("--map builds one safe table; a table set (--starts) takes no map (see precompute.maps.farm)")
    if args.workers < 1:
        raise ValueError(f"--workers must be >= 1, got {args.workers}")
    starts = parse_starts(args.starts, system, seed=getattr(args, "seed", 0))
    out: Path = args.out or OUT / f"{name}_set"
    if out.suffix == ".npz":
        raise ValueError(f"--out {out}: a table set is a folder (e.g. --out out/{name}_set)")
    with exclusive_lock(out / ".lock", what=f"the table set {out}"):
        return build_set(argv, system, starts, out, workers=args.workers, ray_address=args.ray, method=args.method,
                         quiet=args.quiet)


def ensure_set(folder: Path, build_argv: Sequence[str], count: int | None = None, quiet: bool = False) -> Path:
    """``folder``, built first by ``python -m precompute.build *build_argv --out folder`` (``build_argv`` names
    the system and ``--starts``) when it is not a complete set; a failed build is a RuntimeError naming it."""
    if set_complete(folder, count):
        return Path(folder)
    argv = [*build_argv, "--out", str(folder), *(["--quiet"] if quiet else [])]
    if main(argv) != 0 or not set_complete(folder, count):
        raise RuntimeError(f"building the table set {folder} failed (python -m precompute.build {' '.join(argv)})")
    return Path(folder)


if __name__ == "__main__":
    sys.exit(main())
