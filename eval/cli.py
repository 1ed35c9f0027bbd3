"""Command-line pieces every experiment module shares: the source-file flags and running one experiment."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Callable

from cuniform_torch import TableError
from cuniform_torch.fileio import write_json

from . import config
from .methods import Sources


def add_source_args(p: argparse.ArgumentParser, horizon15: bool = False) -> None:
    """--table / --coverage-table / --policy / --device flags (defaults from eval.config: the 2 s tables, or
    the 3 s ones of the closed-loop experiments with ``horizon15``)."""
    p.add_argument("--table", type=Path, default=config.TABLE_15 if horizon15 else config.TABLE,
                   help="max-flow table (also the system, grid and horizon of the experiment)")
    p.add_argument("--coverage-table", type=Path,
                   default=config.COVERAGE_TABLE_15 if horizon15 else config.COVERAGE_TABLE)
    p.add_argument("--policy", type=Path, default=config.POLICY_15 if horizon15 else config.POLICY,
                   help="distilled MLP (cu_mlp)")
    p.add_argument("--device", default="cpu")


def sources_from_args(args: argparse.Namespace) -> Sources:
    return Sources(table=args.table, coverage_table=args.coverage_table, policy=args.policy, device=args.device)


def run_experiment(run: Callable[..., dict], cfg, args: argparse.Namespace, show: Callable[[dict], None]) -> int:
    """``run(cfg, sources)``, then ``show`` the result and write ``--json``; bad input is a one-line error (exit 2)."""
    try:
        result = run(cfg, sources_from_args(args))
    except (TableError, ValueError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    show(result)
    if args.json is not None:
        write_json(args.json, result)
        print(f"wrote {args.json}")
    return 0
