"""Many robots in one call: 32 pendulums swung up by one batched MPPI, by 32 MPPI controllers in a loop, and by
pytorch_mppi's ``MPPI_Batched``, side by side.

    python -m eval.bench pendulum                      # 32 pendulums, K = 100, T = 15, 200 steps
    python -m eval.bench pendulum --robots 64 --steps 100

The pendulum of pytorch_mppi's own example (gym's Pendulum-v1 dynamics: g = 10, m = l = 1, dt = 0.05, torque in
[-2, 2], speed clipped to [-8, 8]; per-step cost ``angle^2 + 0.1 speed^2`` of the next state), noise covariance
10 (std sqrt(10)), lambda 1. The robots start from seeded random states (the same for every method); each
method's return is gym's reward summed over the steps (``-(angle^2 + 0.1 speed^2 + 0.001 u^2)``), averaged
over the robots. Wall seconds are for the whole closed loop (planning and stepping), one torch thread by default.
"""

from __future__ import annotations

import dataclasses
import math
import os
import time
from pathlib import Path

import torch

from cuniform_torch.common.fileio import write_json
from eval.bench.cli import refuse_old_spelling
from precompute.cli import (
    ArgumentParser,
    check_output_file,
    cli_main,
    horizon_arg,
    non_negative_int,
    positive_int,
    threads_arg,
)

G, MASS, LENGTH, DT, MAX_SPEED, MAX_TORQUE = 10.0, 1.0, 1.0, 0.05, 8.0, 2.0


def angle_normalize(x: torch.Tensor) -> torch.Tensor:
    return ((x + math.pi) % (2 * math.pi)) - math.pi


