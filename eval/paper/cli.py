"""Command-line pieces every experiment module shares: source and output flags, the closed-loop flags, and
running one experiment from its flags.

An experiment module (``eval.paper.coverage``, ``eval.paper.uniformity``, ``eval.paper.sudden_obstacle``,
``eval.paper.cluttered``) defines ``CONFIG`` (its config dataclass), ``QUICK`` (the ``--quick`` preset), ``run(cfg,
sources, progress)``, ``markdown(result)`` (and ``figures(result, folder)`` with ``--figures``), then gets its
``make_parser``, ``config_from_args`` and ``main`` from :func:`entry_points`; its flags are ``CONFIG``'s fields
(:func:`precompute.cli.add_dataclass_args`, so each default lives once, in the dataclass), their values checked
as they parse (:data:`OPEN_LOOP_TYPES`, :data:`CLOSED_LOOP_TYPES`). A closed-loop module also defines
``episode_counts(cfg)``, the scenario counts that multiply into episodes: a run of more than
:data:`precompute.cli.MAX_WORK` needs ``--no-limit``. Errors and exit codes are :mod:`precompute.cli`'s:
every ``main`` is decorated with ``cli_main``.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import Any

from cuniform_torch.common.fileio import write_json
from eval.common.methods import Sources
from eval.common.paths import DEFAULT
from precompute.cli import (
    ArgumentParser,
    add_dataclass_args,
    add_no_limit_arg,
    add_system_module_arg,
    check_output_file,
    check_output_folder,
    check_work,
    cli_main,
    dataclass_from_args,
    device_arg,
    float_in,
    horizon_arg,
    import_system_modules,
    int_in,
    positive_float,
    positive_int,
)

__all__ = ["add_source_args", "add_output_args", "OPEN_LOOP_TYPES", "CLOSED_LOOP_TYPES", "open_loop_flags",
           "add_closed_loop_args", "check_episodes", "make_parser", "config_from_args", "config_from_json", "prepare",
           "sources_from_args", "write_result", "main", "entry_points"]

OPEN_LOOP_TYPES = {"samples": positive_int, "seeds": positive_int, "merge_resolution": int_in(1, 1024)}
"""the open-loop configs' counts, checked as the flags parse (:mod:`precompute.cli`)"""
CLOSED_LOOP_TYPES = {"samples": int_in(2, 1_000_000), "seed": int_in(0, 2**31 - 1), "horizon": horizon_arg,
                     "positions": positive_int, "starts": positive_int, "seeds_per_start": positive_int,
                     "appear": float_in(0.0, 3600.0), "goal_tolerance": positive_float}
"""the closed-loop configs' fields, checked as the flags parse (N >= 2: CU-MPPI splits it in two)"""


def add_source_args(p: argparse.ArgumentParser, closed_loop: bool = False) -> None:
    """--table / --coverage-table / --policy / --device / --system-module flags (defaults: :data:`eval.common.paths.DEFAULT`'s
    2 s tables, or the 3 s ones of the closed-loop experiments with ``closed_loop``)."""
    p.add_argument("--table", type=Path, default=DEFAULT.table_cl if closed_loop else DEFAULT.table,
                   help="max-flow table (also the system, grid and horizon of the experiment)")
    p.add_argument("--coverage-table", type=Path,
                   default=DEFAULT.coverage_table_cl if closed_loop else DEFAULT.coverage_table)
    p.add_argument("--policy", type=Path, default=DEFAULT.policy, help="distilled MLP (cu_mlp)")
    p.add_argument("--device", type=device_arg, default="cpu", help="torch device (default: cpu)")
    add_system_module_arg(p)


def add_output_args(p: argparse.ArgumentParser, figures: bool = False) -> None:
    """--json (and --figures) flags, checked by :func:`prepare` before the experiment runs."""
    p.add_argument("--json", type=Path, default=None, help="write the results here")
    if figures:
        p.add_argument("--figures", type=Path, default=None, help="write PNG figures into this folder")


def open_loop_flags(cls: type, quick: str) -> Callable[[argparse.ArgumentParser], None]:
    """The open-loop experiments' flags: sources (2 s tables), every field of ``cls``, ``--quick`` (described by
    ``quick``) and ``--json``."""

    def add(p: argparse.ArgumentParser) -> None:
        add_source_args(p)
        fields = {f.name for f in dataclasses.fields(cls)}
        add_dataclass_args(p, cls, arg_types={k: v for k, v in OPEN_LOOP_TYPES.items() if k in fields})
        p.add_argument("--quick", action="store_true", help=f"{quick} (flags given win)")
        add_output_args(p)

    return add


CLOSED_LOOP_HELP = {
    "methods": "method keys (default: every closed-loop method whose files exist)",
    "include_mlp": "also run cu_mlp in a default run (slow on CPU)",
    "stop_at_goal": "charge a rollout's collisions after its arrival at the goal too (the plain NavigationCost; "
                    "default: the cost ends at the goal, NavigationCost.stop_at_goal)",
}


