"""CU-MPPI's first stage, whole plan against lean, in one process: per-command CPU time side by side.

    python -m eval.bench first_stage                       # K = 64, 256, 1024; T = 15; 300 rounds

Two CU-MPPI controllers of the same seed drive the family benchmark's robot on BARN map 0 (its start, the
navigation cost, the robot's max-flow table): one as it is (the first stage proposes, costs, takes the argmin and
gathers the best sequence: ``CUniformMPPI._best_actions``), one whose first stage runs the whole plan it ran
before (weights, the weighted sequence, a result, then ``best_actions()``), and MPPI (std 1.0) beside them. One
command of each in turn per round, timed by this thread's CPU clock (the time other processes hold the core left
out), so the two paths meet the same machine, load and caches; the least and the median of the rounds are
printed, and the least as a ratio to MPPI's. A separate-process before / after (``eval.bench.family`` on two checkouts) cannot resolve a few percent
on a shared machine: each process's own layout moves a figure by about as much. Both controllers command the
same (checked).

    python -m eval.bench.first_stage --parts               # where a command's time goes, MPPI beside CU-MPPI

``--parts`` times the pieces of one command instead, the same way (round-robin, thread clock, least of the rounds):
MPPI's proposals (``propose_batch``, K) and their weighing (``_evaluate``: the cost call, the weights); CU-MPPI's
first stage (its C-Uniform rollouts, K1 = K / 2; their cost call; the whole lean stage, ``_best_actions``) and its
second (the local proposals, K2 = K - K1; their ``_evaluate``); and CFU-MPPI's command, its sensing (crop and
encode the patch), its first stage's map-policy rollouts (sensing included) and their cost call, in a second
table from rounds of their own. The floor of a two-stage command is the sum of its
two stages: the second cannot start before the first stage's argmin, so the two cost calls cannot be one.
"""

from __future__ import annotations

import os
import statistics
import sys
import time
import types
from pathlib import Path

import torch

from eval.bench.cli import refuse_old_spelling
from precompute.cli import ArgumentParser, cli_main, non_negative_int, positive_int


def make_parser() -> ArgumentParser:
    p = ArgumentParser(prog="python -m eval.bench first_stage", description=(__doc__ or "").split("\n\n")[0])
    p.add_argument("--samples", type=positive_int, nargs="+", default=[64, 256, 1024], help="K (both stages)")
    p.add_argument("--repeats", type=positive_int, default=300)
    p.add_argument("--warmup", type=non_negative_int, default=30)
    p.add_argument("--parts", action="store_true",
                   help="time the parts of a command (proposals, cost calls, stages) instead of whole commands")
    p.add_argument("--cache", type=Path, default=Path("out/nav-cache"),
                   help="where the robot's table is built once and cached")
    return p


def _whole_plan(self, states: torch.Tensor, streams) -> tuple[torch.Tensor, torch.Tensor]:
    """``CompositeProposal.propose_batch`` as it was: the first stage's whole plan, then its best sequence."""
    self.local.seed(self.first._plan(states).best_actions())
    return self.local.propose_batch(states, streams)


@cli_main()
def main(argv: list[str] | None = None) -> int:
    args = make_parser().parse_args(argv)
    torch.set_num_threads(1)
    from cuniform_torch import CUMPPI, MPPI, TablePolicy, read_table
    from cuniform_torch.envs import NavigationCost
    from eval.navigate.robot_files import ensure_table
    from precompute.worlds.barn import load_barn
    from precompute.worlds.robot import NAV_ROBOT

    world = load_barn()[0]
    cost = NavigationCost(world.environment(NAV_ROBOT.radius), world.goal)
    state = torch.tensor(world.start, dtype=torch.float32)
    table = TablePolicy(read_table(ensure_table(NAV_ROBOT, Path(args.cache))))
    if args.parts:
        return _parts(args, table, cost, state)
    print(f"# per-command CPU ms (thread clock), least / median of {args.repeats} round-robin rounds, 1 thread, "
          f"BARN map 0, navigation cost")
    print(f"{'K':>6} {'mppi':>15} {'cumppi whole':>23} {'cumppi lean':>23} {'lean / whole':>13}")
    for k in args.samples:
        whole, lean = CUMPPI(table, cost, k, seed=0), CUMPPI(table, cost, k, seed=0)
        whole.proposal.propose_batch = types.MethodType(_whole_plan, whole.proposal)  # type: ignore[method-assign, union-attr]
        mppi = MPPI(NAV_ROBOT.make_system(), cost, k, table.horizon, noise_std=1.0, seed=0)
        fns = {"mppi": mppi.command, "whole": whole.command, "lean": lean.command}
        times: dict[str, list[float]] = {name: [] for name in fns}
        for r in range(args.warmup + args.repeats):
            for name, fn in fns.items():
                t0 = time.thread_time()
                fn(state)
                if r >= args.warmup:
                    times[name].append(time.thread_time() - t0)
        if not torch.equal(whole.command(state), lean.command(state)):
            print(f"K = {k}: the two paths commanded differently", file=sys.stderr)
            return 1
        base = min(times["mppi"])
        cells = [f"{1e3 * min(v):6.3f} / {1e3 * statistics.median(v):5.3f}"
                 + ("" if name == "mppi" else f" ({min(v) / base:.2f}x)") for name, v in times.items()]
        ratio = min(times["lean"]) / min(times["whole"])
        print(f"{k:>6} {cells[0]:>15} {cells[1]:>23} {cells[2]:>23} {ratio:>12.2f}x")
    print(f"load {os.getloadavg()[0]:.2f}")
    return 0


