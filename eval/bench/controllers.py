"""Per-command time of the MPPI family, side by side with pytorch_mppi, and bare rollout times.

    python -m eval.bench controllers             # K in {500, 1000, 10000}, T = 15 and the table's T
    python -m eval.bench controllers --samples 1000 --repeats 50 --json out/bench.json

Every controller runs on the same Dubins dynamics and the same cost (squared distance to a goal summed over the
horizon), from the same state; each figure is the median of ``--repeats`` timed commands after ``--warmup``
untimed ones (on CUDA, synchronized). pytorch_mppi (``pip install pytorch-mppi``, the ``[bench]`` extra) is
timed in the same run when installed; ratios are ours / theirs. The bare-rollout section times a C-Uniform
table rollout against a Gaussian one at N = 10000, T = 15, on the same Dubins dynamics, both eager, calls
interleaved (table, Gaussian, table, ...) so that load on a shared machine hits both alike: from the origin
(the benchmark figure; the proposal bank rolls out from there too) and from a pose away from it (adds the
change of frame), and with ``--compile`` the compiled table kernel. ``--threads 1`` gives steadier CPU
timings on a loaded machine; ``--rollout-only`` skips the per-command section.
Writes JSON to ``--json`` (default out/bench.json).
"""

from __future__ import annotations

import os
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import torch

from cuniform_torch import CUMPPI, MPPI, CUniformMPPI, Dubins, LogMPPI, load_table, rollout, write_table
from cuniform_torch.common.fileio import write_json
from cuniform_torch.policies.table import Kernel
from cuniform_torch.sampling import GaussianSampler
from eval.common.paths import DEFAULT
from precompute.cli import (
    MAX_COUNT,
    ArgumentParser,
    check_output_file,
    cli_main,
    device_arg,
    horizon_arg,
    int_in,
    non_negative_int,
    positive_int,
    refuse_flags,
    threads_arg,
)


