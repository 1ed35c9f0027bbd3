"""Per-command time of CFU-MPPI against MPPI, side by side:  python -m training.maps.timing [--checkpoint FILE]

The benchmark robot (``precompute.worlds.robot.NAV_ROBOT``: Dubins at 0.5 m/s, dt 0.2 s, 7 turn rates in [-1.5, 1.5]
rad/s, horizon 15) drives through a seeded random forest (a 20 m x 20 m OccupancyGrid of 0.05 m cells) towards
a goal. Per K three controllers take turns, one command each, so that they share the machine's load: MPPI, and
CFU-MPPI twice (each command senses the 72 x 72 patch of 0.05 m around the pose, encodes it once, rolls out the
map policy for half of K and runs the local Gaussian pass with the other half), once with the map policy's
compiled rollout (:mod:`cuniform_torch.maps.kernels`, what a CPU runs) and once step by step (the rollout's
generic loop, what it ran before). Without ``--checkpoint`` the policy is untrained, of the shipped policy's sizes
(the same arithmetic: a timing, not a plan). Printed: sensing and encoding alone, then per K the median command
time of each, the ratios to MPPI, and the map policy's rollout of K / 2 alone (compiled and step by step); the
policy's parameter count, torch's thread count and the load average.
"""

from __future__ import annotations

import math
import os
import statistics
import sys
import time
from collections.abc import Sequence

import torch

from cuniform_torch.controllers.cfu import CFUMPPI
from cuniform_torch.controllers.mppi import MPPI
from cuniform_torch.envs import OccupancyGrid
from cuniform_torch.maps.checkpoint import load_map_policy
from cuniform_torch.maps.encoder import PatchSpec
from cuniform_torch.maps.policy import MapPolicy, MapPolicyConfig
from cuniform_torch.maps.sensing import local_map
from cuniform_torch.sampling.rollout import rollout
from cuniform_torch.systems import make_system
from precompute.cli import (
    MAX_COUNT,
    ArgumentParser,
    check_output_file,
    cli_main,
    int_in,
    non_negative_int,
    positive_int,
    refuse_flags,
    threads_arg,
)

ROBOT = dict(speed=0.5, dt=0.2, max_omega=1.5, num_actions=7, cell_size=[0.05, 0.05, 2 * math.pi / 36])
HORIZON = 15


def forest(seed: int, size: float = 20.0, resolution: float = 0.05, discs: int = 300) -> OccupancyGrid:
    """A seeded grid of random discs (radius 0.1-0.3 m), clear within 1 m of the origin."""
    gen = torch.Generator().manual_seed(seed)
    n = int(size / resolution)
    centres = (torch.rand(discs, 2, generator=gen) - 0.5) * size  # [D, 2]
    radii = 0.1 + 0.2 * torch.rand(discs, generator=gen)  # [D]
    keep = centres.norm(dim=1) > 1.0 + radii
    axis = -size / 2 + (torch.arange(n) + 0.5) * resolution
    xy = torch.stack((axis.expand(n, n), axis.unsqueeze(1).expand(n, n)), dim=-1)  # [n, n, 2]
    occ = torch.zeros(n, n, dtype=torch.bool)
    for c, r in zip(centres[keep], radii[keep]):  # building the world once, not the timed path
        occ |= (xy - c).norm(dim=-1) <= r
    return OccupancyGrid(occ, (-size / 2, -size / 2), resolution)