def add_closed_loop_args(p: argparse.ArgumentParser, cls: type, only: tuple[str, ...] = (), **kwargs) -> None:
    """The closed-loop experiments' flags: the :class:`ControllerSettings` fields a user sets (``--methods``,
    ``--samples``, ``--seed``, ``--horizon``, ``--mlp``, ``--collisions-after-goal``), the experiment's own
    fields ``only`` (``kwargs``: :func:`~precompute.cli.add_dataclass_args`' for them), sources (3 s tables),
    ``--json``, ``--figures``, ``--quick`` and ``--quiet``."""
    add_source_args(p, closed_loop=True)
    shared = ("methods", "samples", "seed", "horizon", "include_mlp", "stop_at_goal")
    add_dataclass_args(p, cls, only=shared, flags={"include_mlp": "--mlp", "stop_at_goal": "--collisions-after-goal"},
                       help=CLOSED_LOOP_HELP, arg_types={k: v for k, v in CLOSED_LOOP_TYPES.items() if k in shared})
    if only:
        arg_types = {k: v for k, v in CLOSED_LOOP_TYPES.items() if k in only} | kwargs.pop("arg_types", {})
        add_dataclass_args(p, cls, only=only, arg_types=arg_types, **kwargs)
    add_output_args(p, figures=True)
    p.add_argument("--quick", action="store_true", help="tiny sizes (a few seconds)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--workers", type=int_in(1, 1024), default=1,
                   help="run the episodes in this many processes, one torch thread each (records the same; default 1)")
    add_no_limit_arg(p)


def check_episodes(cfg: Any, scenarios: dict[str, int], no_limit: bool) -> None:
    """CLIError when ``scenarios`` (``{"positions": 20, "appearance times": 5}``) x the budgets (x the methods
    given; per method without ``--methods``) is more episodes than :data:`precompute.cli.MAX_WORK` (without
    ``--no-limit``)."""
    counts = {**scenarios, "budgets": len(cfg.samples)}
    if cfg.methods is not None:
        counts["methods"] = len(cfg.methods)
    check_work(counts, "episodes" if cfg.methods is not None else "episodes per method", no_limit)


def make_parser(module: ModuleType, add_flags: Callable[[argparse.ArgumentParser], None]) -> ArgumentParser:
    """The parser of an experiment module (``prog`` from its name, description from its docstring's first line)."""
    spec = getattr(module, "__spec__", None)  # run as `python -m eval.x`, the module's __name__ is "__main__"
    name = spec.name if spec is not None else module.__name__
    p = ArgumentParser(prog=f"python -m {name}", description=(module.__doc__ or "").split("\n\n")[0])
    add_flags(p)
    return p


def config_from_args(module: ModuleType, args: argparse.Namespace) -> Any:
    """The module's ``CONFIG`` from the flags given, over ``QUICK`` with ``--quick`` (else the defaults)."""
    return dataclass_from_args(module.CONFIG, args, base=module.QUICK if getattr(args, "quick", False) else None)


def config_from_json(cls: type, values: dict):
    """A config dataclass from its ``asdict`` JSON (lists back to tuples where the field is a tuple)."""
    return dataclass_from_args(cls, argparse.Namespace(**{f.name: values[f.name] for f in dataclasses.fields(cls)
                                                          if f.name in values}))


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


def write_result(path: Path, result: dict) -> None:
    """Write a result as JSON (atomically) and say so."""
    write_json(path, result)
    print(f"wrote {path}")


def main(module: ModuleType, argv, show: Callable[[dict], None] | None = None) -> int:
    """Run the experiment ``module`` from the flags ``argv``: parse, :func:`prepare`, ``run``, then show the
    result (``show``, default: print its markdown), write ``--json`` and the ``--figures``. Bad input raises (the
    entry point's ``cli_main`` turns it into one ``error: ...`` line and exit code 2)."""
    args = module.make_parser().parse_args(argv)
    cfg = module.config_from_args(args)
    prepare(args)
    workers = {"workers": args.workers} if hasattr(args, "workers") else {}  # the closed-loop experiments'
    result = module.run(cfg, sources_from_args(args), progress=not getattr(args, "quiet", False), **workers)
    (show or (lambda r: print(module.markdown(r))))(result)
    if args.json is not None:
        print()
        write_result(args.json, result)
    if getattr(args, "figures", None) is not None:
        for p in module.figures(result, args.figures):
            print(f"wrote {p}")
    sys.stdout.flush()
    return 0


def entry_points(name: str, add_flags: Callable[[argparse.ArgumentParser], None],
                 show: Callable[[dict], None] | None = None, check: Callable[[argparse.Namespace], None] | None = None,
                 threads: int | None = None):
    """``(make_parser, config_from_args, main)`` of the experiment module ``name`` (its ``__name__``): the parser
    gets ``add_flags``; ``check(args)`` may refuse flags (``parser.error``) before the config is made; ``main``
    (:func:`main` under ``cli_main``) sets torch's CPU ``threads`` first when given."""

    def module() -> ModuleType:
        return sys.modules[name]

    def make_parser_() -> ArgumentParser:
        return make_parser(module(), add_flags)

    def config_from_args_(args: argparse.Namespace):
        if check is not None:
            check(args)
        cfg = config_from_args(module(), args)
        episodes = getattr(module(), "episode_counts", None)
        if episodes is not None:
            check_episodes(cfg, episodes(cfg), getattr(args, "no_limit", False))
        return cfg

    @cli_main()
    def main_(argv=None) -> int:
        if threads is not None:
            import torch

            torch.set_num_threads(threads)
        return main(module(), argv, show)

    return make_parser_, config_from_args_, main_
