"""The pendulum from one call: C-Uniform chosen for the user (:mod:`training.auto`) against MPPI, and how honest
the start-conditioned MLP is between the set's starts.

    python -m eval.auto_pendulum                      # build (or reuse), 3 seeds of returns, 20 off-grid starts

The pendulum of pytorch_mppi's example (:mod:`eval.bench.pendulum`: gym's Pendulum-v1, dt 0.05 s, torque in
[-2, 2], speed clipped to [-8, 8], cost ``angle^2 + 0.1 speed^2`` of the next states, return = gym's reward summed
over the steps). :class:`Pendulum` is that system written for the chooser: a dataclass with ``cell_size`` and
``num_actions`` fields (the chooser sets both), the angle declared periodic and wrapped by ``step``.

1. **Build.** ``auto_cuniform(Pendulum(), "0=-pi:pi 1=-8:8", horizon=15)``: the report of what was chosen and
   why, and the times (a fresh ``--out`` builds everything; a rerun reuses it).
2. **Returns.** K = 100, T = 15, 200 steps, lambda 1, for ``--seeds`` seeds: from [pi, 1] (hanging down, one
   robot) and from ``--robots`` random starts (angle uniform in [-pi, pi), speed in [-1, 1], drawn per seed):
   MPPI (noise std sqrt(10), as pytorch_mppi's example), C-Uniform MPPI on the MLP and on the table set, CU-MPPI
   on the MLP (noise std 1). Seeds are the controllers' (and the random starts').
3. **Honesty off the grid.** ``--honesty`` random starts in the region, none in a member's start cell; at each an
   exact table is built from that start; ``--rollouts`` rollouts from it of the MLP, of the table set (its
   nearest member), of the exact table and of uniform actions are histogrammed per level over the exact table's
   level set L_t: TV from uniform (mass off L_t counted), its noise floor (N uniform draws over L_t), the share off
   L_t, and each policy's uniform-fallback (miss) rate, averaged over levels 1..T.

``--json`` writes every number.
"""

from __future__ import annotations

import copy
import dataclasses
import importlib
import math
import os
import sys
import time
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from cuniform_torch.common.fileio import write_json
from cuniform_torch.controllers.mppi import MPPI
from cuniform_torch.grid.cells import Grid
from cuniform_torch.metrics import level_uniformity, noise_floor
from cuniform_torch.policies.table import TablePolicy, UniformPolicy
from cuniform_torch.sampling.rollout import StartMismatchWarning, rollout
from eval.bench.pendulum import pendulum_dynamics, reward, trajectory_cost
from precompute.cli import OUT, ArgumentParser, check_output_file, cli_main, int_in, positive_int
from precompute.flow.builder import BuildConfig, build_table

__all__ = ["Pendulum", "REGION", "closed_loop", "honesty", "main"]

REGION = "0=-3.141592653589793:3.141592653589793 1=-8:8"
"""the starts the pendulum's controller meets: every angle, every speed up to the clip"""


