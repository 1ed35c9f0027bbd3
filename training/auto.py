"""C-Uniform for a new system in one call: choose, build (or reuse) and distil, then a controller.

    python -m training.auto --system my_robots:Pendulum --starts "0=-3.14159:3.14159 1=-8:8" --horizon 15

::

    from training.auto import auto_cuniform
    auto = auto_cuniform(Pendulum(), "0=-3.14159:3.14159 1=-8:8", horizon=15)   # prints what it chose and why
    ctrl = auto.controller(cost, num_samples=100)                               # C-Uniform MPPI on the MLP

:func:`auto_cuniform` runs :func:`precompute.auto.choose` (the action set, the cell sizes, the start grid; module
docstring there), builds the table set (cached by the digest of the choices under ``out``), and, when the set has
more than one member, distils it into one start-conditioned MLP (:mod:`training.sets.distill`; cached beside the
set as ``<set>.policy.pt``), which serves starts between the members. ``AutoResult.controller(cost)`` is a
:class:`~cuniform_torch.CUniformMPPI` (or ``kind="cumppi"``: :class:`~cuniform_torch.CUMPPI`) on the MLP (or
``policy="set"``: the table set). The command prints the same report and the times and writes
``<set>.auto.json``.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import io
import os
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cuniform_torch.common.fileio import write_json
from cuniform_torch.controllers.mppi import CUMPPI, CUniformMPPI
from cuniform_torch.policies.checkpoint import load_policy
from cuniform_torch.policies.table import TablePolicy
from cuniform_torch.policies.table_set import TableSetPolicy, load_table_set
from cuniform_torch.systems import System
from cuniform_torch.tables.file import read_table
from precompute.auto import AutoConfig, Choice, build_auto_set, choose, format_choice, parse_region
from precompute.build import with_threads
from precompute.build_args import system_of
from precompute.cli import (
    OUT,
    ArgumentParser,
    add_dataclass_args,
    cli_main,
    dataclass_from_args,
    horizon_arg,
    int_in,
    positive_float,
    positive_int,
)
from precompute.system_args import load_user_systems
from training.tables.config import DistillConfig

__all__ = ["DistillBudget", "AutoResult", "auto_cuniform", "main"]


@dataclass(frozen=True)
class DistillBudget:
    """The start-conditioned MLP's training (a small network and few epochs: the pendulum's 63 tables train in
    about a minute on one core)."""

    hidden: int = 64
    """hidden units per layer"""
    layers: int = 2
    """hidden layers"""
    epochs: int = 30
    """passes over the set's cells"""
    lr: float = 3e-3
    """Adam's initial learning rate"""
    batch_size: int = 4096
    """samples per step"""


@dataclass
class AutoResult:
    """What :func:`auto_cuniform` built: the choice, the set (or single table), the MLP and the times."""

    choice: Choice
    table_set: TableSetPolicy | TablePolicy
    """the tables: a set (several members) or one table"""
    mlp: Any | None
    """the start-conditioned MLP (:class:`~cuniform_torch.policies.start_mlp.StartMLPPolicy`; None for one table)"""
    path: Path
    """the set's folder (or the table file)"""
    seconds: dict[str, float] = field(default_factory=dict)
    """``choose``, ``build``, ``distill`` (0 when reused)"""

    @property
    def policy(self) -> Any:
        """The policy a controller samples from: the MLP, else the single table."""
        return self.mlp if self.mlp is not None else self.table_set

    def controller(self, cost_fn: Any, num_samples: int = 100, kind: str = "cuniform", policy: str = "mlp",
                   **kwargs: Any) -> CUniformMPPI | CUMPPI:
        """A controller on the chosen tables: ``kind`` ``"cuniform"`` (:class:`CUniformMPPI`) or ``"cumppi"``
        (:class:`CUMPPI`), ``policy`` ``"mlp"`` (the start-conditioned MLP) or ``"set"`` (the table set);
        ``kwargs`` go to the controller (``lambda_``, ``seed``, ``num_robots``, ...).

        :param cost_fn: trajectory cost, ``states [N, T+1, d]``, ``actions [N, T, q]`` -> ``[N]``
        :param num_samples: K rollouts per command
        """
        if policy not in ("mlp", "set"):
            raise ValueError(f"policy must be 'mlp' or 'set', got {policy!r}")
        chosen = self.policy if policy == "mlp" else self.table_set
        if kind == "cuniform":
            return CUniformMPPI(chosen, cost_fn, num_samples=num_samples, **kwargs)
        if kind == "cumppi":
            return CUMPPI(chosen, cost_fn, num_samples=num_samples, **kwargs)
        raise ValueError(f"kind must be 'cuniform' or 'cumppi', got {kind!r}")

    def report(self) -> str:
        """What was chosen and why, and the times."""
        times = ", ".join(f"{k} {v:.1f} s" for k, v in self.seconds.items())
        what = f"{self.path} ({'a start-conditioned MLP over ' if self.mlp is not None else ''}"
        what += f"{len(self.choice.starts)} table{'s' if len(self.choice.starts) > 1 else ''})"
        return format_choice(self.choice) + f"\n  built: {what}; {times}"