def _timer(fn: Callable[[], object], repeats: int, warmup: int, device: torch.device) -> float:
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    for _ in range(warmup):
        fn()
    sync()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        sync()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def _interleaved(fns: dict[str, Callable[[], object]], repeats: int, warmup: int,
                 device: torch.device) -> dict[str, float]:
    """Median seconds of each function, calls interleaved round by round (fair under a varying machine load)."""
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    for _ in range(warmup):
        for fn in fns.values():
            fn()
    sync()
    times: dict[str, list[float]] = {name: [] for name in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            t0 = time.perf_counter()
            fn()
            sync()
            times[name].append(time.perf_counter() - t0)
    return {name: statistics.median(ts) for name, ts in times.items()}


def _table(path: Path, horizon: int):
    """The default Dubins table with at least ``horizon`` steps (built in about a second when missing)."""
    if not path.exists():
        from precompute.flow.builder import BuildConfig, build_table

        print(f"building {path} (dubins, horizon {horizon})", flush=True)
        table, _ = build_table(Dubins(), BuildConfig(horizon=horizon))
        write_table(path, table)
    return path


def make_parser() -> ArgumentParser:
    p = ArgumentParser(prog="python -m eval.bench controllers", description=__doc__.split("\n\n")[0])
    p.add_argument("--samples", type=int_in(2, MAX_COUNT), nargs="+", default=[500, 1000, 10000],
                   help="K, samples per command (each >= 2: CU-MPPI splits it in two)")
    p.add_argument("--horizons", type=horizon_arg, nargs="+", default=[15, 10], help="15 and the default table's 10")
    p.add_argument("--table15", type=Path, default=DEFAULT.bench_table(15), help="a horizon-15 Dubins table")
    p.add_argument("--table", type=Path, default=DEFAULT.table,
                   help="the default (horizon-10) table, read when --horizons has 10 (not with --rollout-only)")
    p.add_argument("--repeats", type=positive_int, default=20)
    p.add_argument("--warmup", type=non_negative_int, default=3)
    p.add_argument("--device", type=device_arg, default="cpu")
    p.add_argument("--compile", action="store_true", help="also time the compiled table kernel (slow to compile)")
    p.add_argument("--threads", type=threads_arg, default=0, help="torch CPU threads (default 0: torch's choice)")
    p.add_argument("--rollout-only", action="store_true", help="only the bare-rollout section")
    p.add_argument("--rollout-repeats", type=positive_int, default=None,
                   help="repeats of the bare rollouts (default: --repeats)")
    p.add_argument("--json", type=Path, default=DEFAULT.bench_json)
    return p


@cli_main()
def main(argv=None) -> int:
    p = make_parser()
    args = p.parse_args(argv)
    if args.rollout_only:
        refuse_flags(p, args, ["samples", "horizons", "table"], "with --rollout-only (only the horizon-15 table's "
                                                                "bare rollouts are timed)")
    elif 10 not in args.horizons:
        refuse_flags(p, args, ["table"], f"without 10 in --horizons (the horizon-10 table; --horizons "
                                         f"{' '.join(map(str, args.horizons))})")
    device = torch.device(args.device)
    if args.threads:
        torch.set_num_threads(args.threads)
    check_output_file(args.json, "--json", example="bench.json")
    try:
        import pytorch_mppi  # noqa: F401
        have_peer = True
    except ImportError:
        have_peer = False
        print("pytorch_mppi is not installed (pip install pytorch-mppi): peer columns skipped")

    system = Dubins()
    goal = torch.tensor([3.0, 1.0], device=device)

    def cost(states, actions):  # [K, T+1, d] -> [K]
        return ((states[:, 1:, :2] - goal) ** 2).sum(dim=(1, 2))

    def running_cost(state, action):  # pytorch_mppi: [K, d] -> [K]
        return ((state[:, :2] - goal) ** 2).sum(dim=1)

    state = torch.tensor([0.0, 0.0, 0.3], device=device)
    wanted = [args.table15] + ([args.table] if not args.rollout_only and 10 in args.horizons else [])
    for path in wanted:  # every table there read before any build or timing: a bad --table is refused at once (a
        if os.path.lexists(path):  # FIFO --table was read after the horizon-15 table's build and rows: 19 s, 635 MB)
            load_table(path, device=device)
    tables = {15: _table(args.table15, 15)}
    if not args.rollout_only and 10 in args.horizons:
        tables[10] = _table(args.table, 10)
    rows = []
    header = f"{'T':>3} {'K':>6} {'MPPI':>8} {'logMPPI':>8} {'CU-MPPI':>8} {'CU bank':>8} {'CUMPPI':>8}"
    if not args.rollout_only:
        print(f"per-command time (ms), median of {args.repeats}, device {device}, torch threads {torch.get_num_threads()}")
        print(header + (f" {'peer':>8} {'MPPI/peer':>10}" if have_peer else ""))
    for T in [] if args.rollout_only else args.horizons:
        if T not in tables:
            tables[T] = _table(DEFAULT.bench_table(T), T)
        policy = load_table(tables[T], device=device)
        for K in args.samples:
            ctrls = {
                "mppi": MPPI(system, cost, K, T, noise_std=0.3, device=device, seed=0),
                "log_mppi": LogMPPI(system, cost, K, T, noise_std=0.3, device=device, seed=0),
                "cuniform": CUniformMPPI(policy, cost, K, horizon=T, seed=0),
                "cuniform_bank": CUniformMPPI(policy, cost, K, horizon=T, bank_size=2 * K, seed=0),
                "cumppi": CUMPPI(policy, cost, K, horizon=T, seed=0),
            }
            ms = {name: 1e3 * _timer(lambda c=c: c.command(state), args.repeats, args.warmup, device)
                  for name, c in ctrls.items()}
            line = f"{T:>3} {K:>6} " + " ".join(f"{ms[n]:>8.2f}" for n in ctrls)
            if have_peer:
                from pytorch_mppi import MPPI as PeerMPPI

                peer = PeerMPPI(system.step, running_cost, 3, noise_sigma=torch.eye(1, device=device) * 0.3**2,
                                num_samples=K, horizon=T, device=device, lambda_=0.567,
                                u_min=torch.tensor([-system.max_omega], device=device),
                                u_max=torch.tensor([system.max_omega], device=device))
                ms["pytorch_mppi"] = 1e3 * _timer(lambda peer=peer: peer.command(state), args.repeats, args.warmup, device)
                line += f" {ms['pytorch_mppi']:>8.2f} {ms['mppi'] / ms['pytorch_mppi']:>10.2f}"
            print(line, flush=True)
            rows.append({"horizon": T, "samples": K, "ms_per_command": ms})

    # bare rollouts: C-Uniform table vs Gaussian noise, N = 10000, T = 15
    N, T = 10000, 15
    policy = load_table(tables[15], device=device)
    gauss = GaussianSampler(torch.zeros(T, 1, device=device), 0.3, -torch.full((1,), system.max_omega, device=device),
                            torch.full((1,), system.max_omega, device=device))
    gen = torch.Generator(device=device).manual_seed(0)
    x0 = torch.zeros(3, device=device)
    pose = torch.tensor([1.0, -2.0, 0.7], device=device)
    reps = args.rollout_repeats or args.repeats
    fns = {
        "table": lambda: rollout(system, policy, x0, N, T, gen),
        "gaussian": lambda: rollout(system, gauss, x0, N, T, gen),
        "table_from_pose": lambda: rollout(system, policy, pose, N, T, gen),
    }
    if policy.kernel is not Kernel.TORCH:  # the torch kernel too: what a GPU, float64 or a machine without numba runs
        torch_kernel = load_table(tables[15], device=device, kernel="torch")
        fns["table_torch_kernel"] = lambda: rollout(system, torch_kernel, x0, N, T, gen)
    bare = _interleaved(fns, reps, args.warmup, device)
    if args.compile:
        compiled = load_table(tables[15], device=device, compile=True)
        t0 = time.perf_counter()
        rollout(system, compiled, x0, N, T, gen)
        bare["compile_seconds"] = time.perf_counter() - t0
        timed = _interleaved({"table_compiled": lambda: rollout(system, compiled, x0, N, T, gen),
                              "gaussian": lambda: rollout(system, gauss, x0, N, T, gen)}, reps, args.warmup, device)
        bare["table_compiled"] = timed["table_compiled"]
        bare["gaussian_beside_compiled"] = timed["gaussian"]
    ratios = {name: bare[name] / bare["gaussian"] for name in fns if name != "gaussian"}
    if args.compile:
        ratios["table_compiled"] = bare["table_compiled"] / bare["gaussian_beside_compiled"]
    print(f"bare rollouts (median of {reps}, interleaved), device {device}, torch threads {torch.get_num_threads()}")
    print(f"bare rollout N={N} T={T}: table ({policy.kernel.value} kernel) {1e3 * bare['table']:.2f} ms, "
          f"gaussian {1e3 * bare['gaussian']:.2f} ms, ratio {ratios['table']:.2f}x"
          + (f"; compiled table {1e3 * bare['table_compiled']:.2f} ms ({ratios['table_compiled']:.2f}x, "
             f"compiled in {bare['compile_seconds']:.1f} s)" if args.compile else ""))
    print(f"bare rollout from pose {pose.tolist()} (adds the change of frame): table "
          f"{1e3 * bare['table_from_pose']:.2f} ms, ratio {ratios['table_from_pose']:.2f}x")
    if "table_torch_kernel" in bare:
        print(f"bare rollout N={N} T={T} with the torch kernel: table {1e3 * bare['table_torch_kernel']:.2f} ms, "
              f"ratio {ratios['table_torch_kernel']:.2f}x")
    write_json(args.json, {"device": str(device), "threads": torch.get_num_threads(), "repeats": args.repeats,
                           "commands": rows, "bare_rollout_seconds": bare, "bare_rollout_ratios": ratios,
                           "torch": torch.__version__})
    print(f"wrote {args.json}")
    return 0