@dataclasses.dataclass(frozen=True)
class Pendulum:
    """gym's Pendulum-v1 as a System the chooser can tune: state (angle, speed), angle 0 upright."""

    cell_size: tuple = (2 * math.pi / 64, 0.25)
    """(rad, rad/s); the chooser replaces it"""
    cell_offset: tuple = (0.0, 0.0)
    """grid offset in cells"""
    num_actions: int = 9
    """torques evenly in [-2, 2] N m; the chooser replaces it"""
    dt: float = 0.05
    """time step (s)"""
    name = "auto_pendulum"
    periodic = (True, False)
    se2_invariant = False

    def action_set(self, dtype: torch.dtype = torch.float32, device: torch.device | str | None = None) -> torch.Tensor:
        """``[A, 1]`` torques."""
        return torch.linspace(-2.0, 2.0, self.num_actions, dtype=torch.float64).to(dtype=dtype, device=device).unsqueeze(1)

    def step(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """``x [N, 2]``, ``u [N, 1]`` -> ``[N, 2]``: gym's step with the angle wrapped to [-pi, pi)."""
        nxt = pendulum_dynamics(x, u)
        return torch.stack((torch.remainder(nxt[:, 0] + math.pi, 2 * math.pi) - math.pi, nxt[:, 1]), dim=1)

    def params(self) -> dict:
        return dataclasses.asdict(self)


def _random_starts(n: int, seed: int) -> torch.Tensor:
    """``[n, 2]`` the bench's random starts: angle uniform in [-pi, pi), speed in [-1, 1]."""
    g = torch.Generator().manual_seed(seed)
    return torch.stack((torch.rand(n, generator=g) * 2 * math.pi - math.pi, torch.rand(n, generator=g) * 2 - 1), 1)


def closed_loop(make, starts: torch.Tensor, steps: int) -> float:
    """Mean return over the robots ``starts [B, 2]`` of the controller ``make(num_robots)`` for ``steps`` steps."""
    b = starts.shape[0]
    ctrl = make(b)
    x, total = starts.clone(), torch.zeros(b)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", StartMismatchWarning)  # off-start rollouts are counted, not the point here
        for _ in range(steps):
            u = ctrl.command(x if b > 1 else x[0]).reshape(b, 1)
            total += reward(x, u)
            x = pendulum_dynamics(x, u)
    return float(total.mean())


def _level_stats(policy: Any, system: Any, table: Any, x0: torch.Tensor, n: int, seed: int) -> dict[str, float]:
    """Mean over levels 1..T of TV, share off L_t of ``n`` rollouts of ``policy`` from ``x0``; its miss rate."""
    grid = Grid.of(system)
    if hasattr(policy, "reset_counters"):
        policy.reset_counters()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", StartMismatchWarning)
        states, _ = rollout(system, policy, x0, n, table.horizon, torch.Generator().manual_seed(seed))
    tv, off = [], []
    for t in range(1, table.horizon + 1):
        ref = torch.from_numpy(table.cells[table.level(t)])
        stats = level_uniformity(grid.cells(states[:, t].double()), ref)
        tv.append(stats["tv"])
        off.append(stats["outside"])
    miss = float(policy.miss_rate) if hasattr(policy, "miss_rate") else 0.0
    return {"tv": float(np.mean(tv)), "outside": float(np.mean(off)), "miss": miss}


def honesty(auto: Any, count: int, rollouts: int, seed: int) -> list[dict[str, Any]]:
    """Per off-grid start (module docstring, 3.): the start, its distance (cells) to the nearest member, the noise
    floor, and per policy (``mlp``, ``set``, ``exact``, ``uniform``) its mean TV, share off L_t and miss rate."""
    choice, system = auto.choice, auto.choice.system
    grid = Grid.of(system)
    member_cells = {tuple(c) for c in grid.cells(torch.from_numpy(choice.starts)).tolist()}
    lo = torch.tensor(choice.region.lo, dtype=torch.float64)
    hi = torch.tensor(choice.region.hi, dtype=torch.float64)
    g = torch.Generator().manual_seed(seed)
    raw = copy.deepcopy(auto.mlp)
    raw.support = None  # its own answers wherever it is asked (inside its box), not uniform off its tables' cells
    rows: list[dict[str, Any]] = []
    while len(rows) < count:
        x0 = torch.zeros(len(system.periodic), dtype=torch.float64)
        x0[list(choice.region.dims)] = lo + (hi - lo) * torch.rand(len(lo), dtype=torch.float64, generator=g)
        if tuple(grid.cells(x0).tolist()) in member_cells:
            continue  # on the grid: the member there is this start's own table
        table, _ = build_table(system, BuildConfig(horizon=choice.horizon, start=tuple(x0.tolist())))
        exact = TablePolicy(table)
        _, dist = auto.table_set.nearest(x0)
        floors = [noise_floor(int(table.level_offsets[t + 1] - table.level_offsets[t]), rollouts, 5,
                              torch.Generator().manual_seed(seed + t))[0] for t in range(1, choice.horizon + 1)]
        x32 = x0.float()
        row: dict[str, Any] = {"start": x0.tolist(), "cells_to_member": float(dist), "cells": int(len(table.cells)),
                               "floor": float(np.mean(floors))}
        for name, pol in (("mlp", auto.mlp), ("mlp_raw", raw), ("set", auto.table_set), ("exact", exact),
                          ("uniform", UniformPolicy(system))):
            row[name] = _level_stats(pol, system, table, x32, rollouts, seed + len(rows))
        rows.append(row)
    return rows


def format_honesty(rows: list[dict[str, Any]], rollouts: int) -> str:
    names = ("mlp", "mlp_raw", "set", "exact", "uniform")
    lines = [f"off-grid starts: {rollouts} rollouts each, per level over the exact table's L_t, mean of levels 1..T",
             "   angle    speed  cells to member  floor |  TV mlp TV mlp* TV set TV exact TV unif |  off mlp off mlp*"
             "  off set | miss mlp miss set"]
    for r in rows:
        lines.append(f"{r['start'][0]:8.3f} {r['start'][1]:8.3f} {r['cells_to_member']:16.1f} {r['floor']:6.3f} | "
                     + " ".join(f"{r[n]['tv']:7.3f}" for n in names) + f" | {r['mlp']['outside']:8.3f} "
                     f"{r['mlp_raw']['outside']:8.3f} {r['set']['outside']:8.3f} | {r['mlp']['miss']:8.3f} "
                     f"{r['set']['miss']:8.3f}")
    mean = {n: np.mean([r[n]["tv"] for r in rows]) for n in names}
    lines.append(f"mean over {len(rows)} starts: floor {np.mean([r['floor'] for r in rows]):.3f}; TV "
                 + ", ".join(f"{n} {mean[n]:.3f}" for n in names)
                 + f"; off L_t: mlp {np.mean([r['mlp']['outside'] for r in rows]):.3f} (max "
                 f"{max(r['mlp']['outside'] for r in rows):.3f}), mlp* {np.mean([r['mlp_raw']['outside'] for r in rows]):.3f} (max "
                 f"{max(r['mlp_raw']['outside'] for r in rows):.3f}), set {np.mean([r['set']['outside'] for r in rows]):.3f} "
                 f"(max {max(r['set']['outside'] for r in rows):.3f}); miss: mlp "
                 f"{np.mean([r['mlp']['miss'] for r in rows]):.3f} (max {max(r['mlp']['miss'] for r in rows):.3f}), set "
                 f"{np.mean([r['set']['miss'] for r in rows]):.3f} (max {max(r['set']['miss'] for r in rows):.3f})")
    lines.append("(mlp: the start-conditioned MLP as deployed, uniform actions off its tables' cells (its misses); mlp*: "
                 "its own answers everywhere; set: the nearest member's table; floor: N uniform draws over L_t)")
    return "\n".join(lines)


def make_parser() -> ArgumentParser:
    p = ArgumentParser(prog="python -m eval.auto_pendulum", description=(__doc__ or "").splitlines()[0])
    p.add_argument("--out", type=Path, default=OUT / "auto", help="the cache folder of the chosen set and its MLP")
    p.add_argument("--workers", type=int_in(1, 64), default=2, help="processes building the tables")
    p.add_argument("--seeds", type=positive_int, default=3)
    p.add_argument("--robots", type=positive_int, default=8, help="random starts per seed")
    p.add_argument("--samples", type=positive_int, default=100, help="K")
    p.add_argument("--steps", type=positive_int, default=200)
    p.add_argument("--honesty", type=int_in(0, 1000), default=20, help="off-grid starts (0: skip)")
    p.add_argument("--rollouts", type=positive_int, default=1000, help="rollouts per off-grid start and policy")
    p.add_argument("--json", type=Path, default=OUT / "auto_pendulum.json")
    return p


@cli_main()
def main(argv: Sequence[str] | None = None) -> int:
    """Build, run, measure (module docstring): 0, or 2 after one ``error: ...`` line."""
    from training.auto import auto_cuniform

    args = make_parser().parse_args(argv)
    check_output_file(args.json, "--json", example="auto_pendulum.json")
    torch.set_num_threads(1)
    # run as python -m, this file is __main__: the worker processes import the class from its module path
    pendulum = importlib.import_module("eval.auto_pendulum").Pendulum
    t0 = time.perf_counter()
    auto = auto_cuniform(pendulum(), REGION, horizon=15, out=args.out, workers=args.workers, quiet=True)
    built = time.perf_counter() - t0
    print(auto.report())
    print(f"one call: {built:.1f} s (load {os.getloadavg()[0]:.2f})")
    K, T, std = args.samples, 15, math.sqrt(10.0)
    makers = {
        "MPPI": lambda s: lambda b: MPPI(auto.choice.system, trajectory_cost, num_samples=K, horizon=T, lambda_=1.0,
                                         noise_std=std, seed=[s + i for i in range(b)] if b > 1 else s, num_robots=b),
        "C-Uniform MPPI, MLP": lambda s: lambda b: auto.controller(
            trajectory_cost, K, lambda_=1.0, seed=[s + i for i in range(b)] if b > 1 else s, num_robots=b),
        "C-Uniform MPPI, table set": lambda s: lambda b: auto.controller(
            trajectory_cost, K, policy="set", lambda_=1.0, seed=[s + i for i in range(b)] if b > 1 else s,
            num_robots=b),
        "CU-MPPI, MLP": lambda s: lambda b: auto.controller(
            trajectory_cost, K, kind="cumppi", lambda_=1.0, noise_std=1.0,
            seed=[s + i for i in range(b)] if b > 1 else s, num_robots=b),
    }
    returns: dict[str, dict[str, list[float]]] = {m: {"down": [], "random": []} for m in makers}
    t1 = time.perf_counter()
    for seed in range(args.seeds):
        down = torch.tensor([[math.pi, 1.0]])
        rand = _random_starts(args.robots, 1000 + seed)
        for name, make in makers.items():
            returns[name]["down"].append(closed_loop(make(seed), down, args.steps))
            returns[name]["random"].append(closed_loop(make(seed), rand, args.steps))
    print(f"returns, K = {K}, T = {T}, {args.steps} steps, seeds 0..{args.seeds - 1} ({time.perf_counter() - t1:.0f} s, "
          f"load {os.getloadavg()[0]:.2f}):")
    print(f"{'method':<28} {'from [pi, 1], per seed':>30} {'mean':>8} | {'from ' + str(args.robots) + ' random starts':>30} "
          f"{'mean':>8}")
    for name, r in returns.items():
        print(f"{name:<28} {' '.join(f'{v:9.1f}' for v in r['down']):>30} {np.mean(r['down']):8.1f} | "
              f"{' '.join(f'{v:9.1f}' for v in r['random']):>30} {np.mean(r['random']):8.1f}")
    rows: list[dict[str, Any]] = []
    if args.honesty:
        t2 = time.perf_counter()
        rows = honesty(auto, args.honesty, args.rollouts, seed=7)
        print(format_honesty(rows, args.rollouts))
        print(f"({time.perf_counter() - t2:.0f} s, load {os.getloadavg()[0]:.2f})")
    write_json(args.json, {"choice": auto.choice.to_dict(), "seconds": {**auto.seconds, "one_call": built},
                           "returns": returns, "honesty": rows, "samples": K, "horizon": T, "steps": args.steps,
                           "robots": args.robots, "rollouts": args.rollouts})
    return 0


if __name__ == "__main__":
    sys.exit(main())
