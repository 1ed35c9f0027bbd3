"""Per-command time of the whole MPPI family on the navigation robot, side by side, for one robot or a batch.

    python -m eval.bench family                                  # K = 64, 256, 1024; T = 15; one robot
    python -m eval.bench family --robots 64 --samples 256        # a batch of 64 robots per command
    python -m eval.bench family --device cuda --samples 1024 8192 --horizon 15 100

Every controller drives the navigation benchmark's robot (Dubins, 0.5 m/s, 7 turn rates, dt 0.2 s) on BARN map 0
(the shipped half) under the navigation cost, from the map's start (robot ``b`` a little further along x): MPPI
(std 1.0), log-MPPI (std 0.3), MPPI with pink and with low-pass noise (std 1.0; ``mppi_pink``, ``mppi_lowpass``),
smooth MPPI (rate std 2.0; ``smppi``) and kernel MPPI (7 control points, std 1.0; ``kmppi``), C-Uniform MPPI on
the robot's max-flow table, CU-MPPI on it (and in one pass, ``cumppi_pipe``), the mixture of half C-Uniform
table and half MPPI std 1.0 rollouts (``mix_cu_mppi``), CFU-MPPI with the
shipped map policy, and pytorch_mppi (the ``[bench]`` extra; ``MPPI_Batched`` for a batch) on the same dynamics
with a per-step goal-and-collision cost. Commands are timed round-robin (one command of each controller in turn,
``--repeats`` rounds after ``--warmup``), so a varying load on a shared machine hits all alike; each figure is a
median (on CUDA, synchronized). Ratios are to MPPI at the same K.

The script uses only the one-robot API when ``--robots 1``, so the same file times an older checkout too:
``cd OLD && PYTHONPATH=. python /path/to/eval/bench/family.py ...`` (before / after in one table).
Writes JSON to ``--json`` (default out/bench_family.json).
"""

from __future__ import annotations

import os
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import torch

from cuniform_torch.common.fileio import write_json
from eval.bench.cli import refuse_old_spelling
from precompute.cli import (
    ArgumentParser,
    check_output_file,
    cli_main,
    device_arg,
    horizon_arg,
    non_negative_int,
    positive_int,
    threads_arg,
)

METHODS = ("mppi", "log_mppi", "mppi_pink", "mppi_lowpass", "smppi", "kmppi", "cuniform", "cumppi", "cumppi_pipe",
           "mix_cu_mppi", "cfu_mppi", "pytorch_mppi")


def make_parser() -> ArgumentParser:
    p = ArgumentParser(prog="python -m eval.bench family", description=(__doc__ or "").split("\n\n")[0])
    p.add_argument("--samples", type=positive_int, nargs="+", default=[64, 256, 1024], help="K per robot")
    p.add_argument("--horizon", type=horizon_arg, nargs="+", default=[15],
                   help="T (the table and the map policy serve up to 15)")
    p.add_argument("--robots", type=positive_int, default=1, help="B robots per command (default 1)")
    p.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS)
    p.add_argument("--repeats", type=positive_int, default=30)
    p.add_argument("--warmup", type=non_negative_int, default=5)
    p.add_argument("--threads", type=threads_arg, default=1, help="torch CPU threads (default 1: steadier on a "
                                                                   "shared machine; 0: torch's choice)")
    p.add_argument("--device", type=device_arg, default="cpu")
    p.add_argument("--clock", choices=("wall", "thread"), default="wall",
                   help="wall: elapsed time (default); thread: this thread's CPU time (CPU only), which leaves out "
                        "the time other processes hold the core: steadier on a loaded shared machine")
    p.add_argument("--stat", choices=("median", "min"), default="median",
                   help="each figure is the median of the rounds (default), or their minimum: the least disturbed "
                        "round, the steadier figure when other jobs share the machine")
    p.add_argument("--cuda-graph", action="store_true",
                   help="also time each controller with cuda_graph=True (a command is one graph replay)")
    p.add_argument("--cost", choices=("navigation", "goal"), default="navigation",
                   help="navigation: goal distance and collisions with the map's cylinders (default); goal: the "
                        "squared goal distance only (the simple cost of GPU bars such as MPPI-Generic's)")
    p.add_argument("--table-kernel", choices=("auto", "torch", "numba", "triton"), default="auto",
                   help="the table policy's kernel (TablePolicy's kernel=): auto picks numba on a CPU and the fused "
                        "Triton rollout on CUDA; torch runs the tensor ops (default auto)")
    p.add_argument("--cache", type=Path, default=Path("out/nav-cache"),
                   help="where the robot's table is built once and cached")
    p.add_argument("--json", type=Path, default=Path("out/bench_family.json"))
    return p


