"""Command-line pieces every experiment module shares: the source-file flags and running one experiment.

Errors and exit codes are :mod:`cuniform_torch.cli`'s: every ``main`` is decorated with ``cli_main``.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Callable

from cuniform_torch.cli import add_system_module_arg, check_output_file, check_output_folder, import_system_modules
from cuniform_torch.fileio import write_json

from . import config
from .methods import Sources


def add_source_args(p: argparse.ArgumentParser, horizon15: bool = False) -> None:
    """--table / --coverage-table / --policy / --device / --system-module flags (defaults from eval.config: the
    2 s tables, or the 3 s ones of the closed-loop experiments with ``horizon15``)."""
    p.add_argument("--table", type=Path, default=config.TABLE_15 if horizon15 else config.TABLE,
                   help="max-flow table (also the system, grid and horizon of the experiment)")
    p.add_argument("--coverage-table", type=Path,
                   default=config.COVERAGE_TABLE_15 if horizon15 else config.COVERAGE_TABLE)
    p.add_argument("--policy", type=Path, default=config.POLICY_15 if horizon15 else config.POLICY,
                   help="distilled MLP (cu_mlp)")
    p.add_argument("--device", default="cpu")
    add_system_module_arg(p)


def prepare(args: argparse.Namespace) -> None:
    """Before the experiment runs: import the ``--system-module`` modules and check the output paths
    (``--json``, ``--figures``), so that a bad one fails now rather than after the work."""
    import_system_modules(args.system_module)
    if getattr(args, "json", None) is not None:
        check_output_file(args.json, "--json", example="result.json")
    if getattr(args, "figures", None) is not None:
        check_output_folder(args.figures, "--figures")


def sources_from_args(args: argparse.Namespace) -> Sources:
    return Sources(table=args.table, coverage_table=args.coverage_table, policy=args.policy, device=args.device)


def run_experiment(run: Callable[..., dict], cfg, args: argparse.Namespace, show: Callable[[dict], None]) -> int:
    """``prepare``, ``run(cfg, sources)``, then ``show`` the result and write ``--json``; bad input raises (the
    entry point's ``cli_main`` turns it into one ``error: ...`` line and exit code 2)."""
    prepare(args)
    result = run(cfg, sources_from_args(args))
    show(result)
    if args.json is not None:
        write_json(args.json, result)
        print(f"wrote {args.json}")
    return 0