def make_cost(world: OccupancyGrid, goal: tuple[float, float]):
    def cost(states: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        hit = world.contains(states[:, 1:, :2]).any(dim=1)  # [K]
        g = torch.tensor(goal, dtype=states.dtype, device=states.device)
        return (states[:, 1:, :2] - g).square().sum(dim=-1).sum(dim=1) + 1e4 * hit
    return cost


def untrained_policy(system, spec: PatchSpec, hidden: int, layers: int, embed: int, channels: int,
                     local_features: int = 0) -> MapPolicy:
    torch.manual_seed(0)
    reach = ROBOT["speed"] * ROBOT["dt"] * HORIZON
    config = MapPolicyConfig(state_dim=3, num_actions=ROBOT["num_actions"], horizon=HORIZON,
                             periodic=[False, False, True], feature_scale=[reach, reach, 1.0], patch=spec.to_dict(),
                             hidden=hidden, layers=layers, embed=embed, channels=channels,
                             local_features=local_features)
    return MapPolicy(config, system, system.action_set()).eval()


def time_side_by_side(controllers: dict[str, tuple[object, object]], system, commands: int,
                      warmup: int) -> dict[str, list[float]]:
    """Command times (ms) of each named ``(controller, before)`` pair, taking turns one command at a time
    (``before()``, when not None, runs untimed before each command: the policy's path switch)."""
    poses = {name: torch.zeros(3) for name in controllers}
    times: dict[str, list[float]] = {name: [] for name in controllers}
    for k in range(warmup + commands):
        for name, (controller, before) in controllers.items():
            if before is not None:
                before()
            x = poses[name]
            start = time.perf_counter()
            u = controller.command(x)
            elapsed = time.perf_counter() - start
            if not bool(torch.isfinite(u).all()):
                raise ValueError(f"{name}: command {k} is not finite: {u.tolist()}")
            if k >= warmup:
                times[name].append(elapsed * 1e3)
            poses[name] = system.step(x.unsqueeze(0), u.unsqueeze(0))[0]
    return times


def _repeat(fn, warmup: int, commands: int) -> list[float]:
    """Times (ms) of ``commands`` calls of ``fn`` after ``warmup`` untimed ones."""
    out = []
    for k in range(warmup + commands):
        start = time.perf_counter()
        fn()
        if k >= warmup:
            out.append((time.perf_counter() - start) * 1e3)
    return out


def _stats(ms: list[float]) -> str:
    ordered = sorted(ms)
    return f"median {statistics.median(ms):6.2f} ms, p90 {ordered[int(0.9 * (len(ms) - 1))]:6.2f} ms"


SIZES = ("hidden", "layers", "embed", "channels", "local_features")
"""the untrained policy's sizes: flags that a --checkpoint (which has its own) refuses"""


def make_parser() -> ArgumentParser:
    parser = ArgumentParser(prog="python -m training.maps.timing", description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int_in(2, MAX_COUNT), nargs="+", default=[16, 64, 256, 1024],
                        help="budgets K to time (each >= 2)")
    parser.add_argument("--commands", type=positive_int, default=60, help="timed commands per K (after the warm-up)")
    parser.add_argument("--warmup", type=non_negative_int, default=5)
    parser.add_argument("--checkpoint", default=None, help="a trained map policy (default: an untrained one)")
    for name, default in zip(SIZES, (64, 2, 32, 8, 4)):  # the shipped policy's (training.maps.pretrained)
        parser.add_argument(f"--{name.replace('_', '-')}", type=int_in(0 if name == "local_features" else 1, 65536),
                            default=default,
                            help=f"of the untrained policy (default {default}; not with --checkpoint)")
    parser.add_argument("--threads", type=threads_arg, default=1, help="torch CPU threads (0: torch's choice)")
    parser.add_argument("--seed", type=int_in(0, 2**31 - 1), default=0, help="seed of the forest")
    parser.add_argument("--json", default=None, help="also write the numbers here")
    return parser


@cli_main()
def main(argv: Sequence[str] | None = None) -> int:
    parser = make_parser()
    args = parser.parse_args(argv)
    if args.json:
        check_output_file(args.json, "--json", "timing.json")
    if args.checkpoint is not None:
        refuse_flags(parser, args, SIZES, "with --checkpoint (the checkpoint has its own sizes)")
    if args.threads:
        torch.set_num_threads(args.threads)
    system = make_system("dubins", **ROBOT)
    spec = PatchSpec((72, 72), 0.05, (-1.8, -1.8))
    policy = (load_map_policy(args.checkpoint) if args.checkpoint else
              untrained_policy(system, spec, args.hidden, args.layers, args.embed, args.channels,
                               args.local_features))
    world = forest(args.seed)
    cost = make_cost(world, (8.0, 0.0))
    print(f"map policy: {policy.num_parameters:,} parameters (encoder {sum(p.numel() for p in policy.encoder.parameters()):,}),"
          f" patch {list(policy.patch_spec.shape)} at {policy.patch_spec.resolution} m; torch threads "
          f"{torch.get_num_threads()}; load {os.getloadavg()[0]:.2f}")
    pose = torch.tensor([0.3, 0.1, 0.2])
    patch = local_map(world, pose, policy.patch_spec)
    sense = _repeat(lambda: local_map(world, pose, policy.patch_spec), args.warmup, args.commands)
    encode = _repeat(lambda: policy.set_map(patch), args.warmup, args.commands)
    print(f"sensing the patch: {_stats(sense)}; encoding it (set_map): {_stats(encode)}")
    results = {"parameters": policy.num_parameters, "sense_ms": statistics.median(sense),
               "encode_ms": statistics.median(encode), "commands": {}}
    print(f"{'K':>6} {'MPPI':>9} {'CFU-MPPI':>9} {'ratio':>6} {'CFU step-by-step':>17} {'ratio':>6} "
          f"{'its rollout':>12} {'step-by-step':>13}  (median ms per command; rollout: the map policy's K/2, "
          f"horizon {HORIZON})")
    for k in args.samples:
        mppi = MPPI(system, cost, num_samples=k, horizon=HORIZON, seed=0)
        cfu = CFUMPPI(policy, world, cost, num_samples=k, seed=0)
        stepwise = CFUMPPI(policy, world, cost, num_samples=k, seed=0)
        times = time_side_by_side({"mppi": (mppi, None), "cfu": (cfu, lambda: setattr(policy, "compiled", True)),
                                   "stepwise": (stepwise, lambda: setattr(policy, "compiled", False))},
                                  system, args.commands, args.warmup)
        policy.compiled = True
        med = {name: statistics.median(ms) for name, ms in times.items()}
        roll, half = {}, max(1, k // 2)
        for compiled in (True, False):  # the first stage alone, from the patch set above
            policy.compiled = compiled
            policy.set_map(patch)
            gen = torch.Generator().manual_seed(0)
            roll[compiled] = statistics.median(_repeat(lambda n=half, g=gen: rollout(
                system, policy, pose, n, HORIZON, g), args.warmup, args.commands))
        policy.compiled = True
        results["commands"][k] = {"median_ms": med["cfu"], "all_ms": times["cfu"], "mppi_median_ms": med["mppi"],
                                  "step_by_step_median_ms": med["stepwise"], "rollout_ms": roll[True],
                                  "rollout_step_by_step_ms": roll[False]}
        print(f"{k:6d} {med['mppi']:9.2f} {med['cfu']:9.2f} {med['cfu'] / med['mppi']:5.1f}x "
              f"{med['stepwise']:17.2f} {med['stepwise'] / med['mppi']:5.1f}x {roll[True]:12.2f} {roll[False]:13.2f}")
    print(f"load after: {os.getloadavg()[0]:.2f}")
    if args.json:
        from cuniform_torch.common.fileio import write_json
        write_json(args.json, results)
    return 0


if __name__ == "__main__":
    sys.exit(main())