def auto_cuniform(system: System, starts: str | dict, horizon: int = 15, *, out: str | Path = OUT / "auto",
                  config: AutoConfig | None = None, distill: DistillBudget = DistillBudget(), workers: int = 1,
                  seed: int = 0, quiet: bool = False) -> AutoResult:
    """Choose, build or reuse, distil (module docstring); prints the report unless ``quiet``.

    :param system: a dataclass system with a ``cell_size`` field (and ``num_actions`` for the chooser to set
        the action count); its ``periodic`` declares the angles
    :param starts: the region of starts, ``"DIM=LO:HI ..."`` or ``{dim: (lo, hi)}``
    :param horizon: steps T of the tables
    :param out: the cache folder (a set per digest of the choices)
    :param config: the chooser's budgets (its ``horizon`` is replaced by ``horizon``)
    :param distill: the MLP's size and training
    :param workers: processes building the tables
    :param seed: seed of the MLP's training
    """
    config = dataclasses.replace(config or AutoConfig(), horizon=horizon)
    region = parse_region(starts, system)
    say = (lambda *a: None) if quiet else (lambda *a: print(*a, flush=True))
    seconds: dict[str, float] = {}
    t0 = time.perf_counter()
    choice = choose(system, region, config)
    seconds["choose"] = time.perf_counter() - t0
    say(format_choice(choice))
    t0 = time.perf_counter()
    path = build_auto_set(choice, Path(out), workers=workers, quiet=quiet)
    seconds["build"] = time.perf_counter() - t0
    if path.suffix == ".npz":
        table = TablePolicy(read_table(path))
        result = AutoResult(choice, table, None, path, seconds)
        say(f"  built: {path} (one table); build {seconds['build']:.1f} s")
        return result
    tset = load_table_set(path)
    policy_path = path.with_name(path.name + ".policy.pt")
    t0 = time.perf_counter()
    if not policy_path.exists():
        from training.distill import distill as run_distill

        cfg = DistillConfig(tables=[str(path)], out=str(policy_path), hidden=distill.hidden, layers=distill.layers,
                            epochs=distill.epochs, lr=distill.lr, batch_size=distill.batch_size, seed=seed,
                            quiet=quiet, eval_samples=[200], eval_every=max(distill.epochs, 1),
                            logdir=str(path.with_name(path.name + ".runs")))
        with contextlib.redirect_stdout(io.StringIO()) if quiet else contextlib.nullcontext():
            with_threads(1, lambda: run_distill(cfg))  # quiet: its per-member comparison is in the JSON beside it
    seconds["distill"] = time.perf_counter() - t0
    mlp = load_policy(policy_path)
    result = AutoResult(choice, tset, mlp, path, seconds)
    say(f"  built: {path} and {policy_path.name}; " + ", ".join(f"{k} {v:.1f} s" for k, v in seconds.items()))
    return result


def make_parser() -> ArgumentParser:
    parser = ArgumentParser(prog="python -m training.auto", description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--system", required=True, help="a registered system or module:factory (a dataclass "
                                                        "with a cell_size field; num_actions lets the chooser set A)")
    parser.add_argument("--system-module", action="append", default=[], metavar="MODULE",
                        help="import MODULE first (repeatable); it registers user systems with register_system")
    parser.add_argument("--param", action="append", default=[], metavar="KEY=VALUE",
                        help="a system parameter as JSON (repeatable)")
    parser.add_argument("--starts", required=True, metavar="SPEC",
                        help="the region of starts, 'DIM=LO:HI ...' (e.g. '0=-3.14159:3.14159 1=-8:8')")
    add_dataclass_args(parser, AutoConfig, arg_types={
        "horizon": horizon_arg, "seed": int_in(0, 2**31 - 1), "shift_cells": positive_float,
        **{n: positive_int for n in ("cell_budget", "member_budget", "probes", "sequences", "actions_per_dim")}})
    add_dataclass_args(parser, DistillBudget, arg_types={"hidden": int_in(1, 65536), "layers": int_in(1, 64),
                                                         "epochs": positive_int, "batch_size": positive_int,
                                                         "lr": positive_float})
    parser.add_argument("--workers", type=int_in(1, 1024), default=2, help="processes building the tables")
    parser.add_argument("--out", type=Path, default=OUT / "auto", help="the cache folder")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    return parser


@cli_main(interrupted="interrupted: the finished tables are kept; rerun to resume")
def main(argv: Sequence[str] | None = None) -> int:
    """Choose, build and distil from the flags ``argv``: 0, or 2 after one ``error: ...`` line."""
    argv = sys.argv[1:] if argv is None else list(argv)
    load_user_systems(argv)  # --system-module and module:factory first: their systems are then known
    args = make_parser().parse_args(argv)
    _, system = system_of(argparse.Namespace(system=args.system, param=args.param))
    config = dataclass_from_args(AutoConfig, args)
    budget = dataclass_from_args(DistillBudget, args)
    t0 = time.perf_counter()
    result = with_threads(1, lambda: auto_cuniform(system, args.starts, config.horizon, out=args.out, config=config,
                                                   distill=budget, workers=args.workers, quiet=args.quiet))
    record = result.path.with_name(result.path.name + ".auto.json")
    write_json(record, {**result.choice.to_dict(), "seconds": {**result.seconds, "total": time.perf_counter() - t0},
                        "path": str(result.path), "load_1min": os.getloadavg()[0]})
    print(f"total {time.perf_counter() - t0:.1f} s (load {os.getloadavg()[0]:.2f}); wrote {record}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