def _round_robin(fns: dict, warmup: int, repeats: int) -> dict[str, float]:
    """The least CPU seconds (thread clock) of each closure, one call of each in turn per round."""
    times: dict[str, list[float]] = {name: [] for name in fns}
    for r in range(warmup + repeats):
        for name, fn in fns.items():
            t0 = time.thread_time()
            fn()
            if r >= warmup:
                times[name].append(time.thread_time() - t0)
    return {name: min(v) for name, v in times.items()}


_CFU_PARTS = ("cfu command", "cfu sense", "cfu stage 1 rollouts", "cfu stage 1 cost")
"""CFU-MPPI's parts that ``--parts`` times too: a command, its sensing (the patch cropped and encoded by the map
policy's CNN: ``CFUMPPI.sense``), its first stage's map-policy rollouts (K1 = K / 2; the stage senses first, so
this includes the sensing) and their cost call"""

_PARTS = ("mppi command", "mppi proposals", "mppi evaluate", "cumppi command", "stage 1 rollouts", "stage 1 cost",
          "stage 1", "stage 2 proposals", "stage 2 evaluate")
"""what ``--parts`` times (module docstring)"""


def _part_fns(k: int, table, cost, state: torch.Tensor) -> dict:
    """One closure per part of :data:`_PARTS` at K = ``k``: an MPPI and a CU-MPPI command and their pieces (the
    costed ones on proposals drawn once)."""
    from cuniform_torch import CUMPPI, MPPI
    from precompute.worlds.robot import NAV_ROBOT

    states = state.unsqueeze(0)  # [1, d]: the batched calls' one robot
    mppi = MPPI(NAV_ROBOT.make_system(), cost, k, table.horizon, noise_std=1.0, seed=0)
    cu = CUMPPI(table, cost, k, seed=0)
    first, local = cu.cuniform, cu.local
    m_x, m_u = mppi._batch.propose_batch(states, mppi.streams)
    c_x, c_u = first._batch.propose_batch(states, first.streams)
    l_x, l_u = local.propose_batch(states, cu.streams)
    return {"mppi command": lambda: mppi.command(state),
            "mppi proposals": lambda: mppi._batch.propose_batch(states, mppi.streams),
            "mppi evaluate": lambda: mppi._evaluate(m_x, m_u),
            "cumppi command": lambda: cu.command(state),
            "stage 1 rollouts": lambda: first._batch.propose_batch(states, first.streams),
            "stage 1 cost": lambda: first._state_costs(c_x, c_u),
            "stage 1": lambda: first._best_actions(states),
            "stage 2 proposals": lambda: local.propose_batch(states, cu.streams),
            "stage 2 evaluate": lambda: cu._evaluate(l_x, l_u)}


def _cfu_fns(k: int, cost, state: torch.Tensor) -> dict:
    """One closure per part of :data:`_CFU_PARTS` at K = ``k``: the shipped map policy on ``cost.env`` (a
    NavigationCost's), as ``eval.bench.family`` runs it."""
    from cuniform_torch import CFUMPPI
    from precompute.worlds.robot import NAV_ROBOT

    states = state.unsqueeze(0)  # [1, d]
    cfu = CFUMPPI("unicycle-0.5", cost.env, cost, k, horizon=NAV_ROBOT.horizon, seed=0)
    first = cfu.cuniform
    cfu.sense(states)  # the map the rollouts read
    f_x, f_u = first._batch.propose_batch(states, first.streams)
    return {"cfu command": lambda: cfu.command(state),
            "cfu sense": lambda: cfu.sense(states),
            "cfu stage 1 rollouts": lambda: first._batch.propose_batch(states, first.streams),
            "cfu stage 1 cost": lambda: first._state_costs(f_x, f_u)}


def _parts(args, table, cost, state: torch.Tensor) -> int:
    """``--parts``: per K, the least CPU ms of each part of an MPPI and a CU-MPPI command (module docstring)."""
    print(f"# per-command-part CPU ms (thread clock), least of {args.repeats} round-robin rounds, 1 thread, "
          f"BARN map 0, navigation cost")
    print(f"{'K':>6} " + " ".join(f"{n:>17}" for n in _PARTS) + f" {'two stages / mppi':>18}")
    cfu_rows: list[str] = []
    for k in args.samples:
        fns = _part_fns(k, table, cost, state)
        least = _round_robin(fns, args.warmup, args.repeats)
        # CFU-MPPI in rounds of its own (with MPPI for the ratio): its network and patch would push the others' data
        # out of the cache between their calls
        cfu = _round_robin(_cfu_fns(k, cost, state) | {"mppi command": fns["mppi command"]}, args.warmup, args.repeats)
        ratio = (least["stage 1"] + least["stage 2 proposals"] + least["stage 2 evaluate"]) / least["mppi command"]
        print(f"{k:>6} " + " ".join(f"{1e3 * least[n]:>17.3f}" for n in _PARTS) + f" {ratio:>17.2f}x")
        cfu_rows.append(f"{k:>6} " + " ".join(f"{1e3 * cfu[n]:>20.3f}" for n in (*_CFU_PARTS, "mppi command"))
                        + f" {cfu['cfu command'] / cfu['mppi command']:>17.2f}x")
    print(f"# CFU-MPPI's parts, rounds of their own with MPPI's command\n{'K':>6} "
          + " ".join(f"{n:>20}" for n in (*_CFU_PARTS, "mppi command")) + f" {'cfu / mppi':>18}")
    print("\n".join(cfu_rows))
    print(f"load {os.getloadavg()[0]:.2f}")
    return 0


refuse_old_spelling(__name__, "first_stage")  # run as the old module command: one line naming the new spelling, exit 2
