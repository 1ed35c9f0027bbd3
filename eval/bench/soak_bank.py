"""Soak of the background proposal bank: many C-Uniform commands while a worker thread refreshes the bank.

    python -m eval.bench soak_bank                                    # 20 000 commands, bank 20 000, K = 1000, refresh 5
    python -m eval.bench soak_bank --commands 20000 --fail-once --json out/soak_bank.json

A :class:`~cuniform_torch.controllers.mppi.CUniformMPPI` with ``bank_background=True`` runs ``--commands`` commands from one
pose on the Dubins car (cost: squared distance to a goal summed over the horizon). Every ``--sample-every``
commands the process's resident memory (RSS, from /proc) and the live ``cuniform-bank`` worker threads are
recorded. ``--fail-once`` makes the first background refresh raise, to show that the controller reports it once
(a ``BankRefreshWarning``), goes on with its bank and later refreshes succeed. After ``close()`` no worker
thread may be left. What to look for: RSS flat from the warm-up (5% of the commands) to the end, at most one
worker thread, none after close.
Writes JSON to ``--json`` when given; exit code 1 when a worker thread outlives ``close()`` or a command is not
finite.
"""

from __future__ import annotations

import threading
import warnings
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
from tqdm import tqdm

from cuniform_torch import CUniformMPPI, Dubins, load_table
from cuniform_torch.common.fileio import write_json
from cuniform_torch.controllers.mppi import BankRefreshWarning
from eval.bench.cli import refuse_old_spelling
from precompute.cli import (
    MAX_COUNT,
    ArgumentParser,
    add_system_module_arg,
    check_output_file,
    cli_main,
    device_arg,
    horizon_arg,
    import_system_modules,
    int_in,
    positive_int,
    refuse_flags,
)

THREAD_PREFIX = "cuniform-bank"


@dataclass
class SoakResult:
    """What one soak measured (sizes in MiB)."""

    commands: int
    rss_start_mib: float
    """after construction and the first command"""
    rss_warm_mib: float
    """after the first 5% of the commands (the second bank, the worker's allocations and caches exist by then)"""
    rss_end_mib: float
    """after the last command, before ``close()``"""
    rss_max_mib: float
    max_worker_threads: int
    """most live ``cuniform-bank`` threads seen at a sample"""
    worker_threads_after_close: int
    banks_swapped: int
    bank_failures: int
    warnings: int
    """BankRefreshWarnings emitted"""
    finite: bool
    """every command was finite"""


def rss_mib() -> float:
    """Resident memory of this process now (Linux /proc; the peak from getrusage elsewhere)."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def worker_threads() -> int:
    """Live threads of any controller's bank worker."""
    return sum(t.name.startswith(THREAD_PREFIX) and t.is_alive() for t in threading.enumerate())


def fail_first_refresh(ctrl: CUniformMPPI) -> None:
    """Make the controller's first background refresh raise RuntimeError (later ones draw as usual)."""
    draw = ctrl._draw_bank
    calls = [0]

    def failing(generator: torch.Generator):
        calls[0] += 1
        if calls[0] == 1:
            raise RuntimeError("injected failure of the first background refresh (--fail-once)")
        return draw(generator)

    ctrl._draw_bank = failing


def soak(policy, commands: int, num_samples: int = 1000, bank_size: int = 20000, refresh: int = 5,
         fail_once: bool = False, sample_every: int = 100, quiet: bool = True, seed: int = 0) -> SoakResult:
    """Run ``commands`` background-bank commands of ``policy`` (a Dubins table or MLP) and measure them."""
    goal = torch.tensor([3.0, 1.0], dtype=policy.dtype, device=policy.device)

    def cost(states, actions):  # [K, T+1, d] -> [K]
        return ((states[:, 1:, :2] - goal) ** 2).sum(dim=(1, 2))

    state = torch.tensor([0.2, -0.1, 0.3], dtype=policy.dtype, device=policy.device)
    before = worker_threads()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", BankRefreshWarning)
        ctrl = CUniformMPPI(policy, cost, num_samples=num_samples, bank_size=bank_size, bank_refresh=refresh,
                            bank_background=True, seed=seed)
        try:
            if fail_once:
                fail_first_refresh(ctrl)
            finite = bool(torch.isfinite(ctrl.command(state)).all())
            rss_start = rss_max = rss_warm = rss_mib()
            threads = worker_threads() - before
            warm = max(1, commands // 20)
            for i in tqdm(range(1, commands), disable=quiet, desc="soak", unit="cmd", mininterval=1.0):
                finite &= bool(torch.isfinite(ctrl.command(state)).all())
                if i == warm:
                    rss_warm = rss_mib()
                if i % sample_every == 0:
                    rss_max = max(rss_max, rss_mib())
                    threads = max(threads, worker_threads() - before)
            rss_end = rss_mib()
        finally:
            ctrl.close()
    return SoakResult(commands, round(rss_start, 1), round(rss_warm, 1), round(rss_end, 1), round(max(rss_max, rss_end), 1), threads,
                      worker_threads() - before, ctrl.banks_swapped, ctrl.bank_failures,
                      sum(issubclass(w.category, BankRefreshWarning) for w in caught), finite)


def _policy(path: Path | None, horizon: int, device: str):
    if path is not None:
        return load_table(path, device=device)
    from cuniform_torch.policies.table import TablePolicy
    from precompute.flow.builder import BuildConfig, build_table

    table, _ = build_table(Dubins(), BuildConfig(horizon=horizon))
    return TablePolicy(table, device=device)


def make_parser() -> ArgumentParser:
    p = ArgumentParser(prog="python -m eval.bench soak_bank", description=__doc__.split("\n\n")[0])
    p.add_argument("--commands", type=positive_int, default=20000)
    p.add_argument("--samples", type=int_in(2, MAX_COUNT), default=1000, help="K, proposals per command")
    p.add_argument("--bank-size", type=positive_int, default=20000)
    p.add_argument("--refresh", type=positive_int, default=5, help="commands between background refreshes")
    p.add_argument("--fail-once", action="store_true", help="make the first background refresh raise")
    p.add_argument("--table", type=Path, default=None, help="a Dubins table (default: built in memory, --horizon)")
    p.add_argument("--horizon", type=horizon_arg, default=15,
                   help="of the table built in memory (15: the 3 s table; not with --table)")
    p.add_argument("--sample-every", type=positive_int, default=100, help="commands between RSS / thread samples")
    p.add_argument("--device", type=device_arg, default="cpu")
    p.add_argument("--quiet", action="store_true")
    p.add_argument("--json", type=Path, default=None)
    add_system_module_arg(p)
    return p


@cli_main()
def main(argv=None) -> int:
    p = make_parser()
    args = p.parse_args(argv)
    if args.table is not None:
        refuse_flags(p, args, ["horizon"], f"with --table (the horizon is {args.table}'s)")
    import_system_modules(args.system_module)
    if args.json is not None:
        check_output_file(args.json, "--json", "soak_bank.json")
    policy = _policy(args.table, args.horizon, args.device)
    result = soak(policy, args.commands, args.samples, args.bank_size, args.refresh, args.fail_once,
                  args.sample_every, args.quiet)
    for key, value in asdict(result).items():
        print(f"{key:28} {value}")
    if args.json is not None:
        write_json(args.json, asdict(result))
        print(f"wrote {args.json}")
    return 0 if result.finite and result.worker_threads_after_close == 0 else 1


refuse_old_spelling(__name__, "soak_bank")  # run as the old module command: one line naming the new spelling, exit 2
