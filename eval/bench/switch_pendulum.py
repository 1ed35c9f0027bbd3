"""A pytorch_mppi user switches by changing the import line: the same pendulum script run with pytorch_mppi and with
``cuniform_torch.pytorch_mppi``, the returns of each seed side by side.

    python -m eval.bench switch_pendulum                 # seeds 0 1 2, 200 steps each
    python -m eval.bench switch_pendulum --defaults      # also this library's MPPI with its defaults (below)

The script is :mod:`eval.bench.pendulum_user_pytorch_mppi`; its twin :mod:`eval.bench.pendulum_user_cuniform` differs
by the import line only (printed first, as a unified diff). Each episode starts hanging down (angle pi, speed 1);
its return is gym's Pendulum-v1 reward summed over the steps (0 is upright and still throughout). Both seed their
run with ``torch.manual_seed(seed)`` (the drop-in draws its stream's seed from torch's generator), so the two
columns share seeds, not random numbers: they agree within the spread across seeds, not to the digit.

``--defaults`` adds ``cuniform_torch.MPPI(dynamics, nx=2, running_cost=..., u_min=-2, u_max=2, lambda_="auto")``:
no noise given (a quarter of the action range: std 1) and the temperature chosen per command for an effective
sample size of K / 10, what a user gets for a new system without tuning.
"""

from __future__ import annotations

import difflib
import os
import statistics
import time
from pathlib import Path

import torch

from cuniform_torch.common.fileio import write_json
from eval.bench.cli import refuse_old_spelling
from precompute.cli import ArgumentParser, check_output_file, cli_main, non_negative_int, positive_int

HERE = Path(__file__).parent
SCRIPTS = {"pytorch_mppi": "pendulum_user_pytorch_mppi", "cuniform": "pendulum_user_cuniform"}


def script_diff() -> str:
    """The unified diff of the two user scripts."""
    a, b = (HERE / f"{SCRIPTS[k]}.py" for k in ("pytorch_mppi", "cuniform"))
    return "".join(difflib.unified_diff(a.read_text().splitlines(True), b.read_text().splitlines(True),
                                        a.name, b.name, n=0))


def run_defaults(seed: int, steps: int) -> float:
    """The same episode with this library's MPPI and its defaults (noise from the bounds, automatic temperature)."""
    import numpy as np

    from cuniform_torch import MPPI
    from eval.bench import pendulum_user_cuniform as user

    env = user.Pendulum([np.pi, 1.0])
    mppi = MPPI(user.dynamics, nx=2, running_cost=user.running_cost, u_min=-2.0, u_max=2.0, lambda_="auto",
                num_samples=user.N_SAMPLES, horizon=user.TIMESTEPS, seed=seed)
    total = 0.0
    for _ in range(steps):
        _, reward = env.step(mppi.command(env.state.copy()))  # a numpy state: a numpy command back
        total += reward
    return total


def make_parser() -> ArgumentParser:
    p = ArgumentParser(prog="python -m eval.bench switch_pendulum", description=(__doc__ or "").split("\n\n")[0])
    p.add_argument("--seed", dest="seeds", type=non_negative_int, nargs="+", default=[0, 1, 2],
                   help="the seeds, one run of each script per seed (default 0 1 2)")
    p.add_argument("--steps", type=positive_int, default=200)
    p.add_argument("--defaults", action="store_true", help="also this library's MPPI with its defaults")
    p.add_argument("--threads", type=positive_int, default=1, help="torch CPU threads")
    p.add_argument("--json", type=Path, default=Path("out/switch_pendulum.json"))
    return p


@cli_main()
def main(argv: list[str] | None = None) -> int:
    args = make_parser().parse_args(argv)
    check_output_file(args.json, "--json", example="switch_pendulum.json")
    torch.set_num_threads(args.threads)
    import importlib

    runs = {}
    for name, module in SCRIPTS.items():
        try:
            runs[name] = importlib.import_module(f"eval.bench.{module}").run
        except ImportError as exc:  # pytorch_mppi is the [bench] extra
            print(f"{module} needs pytorch_mppi ({exc}; pip install pytorch-mppi, the [bench] extra): its column is "
                  f"skipped")
    if args.defaults:
        runs["cuniform_defaults"] = run_defaults
    print(script_diff())
    print(f"{args.steps} steps, {torch.get_num_threads()} thread(s), load {os.getloadavg()[0]:.2f}")
    print(f"{'seed':>4} " + " ".join(f"{name:>18}" for name in runs))
    rows: dict[str, list[float]] = {name: [] for name in runs}
    seconds: dict[str, float] = dict.fromkeys(runs, 0.0)
    for seed in args.seeds:
        for name, run in runs.items():
            t0 = time.perf_counter()
            rows[name].append(float(run(seed, args.steps)))
            seconds[name] += time.perf_counter() - t0
        print(f"{seed:>4} " + " ".join(f"{rows[name][-1]:>18.1f}" for name in runs))
    spread = {name: statistics.stdev(v) if len(v) > 1 else 0.0 for name, v in rows.items()}
    print("mean " + " ".join(f"{statistics.fmean(rows[n]):>11.1f} +- {spread[n]:>4.1f}" for n in runs))
    print("s/cmd" + " ".join(f"{seconds[n] / (len(args.seeds) * args.steps) * 1e3:>15.2f} ms" for n in runs))
    write_json(args.json, {"steps": args.steps, "seeds": args.seeds, "returns": rows,
                           "ms_per_command": {n: seconds[n] / (len(args.seeds) * args.steps) * 1e3 for n in runs}})
    return 0


refuse_old_spelling(__name__, "switch_pendulum")  # run as the old module command: one line naming the new spelling, exit 2