def pendulum_dynamics(state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
    """pytorch_mppi's example dynamics: ``state [N, 2]`` (angle, speed), ``action [N, 1]`` -> ``[N, 2]``."""
    th, thdot = state[:, 0], state[:, 1]
    u = torch.clamp(action[:, 0], -MAX_TORQUE, MAX_TORQUE)
    newthdot = thdot + (-3 * G / (2 * LENGTH) * torch.sin(th + math.pi) + 3.0 / (MASS * LENGTH**2) * u) * DT
    newthdot = torch.clamp(newthdot, -MAX_SPEED, MAX_SPEED)
    return torch.stack((th + newthdot * DT, newthdot), dim=1)


def running_cost(state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
    """pytorch_mppi's example cost of one step: ``[N, 2]`` -> ``[N]``."""
    return angle_normalize(state[:, 0]) ** 2 + 0.1 * state[:, 1] ** 2


def trajectory_cost(states: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
    """The same cost summed over a rollout's next states: ``[N, T+1, 2]`` -> ``[N]``."""
    nxt = states[:, 1:]
    return (angle_normalize(nxt[..., 0]) ** 2 + 0.1 * nxt[..., 1] ** 2).sum(dim=1)


@dataclasses.dataclass(frozen=True)
class Pendulum:
    """The pendulum as a System of this library (what the MPPI core reads: the dynamics and the action bounds)."""

    name = "pendulum"
    periodic = (True, False)
    se2_invariant = False
    cell_size: tuple = (2 * math.pi / 64, 0.25)
    dt: float = DT
    cell_offset: tuple = (0.0, 0.0)

    def action_set(self, dtype: torch.dtype = torch.float32, device: torch.device | str | None = None) -> torch.Tensor:
        return torch.linspace(-MAX_TORQUE, MAX_TORQUE, 9, dtype=dtype, device=device).unsqueeze(1)  # [A, 1]

    def step(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        return pendulum_dynamics(x, u)

    def params(self) -> dict:
        return {}


def reward(state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
    """gym's Pendulum-v1 reward of taking ``action`` at ``state``: ``[N]``."""
    u = torch.clamp(action[:, 0], -MAX_TORQUE, MAX_TORQUE)
    return -(angle_normalize(state[:, 0]) ** 2 + 0.1 * state[:, 1] ** 2 + 0.001 * u**2)


def table_set(horizon: int, angles: int, speeds: int):
    """A C-Uniform table set for the pendulum, built in memory: one max-flow table per start on an
    ``angles x speeds`` grid (angle over a turn, speed in [-4, 4]); each robot's member is the nearest start."""
    from cuniform_torch import TablePolicy, register_system
    from cuniform_torch.policies.table_set import TableSetPolicy
    from precompute.flow.builder import BuildConfig, build_table

    register_system("pendulum", Pendulum)  # a table names its system; this one is made here

    grid = [(2 * math.pi * i / angles - math.pi, -4.0 + 8.0 * j / max(speeds - 1, 1))
            for i in range(angles) for j in range(speeds)]
    members = [TablePolicy(build_table(Pendulum(), BuildConfig(horizon=horizon, start=start))[0]) for start in grid]
    return TableSetPolicy(members, torch.tensor(grid, dtype=torch.float64))


def run(method: str, starts: torch.Tensor, args, tables=None) -> tuple[float, float]:
    """Seconds of the closed loop and the mean return of ``method`` from ``starts [B, 2]``."""
    from cuniform_torch import MPPI, CUniformMPPI

    b = starts.shape[0]
    std = math.sqrt(10.0)
    kw = dict(num_samples=args.samples, horizon=args.horizon, lambda_=1.0, noise_std=std)
    if method == "cuniform_batched":
        ctrl = CUniformMPPI(tables, trajectory_cost, num_samples=args.samples, lambda_=1.0, seed=list(range(b)),
                            num_robots=b)
        policy = ctrl.command
    elif method == "cuniform_loop":
        cus = [CUniformMPPI(tables, trajectory_cost, num_samples=args.samples, lambda_=1.0, seed=i)
               for i in range(b)]

        def policy(x: torch.Tensor) -> torch.Tensor:
            return torch.stack([c.command(x[i]) for i, c in enumerate(cus)])
    elif method == "batched":
        ctrl = MPPI(Pendulum(), trajectory_cost, seed=list(range(b)), num_robots=b, **kw)
        policy = ctrl.command
    elif method == "loop":
        ctrls = [MPPI(Pendulum(), trajectory_cost, seed=i, **kw) for i in range(b)]

        def policy(x: torch.Tensor) -> torch.Tensor:
            return torch.stack([c.command(x[i]) for i, c in enumerate(ctrls)])
    else:
        import pytorch_mppi

        torch.manual_seed(0)
        peer = pytorch_mppi.MPPI_Batched(pendulum_dynamics, running_cost, 2, noise_sigma=torch.eye(1) * 10.0,
                                         num_envs=b, num_samples=args.samples, horizon=args.horizon, lambda_=1.0,
                                         u_min=torch.tensor([-MAX_TORQUE]), u_max=torch.tensor([MAX_TORQUE]))
        policy = peer.command
    x = starts.clone()
    total = torch.zeros(b)
    t0 = time.perf_counter()
    for _ in range(args.steps):
        u = policy(x).reshape(b, 1)
        total += reward(x, u)
        x = pendulum_dynamics(x, u)
    return time.perf_counter() - t0, float(total.mean())


def make_parser() -> ArgumentParser:
    p = ArgumentParser(prog="python -m eval.bench pendulum", description=(__doc__ or "").split("\n\n")[0])
    p.add_argument("--robots", type=positive_int, default=32)
    p.add_argument("--samples", type=positive_int, default=100, help="K per robot")
    p.add_argument("--horizon", type=horizon_arg, default=15)
    p.add_argument("--steps", type=positive_int, default=200)
    p.add_argument("--seed", type=non_negative_int, default=0, help="of the starts")
    p.add_argument("--threads", type=threads_arg, default=1, help="torch CPU threads (0: torch's choice)")
    p.add_argument("--cuniform", type=positive_int, nargs=2, metavar=("ANGLES", "SPEEDS"), default=None,
                   help="also C-Uniform MPPI, batched and in a loop, on a table set of ANGLES x SPEEDS starts "
                        "(built in memory first: about half a second a table)")
    p.add_argument("--json", type=Path, default=Path("out/bench_pendulum.json"))
    return p


@cli_main()
def main(argv: list[str] | None = None) -> int:
    args = make_parser().parse_args(argv)
    check_output_file(args.json, "--json", example="bench_pendulum.json")
    if args.threads:
        torch.set_num_threads(args.threads)
    g = torch.Generator().manual_seed(args.seed)
    starts = torch.stack((torch.rand(args.robots, generator=g) * 2 * math.pi - math.pi,
                          torch.rand(args.robots, generator=g) * 2 - 1), dim=1)
    methods = ["batched", "loop"]
    try:
        import pytorch_mppi  # noqa: F401
        methods.append("pytorch_mppi")
    except ImportError:
        print("pytorch_mppi is not installed (pip install pytorch-mppi, the [bench] extra): its row is skipped")
    rows = {}
    print(f"{args.robots} pendulums, K = {args.samples}, T = {args.horizon}, {args.steps} steps, "
          f"{torch.get_num_threads()} thread(s), load {os.getloadavg()[0]:.2f}")
    print(f"{'method':<34} {'wall s':>8} {'mean return':>12}")
    labels = {"batched": "MPPI, one batched controller", "loop": f"MPPI, {args.robots} controllers in a loop",
              "pytorch_mppi": "pytorch_mppi MPPI_Batched", "cuniform_batched": "C-Uniform MPPI, batched",
              "cuniform_loop": f"C-Uniform MPPI, {args.robots} in a loop"}
    tables = None
    if args.cuniform is not None:
        t0 = time.perf_counter()
        tables = table_set(args.horizon, *args.cuniform)
        print(f"(a table set of {len(tables.members)} members built in {time.perf_counter() - t0:.1f} s)")
        methods += ["cuniform_batched", "cuniform_loop"]
    for m in methods:
        seconds, ret = run(m, starts, args, tables)
        rows[m] = {"seconds": seconds, "mean_return": ret}
        print(f"{labels[m]:<34} {seconds:>8.2f} {ret:>12.1f}")
    if "loop" in rows:
        print(f"batched vs loop: {rows['loop']['seconds'] / rows['batched']['seconds']:.1f}x faster")
    if "cuniform_loop" in rows:
        print(f"C-Uniform batched vs loop: "
              f"{rows['cuniform_loop']['seconds'] / rows['cuniform_batched']['seconds']:.1f}x faster")
    if "pytorch_mppi" in rows:
        print(f"batched vs MPPI_Batched: {rows['pytorch_mppi']['seconds'] / rows['batched']['seconds']:.1f}x faster")
    write_json(args.json, {"robots": args.robots, "samples": args.samples, "horizon": args.horizon,
                           "steps": args.steps, "rows": rows})
    return 0


refuse_old_spelling(__name__, "pendulum")  # run as the old module command: one line naming the new spelling, exit 2