def _batch_kw(robots: int) -> dict:
    """``num_robots`` only when batching (an older checkout has no such argument)."""
    return {} if robots == 1 else {"num_robots": robots}


def build(args) -> tuple[dict[tuple[str, int, int], Callable[[], object]], dict]:
    """One ``command`` closure per (method, K, T), all on the same map, cost and states."""
    from cuniform_torch import CFUMPPI, CUMPPI, MPPI, CUniformMPPI, LogMPPI, TablePolicy, read_table
    from cuniform_torch.controllers import ColoredMPPI, CUniformMixtureMPPI, KernelMPPI, LowPassMPPI, SmoothMPPI
    from cuniform_torch.envs import NavigationCost
    from eval.navigate.robot_files import ensure_table
    from precompute.worlds.barn import load_barn
    from precompute.worlds.robot import NAV_ROBOT

    device = torch.device(args.device)
    system = NAV_ROBOT.make_system()
    world = load_barn()[0]
    env = world.environment(NAV_ROBOT.radius)
    cost = NavigationCost(env, world.goal)
    if args.cost == "goal":
        goal_xy = torch.tensor(world.goal, dtype=torch.float32, device=device)

        def cost(states: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:  # [N, T+1, d] -> [N]
            return (states[:, 1:, :2] - goal_xy).square().sum(dim=(1, 2))
    b = args.robots
    start = torch.tensor(world.start, dtype=torch.float32, device=device)
    states = start.repeat(b, 1)
    states[:, 0] += 0.05 * torch.arange(b, device=device)
    state = states[0] if b == 1 else states
    needs_table = {"cuniform", "cumppi", "cumppi_pipe", "mix_cu_mppi"} & set(args.methods)
    table = None
    if needs_table and min(args.horizon) <= NAV_ROBOT.horizon:
        table = TablePolicy(read_table(ensure_table(NAV_ROBOT, Path(args.cache))), device=device,
                            **({} if args.table_kernel == "auto" else {"kernel": args.table_kernel}))
    kw = _batch_kw(b)
    fns: dict[tuple[str, int, int], Callable[[], object]] = {}
    def make(name: str, k: int, t: int):
        """The controller ``name`` at K = ``k``, T = ``t`` (None where it cannot serve that horizon); a name
        ending in ``+graph`` is the controller with ``cuda_graph=True``."""
        if name.endswith("+graph"):
            return make_with(name[:-len("+graph")], k, t, dict(kw, cuda_graph=True))
        return make_with(name, k, t, kw)

    def make_with(name: str, k: int, t: int, kw: dict):
        if name == "mppi":
            return MPPI(system, cost, k, t, noise_std=1.0, device=device, seed=0, **kw)
        if name == "log_mppi":
            return LogMPPI(system, cost, k, t, noise_std=0.3, device=device, seed=0, **kw)
        if name == "mppi_pink":
            return ColoredMPPI(system, cost, k, t, noise_std=1.0, beta=1.0, device=device, seed=0, **kw)
        if name == "mppi_lowpass":
            return LowPassMPPI(system, cost, k, t, noise_std=1.0, a=0.8, device=device, seed=0, **kw)
        if name == "smppi":
            return SmoothMPPI(system, cost, k, t, noise_std=2.0, device=device, seed=0, **kw)
        if name == "kmppi":
            return KernelMPPI(system, cost, k, t, noise_std=1.0, device=device, seed=0, **kw)
        if t > NAV_ROBOT.horizon:
            return None
        if name == "cuniform" and table is not None:
            return CUniformMPPI(table, cost, k, horizon=t, seed=0, **kw)
        if name == "cumppi" and table is not None:
            return CUMPPI(table, cost, k, horizon=t, seed=0, **kw)
        if name == "cumppi_pipe" and table is not None:
            return CUMPPI(table, cost, k, horizon=t, seed=0, pipelined=True, **kw)
        if name == "mix_cu_mppi" and table is not None:
            return CUniformMixtureMPPI(table, cost, k, cuniform_fraction=0.5, noise_std=1.0, horizon=t, seed=0, **kw)
        if name == "cfu_mppi":
            return CFUMPPI("unicycle-0.5", env, cost, k, horizon=t, device=device, seed=0, **kw)
        return None

    names = list(args.methods) + ([f"{m}+graph" for m in args.methods if m != "pytorch_mppi"]
                                  if args.cuda_graph else [])
    for t in args.horizon:
        for k in args.samples:
            for name in names:
                try:
                    ctrl = (_peer(system, env, world.goal, k, t, b, device) if name == "pytorch_mppi"
                            else make(name, k, t))
                    if ctrl is not None:
                        ctrl.command(state)  # fails here, not in the timed rounds
                except Exception as exc:  # a benchmark reports what it could not time and goes on
                    print(f"{name} at K = {k}, T = {t}: not timed ({type(exc).__name__}: {exc})"[:300])
                    continue
                if ctrl is not None:
                    fns[(name, k, t)] = lambda ctrl=ctrl: ctrl.command(state)
    info = {"map": int(world.map_id), "robots": b, "device": str(device), "threads": torch.get_num_threads(),
            "cost": args.cost, "table_kernel": None if table is None else table.kernel.value}
    return fns, info


def _peer(system, env, goal, k: int, t: int, robots: int, device: torch.device):
    """pytorch_mppi on the same dynamics (None when it is not installed): ``MPPI``, or ``MPPI_Batched`` for a batch."""
    try:
        import pytorch_mppi
    except ImportError:
        return None
    goal_t = torch.tensor(goal, dtype=torch.float32, device=device)

    def running_cost(x, u, *_):  # [N, d] -> [N]: goal distance and a collision penalty per state
        hit = env.in_collision(x[:, None, :2], None)[:, 0]
        return (x[:, :2] - goal_t).square().sum(dim=1) + 1e3 * hit.to(x.dtype)

    common = dict(noise_sigma=torch.eye(1, device=device), num_samples=k, horizon=t, device=device, lambda_=0.567,
                  u_min=torch.tensor([-1.5], device=device), u_max=torch.tensor([1.5], device=device))
    if robots == 1:
        return pytorch_mppi.MPPI(system.step, running_cost, 3, **common)
    return pytorch_mppi.MPPI_Batched(system.step, running_cost, 3, num_envs=robots, **common)


def time_round_robin(fns: dict, repeats: int, warmup: int, device: torch.device, clock: str = "wall",
                     stat: str = "median") -> dict:
    """Median (``stat="min"``: least) seconds of each closure, one call of each in turn per round
    (``clock="thread"``: CPU seconds of this thread)."""
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    now = time.thread_time if clock == "thread" else time.perf_counter
    for _ in range(warmup):
        for fn in fns.values():
            fn()
    sync()
    times: dict = {key: [] for key in fns}
    for _ in range(repeats):
        for key, fn in fns.items():
            t0 = now()
            fn()
            sync()
            times[key].append(now() - t0)
    pick = min if stat == "min" else statistics.median
    return {key: pick(v) for key, v in times.items()}


@cli_main()
def main(argv: list[str] | None = None) -> int:
    parser = make_parser()
    args = parser.parse_args(argv)
    check_output_file(args.json, "--json", example="bench_family.json")
    if args.clock == "thread" and torch.device(args.device).type != "cpu":
        parser.error(f"--clock thread times a CPU thread; on {args.device} a command waits for the device: use "
                     f"--clock wall")
    if args.threads:
        torch.set_num_threads(args.threads)
    fns, info = build(args)
    medians = time_round_robin(fns, args.repeats, args.warmup, torch.device(args.device), args.clock, args.stat)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    what = "per-command ms" if args.clock == "wall" else "per-command CPU ms (thread clock)"
    print(f"# {what}, {'least' if args.stat == 'min' else 'median'} of {args.repeats} round-robin rounds; "
          f"{info['robots']} robot(s) per command, "
          f"{args.device}, {info['threads']} thread(s), BARN map {info['map']}, {args.cost} cost, load {load:.2f}"
          + (f", table kernel {info['table_kernel']}" if info.get("table_kernel") else ""))
    names = list(dict.fromkeys(key[0] for key in medians))
    print(f"{'T':>4} {'K':>6} " + " ".join(f"{m:>13}" for m in names))
    rows = []
    for t in args.horizon:
        for k in args.samples:
            base = medians.get(("mppi", k, t))
            cells = []
            for m in names:
                s = medians.get((m, k, t))
                if s is None:
                    cells.append(f"{'-':>13}")
                    continue
                ratio = f"({s / base:.2f}x)" if base else ""
                cells.append(f"{1e3 * s:>6.3f}{ratio:>7}")
                rows.append({"method": m, "samples": k, "horizon": t, "ms": 1e3 * s,
                             "ratio_to_mppi": s / base if base else None})
            print(f"{t:>4} {k:>6} " + " ".join(cells))
    write_json(args.json, {**info, "load": load, "repeats": args.repeats, "clock": args.clock, "stat": args.stat,
                           "rows": rows})
    print(f"wrote {args.json}")
    return 0


refuse_old_spelling(__name__, "family")  # run as the old module command: one line naming the new spelling, exit 2
