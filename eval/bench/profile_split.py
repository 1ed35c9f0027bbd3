"""Where a control cycle goes, from a cProfile of a benchmark run:  python -m eval.bench profile_split PROFILE

Make the profile with ``python -m cProfile -o PROFILE -m eval.navigate ... --methods M --budgets K --workers 1``
(one method and one K per profile: the split is per command of the whole run). Printed, in ms per command:

* ``sampling``: the proposal's ``propose_batch`` called by the controller's ``_plan`` (noise and rollouts);
* ``cost``: ``plan``'s ``_evaluate`` (the cost function over the K rollouts);
* ``the rest of plan``: weights, the weighted average, the warm start;
* ``command``: all of ``command`` (``plan`` plus its input checks);
* ``episode harness``: the simulator loop's time beyond the commands (stepping, collision checks, bookkeeping).

A two-stage controller (CU-MPPI, CFU-MPPI) plans inside its proposal, and cProfile merges the two levels of
``plan``: its sampling, cost and rest are not split (nan), only ``command`` and the harness.

It reads only function names of the controller core (``command``, ``_plan`` or before batching ``plan``,
``_evaluate``, ``propose_batch`` or ``propose``, ``simulate``), so the profile of an older checkout (a git worktree)
splits the same way.
cProfile's own overhead inflates code of many small calls: compare splits of profiles, not with unprofiled
times.
"""

from __future__ import annotations

import pstats
from collections.abc import Sequence
from pathlib import Path

from cuniform_torch.common.fileio import check_regular
from eval.bench.cli import refuse_old_spelling
from precompute.cli import ArgumentParser, CLIError, cli_main

__all__ = ["split", "main"]

_CORE_FILES = ("controllers/core.py", "mppi_core.py")
"""where ``command`` / ``plan`` / ``_evaluate`` of the MPPI core live (this version, and before the layout change)"""


def _find(stats: dict, name: str, files: Sequence[str]) -> list[tuple]:
    return [key for key in stats if key[2] == name and key[0].replace("\\", "/").endswith(tuple(files))]


def split(profile: str | Path) -> dict[str, float]:
    """``profile`` (a cProfile output file) -> commands and ms per command of each part (module docstring)."""
    try:
        check_regular(profile, "a cProfile output")  # a FIFO would block the read
        stats = pstats.Stats(str(profile)).stats  # type: ignore[attr-defined]
    except (OSError, EOFError, ValueError, TypeError) as exc:
        raise CLIError(f"{profile}: not a readable cProfile output ({type(exc).__name__}: {exc})") from None
    commands = _find(stats, "command", _CORE_FILES)
    # the batched core plans in ``_plan`` (``plan`` and ``command`` call it); an older core plans in ``plan``
    plans = _find(stats, "_plan", _CORE_FILES) or _find(stats, "plan", _CORE_FILES)
    if not commands or not plans:
        raise CLIError(f"{profile}: no controller command in this profile (profile an eval.navigate run)")
    n = sum(stats[k][0] for k in commands)  # primitive calls: one per command
    command_s = sum(stats[k][3] for k in commands)
    outer = set(plans)

    def called_from_plan(name: str, files: Sequence[str] | None = None) -> float:
        total = 0.0
        for key, (_, _, _, _, callers) in stats.items():
            if key[2] != name or (files is not None and not key[0].replace("\\", "/").endswith(tuple(files))):
                continue
            for caller, edge in callers.items():
                if caller in outer and key not in outer:
                    total += edge[3]
        return total

    plan_s = sum(stats[k][3] for k in plans)
    recursive = any(stats[k][1] != stats[k][0] for k in plans)
    nan = float("nan")
    # a two-stage controller (CU-MPPI, CFU-MPPI) runs a plan inside its proposal: cProfile merges the two levels,
    # so only the whole command is split off
    sampling = nan if recursive else called_from_plan("propose_batch") + called_from_plan("propose")
    cost = nan if recursive else called_from_plan("_evaluate", _CORE_FILES)
    sims = [k for k in stats if k[2] == "simulate"]
    harness = sum(stats[k][3] for k in sims) - command_s if sims else float("nan")
    ms = 1e3 / max(n, 1)
    return {"commands": float(n), "sampling": sampling * ms, "cost": cost * ms,
            "rest of plan": (plan_s - sampling - cost) * ms, "command": command_s * ms, "episode harness": harness * ms}


def make_parser() -> ArgumentParser:
    p = ArgumentParser(prog="python -m eval.bench profile_split", description=__doc__.splitlines()[0])
    p.add_argument("profiles", nargs="+", help="cProfile output files (python -m cProfile -o FILE -m eval.navigate ...)")
    return p


@cli_main()
def main(argv: Sequence[str] | None = None) -> int:
    args = make_parser().parse_args(argv)
    rows = [(str(p), split(p)) for p in args.profiles]
    parts = ["sampling", "cost", "rest of plan", "command", "episode harness"]
    print("| profile | commands | " + " | ".join(f"{p} (ms)" for p in parts) + " |")
    print("|---|---:|" + "---:|" * len(parts))
    for name, row in rows:
        print(f"| {name} | {int(row['commands'])} | " + " | ".join(f"{row[p]:.3f}" for p in parts) + " |")
    return 0


refuse_old_spelling(__name__, "profile_split")  # run as the old module command: one line naming the new spelling, exit 2
