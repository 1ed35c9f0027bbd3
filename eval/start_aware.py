"""How well a table set serves starts it was not built at: ``python -m eval.start_aware``.

A table set (``python -m precompute.build set --starts SPEC``) is read as one start-aware policy
(:class:`~cuniform_torch.policies.table_set.TableSetPolicy`: each rollout uses the table whose start is nearest). This
command draws random starts inside the set's start box (and, for an SE(2)-invariant system, random poses), builds
the table of each exact start, rolls both out N times from that start, and prints per start: the set's miss rate
(lookups that fell back), whether it warned, its real-rollout coverage (distinct cells reached) and the ratio to
the exact-start table's coverage. The targets it checks: miss rate < 5%, coverage within 10% of the exact table.

The set is built on first use into ``--cache`` (one folder per settings hash, resumable) unless ``--set DIR`` names
one: then the system, its parameters and the horizon are the set's (read from its tables; a user system's module
comes with ``--system-module``), and ``--system``, ``--param``, ``--horizon`` given too must agree with them. The
exact tables are built in this process (``precompute.flow.builder``). Every start is an episode of the set
(``new_episode``): its warning column says whether that start's rollout warned.
"""

from __future__ import annotations

import hashlib
import json
import math
import warnings
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from cuniform_torch import TablePolicy, load_table, rollout
from cuniform_torch.common.fileio import write_json
from cuniform_torch.metrics import coverage
from cuniform_torch.policies.table_set import TableSetPolicy
from cuniform_torch.sampling import StartMismatchWarning
from cuniform_torch.systems import System, make_system, resolve_system
from precompute import SetConfig, build_table_set
from precompute.cli import (
    MAX_COUNT,
    ArgumentParser,
    add_system_module_arg,
    check_output_file,
    cli_main,
    horizon_arg,
    import_system_modules,
    int_in,
    positive_int,
)
from precompute.flow.builder import BuildConfig, build_table
from precompute.system_args import parse_params
from precompute.table_set import parse_starts

__all__ = ["StartRow", "random_starts", "measure_start", "main"]

MISS_TARGET = 0.05
COVERAGE_TARGET = 0.9
POSE_RANGE = 5.0  # m: random poses of an SE(2)-invariant system are drawn in [-5, 5]^2 x [-pi, pi)


@dataclass
class StartRow:
    """One random start's measurement."""

    start: list[float]
    set_distance: float
    """cells from the start to the chosen table's start (over the dimensions that choose it)"""
    set_miss_rate: float
    """lookups that fell back to uniform actions"""
    set_nearest_rate: float
    """lookups answered by the nearest cell of the level (the state's cell was one cell off the level set)"""
    warned: bool
    set_coverage: int
    exact_coverage: int
    exact_miss_rate: float
    exact_nearest_rate: float

    @property
    def ratio(self) -> float:
        return self.set_coverage / self.exact_coverage if self.exact_coverage else float("nan")


def set_folder(cache: Path, system: str, params: dict[str, Any], horizon: int, spec: str) -> Path:
    """The cache folder of a set's settings."""
    blob = json.dumps(dict(system=system, params=params, horizon=horizon, starts=spec), sort_keys=True)
    return cache / f"{system}-h{horizon}-{hashlib.sha256(blob.encode()).hexdigest()[:12]}"


def random_starts(system: System, set_starts: np.ndarray, count: int, seed: int) -> np.ndarray:
    """``count`` starts ``[count, d]``: uniform in the set's start box over the dimensions the set varies, and a
    uniform pose (x, y in +-POSE_RANGE, theta in [-pi, pi)) for an SE(2)-invariant system; others 0."""
    rng = np.random.default_rng(seed)
    lo, hi = set_starts.min(axis=0), set_starts.max(axis=0)
    starts = rng.uniform(lo, hi, size=(count, len(lo)))
    if getattr(system, "se2_invariant", False):
        starts[:, :2] = rng.uniform(-POSE_RANGE, POSE_RANGE, size=(count, 2))
        starts[:, 2] = rng.uniform(-math.pi, math.pi, size=count)
    return starts


def measure_start(system: System, policy: TableSetPolicy, start: np.ndarray, horizon: int, samples: int,
                  seed: int) -> StartRow:
    """Roll the set and the exact-start table out ``samples`` times from ``start [d]``."""
    x0 = torch.tensor(start, dtype=policy.dtype)
    build_start = np.array(start, dtype=np.float64)
    if getattr(system, "se2_invariant", False):
        build_start[:3] = 0.0  # the exact table is built at the origin pose and moved by the frame change
    exact = TablePolicy(build_table(system, BuildConfig(horizon=horizon, start=tuple(build_start.tolist())))[0])
    policy.reset_counters()
    policy.new_episode()  # each start its own episode: it warns (or not) on its own, whatever came before
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", StartMismatchWarning)
        states, _ = rollout(system, policy, x0, samples, horizon, torch.Generator().manual_seed(seed))
    warned = any(issubclass(w.category, StartMismatchWarning) for w in caught)
    set_cov = coverage(states, policy.grid).total
    set_miss, set_nearest = policy.miss_rate, policy.nearest_rate
    exact.reset_counters()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", StartMismatchWarning)
        states, _ = rollout(system, exact, x0.to(exact.dtype), samples, horizon, torch.Generator().manual_seed(seed))
    return StartRow(start=[float(v) for v in start], set_distance=policy.last_start_distance, set_miss_rate=set_miss,
                    set_nearest_rate=set_nearest,
                    warned=warned, set_coverage=set_cov, exact_coverage=coverage(states, exact.grid).total,
                    exact_miss_rate=exact.miss_rate, exact_nearest_rate=exact.nearest_rate)


def summary(rows: list[StartRow]) -> dict[str, Any]:
    """Worst and mean miss rate and coverage ratio, and whether the targets hold."""
    miss = np.array([r.set_miss_rate for r in rows])
    near = np.array([r.set_nearest_rate for r in rows])
    ratio = np.array([r.ratio for r in rows])
    return dict(starts=len(rows), miss_max=float(miss.max()), miss_mean=float(miss.mean()),
                nearest_max=float(near.max()), nearest_mean=float(near.mean()),
                exact_nearest_mean=float(np.mean([r.exact_nearest_rate for r in rows])),
                ratio_min=float(ratio.min()), ratio_mean=float(ratio.mean()), warned=int(sum(r.warned for r in rows)),
                miss_ok=bool(miss.max() < MISS_TARGET), coverage_ok=bool(ratio.min() >= COVERAGE_TARGET))


def format_rows(rows: list[StartRow], dims: list[int]) -> str:
    """The per-start table, then the summary line."""
    head = "  ".join(f"x[{k}]".rjust(7) for k in dims)
    lines = [f"{head}  {'cells':>6}  {'miss':>6}  {'near':>6}  {'warn':>4}  {'cov set':>8}  {'cov exact':>9}  "
             f"{'ratio':>6}"]
    for r in rows:
        vals = "  ".join(f"{r.start[k]:7.3f}" for k in dims)
        warned = "yes" if r.warned else "no"
        lines.append(f"{vals}  {r.set_distance:6.2f}  {r.set_miss_rate:6.3f}  {r.set_nearest_rate:6.3f}  {warned:>4}  "
                     f"{r.set_coverage:8d}  {r.exact_coverage:9d}  {r.ratio:6.3f}")
    s = summary(rows)
    verdict = {True: "ok", False: "MISSED"}
    lines.append(f"{s['starts']} starts: set miss rate max {s['miss_max']:.3f} (mean {s['miss_mean']:.3f}, target "
                 f"< {MISS_TARGET}) {verdict[s['miss_ok']]}; nearest-cell answers max {s['nearest_max']:.3f} (mean "
                 f"{s['nearest_mean']:.3f}; the exact tables' mean {s['exact_nearest_mean']:.3f}); coverage / "
                 f"exact-start table min {s['ratio_min']:.3f} (mean {s['ratio_mean']:.3f}, target >= "
                 f"{COVERAGE_TARGET}) {verdict[s['coverage_ok']]}; {s['warned']} start(s) warned")
    return "\n".join(lines)


def make_parser() -> ArgumentParser:
    p = ArgumentParser(prog="python -m eval.start_aware", description=(__doc__ or "").split("\n\n")[0])
    p.add_argument("--system", default=None,
                   help="registered system (or module:factory); default ks_speed, or the --set's own")
    add_system_module_arg(p)
    p.add_argument("--param", action="append", default=[], metavar="KEY=VALUE", help="a system parameter")
    p.add_argument("--horizon", type=horizon_arg, default=None, help="steps (default 5, or the --set's own)")
    p.add_argument("--starts", default=None, metavar="SPEC",
                   help="the set's starts (precompute.build set --starts; default: ks_speed's speeds 0, 0.2, ..., 1, "
                        "one cell apart)")
    p.add_argument("--set", type=Path, default=None, metavar="DIR",
                   help="a built set to measure instead (its system and horizon are read from its tables)")
    p.add_argument("--random", type=positive_int, default=20, help="random starts to measure")
    p.add_argument("--seed", type=int_in(0, 2**31 - 1), default=0, help="seed of the random starts and the rollouts")
    p.add_argument("--samples", type=int_in(2, MAX_COUNT), default=1000, help="rollouts per start and policy")
    p.add_argument("--workers", type=int_in(1, 1024), default=1, help="processes for building the set")
    p.add_argument("--cache", type=Path, default=Path("out/start_aware"), help="where built sets are kept")
    p.add_argument("--json", type=Path, default=None, help="write the rows and the summary here")
    p.add_argument("--quiet", action="store_true")
    return p


def _check(args) -> None:
    for name, low in (("horizon", 1), ("random", 1), ("samples", 2), ("workers", 1)):
        if getattr(args, name) is not None and getattr(args, name) < low:
            raise ValueError(f"--{name} must be >= {low}, got {getattr(args, name)}")
    if args.json is not None:
        check_output_file(args.json, "--json")
    if args.set is not None and args.starts is not None:
        raise ValueError("give --set DIR (a built set) or --starts SPEC (a set to build), not both")


def _load_set(folder: Path) -> TableSetPolicy:
    """The set in ``folder``; a clear error when it is none."""
    if not folder.is_dir():
        raise ValueError(f"--set {folder}: no such folder (a table set is a folder with tables.json)")
    policy = load_table(folder)
    if not isinstance(policy, TableSetPolicy):
        raise ValueError(f"--set {folder} is one table, not a table set (a folder with tables.json)")
    return policy


def _set_system(args, policy: TableSetPolicy) -> tuple[str, dict[str, Any], System, int]:
    """The name, parameters, system and horizon of a built set (its tables'), checked against the flags given."""
    system = policy.system
    name = system.name
    params = json.loads(json.dumps(system.params(), default=list)) if callable(getattr(system, "params", None)) else {}
    if args.system is not None and resolve_system(args.system) != name:
        raise ValueError(f"--set {args.set} holds a {name} set, but --system says {args.system}; leave --system out "
                         f"(the set's system is used)")
    asked = parse_params(args.param)
    differ = {k: v for k, v in asked.items() if k not in params or params[k] != json.loads(json.dumps(v, default=list))}
    if differ:
        raise ValueError(f"--set {args.set}: its {name} tables were built with {params}; --param asks for {differ}")
    if args.horizon is not None and args.horizon != policy.horizon:
        raise ValueError(f"--set {args.set}: its tables have horizon {policy.horizon}, --horizon says {args.horizon}")
    return name, params, system, policy.horizon


@cli_main()
def main(argv: Sequence[str] | None = None) -> int:
    args = make_parser().parse_args(argv)
    _check(args)
    torch.set_num_threads(1)
    import_system_modules(args.system_module)
    folder = args.set
    if folder is not None:  # the set says what it is
        policy = _load_set(folder)
        name, params, system, horizon = _set_system(args, policy)
        spec = None
    else:
        name, params = resolve_system(args.system or "ks_speed"), parse_params(args.param)
        system = make_system(name, **params)
        horizon = 5 if args.horizon is None else args.horizon
        spec = "3=0:1:6" if args.starts is None else args.starts
        parse_starts(spec, system)  # a bad SPEC: its own message, before anything is built
        folder = set_folder(args.cache, name, params, horizon, spec)
        # the library function `python -m precompute.build set` calls; a complete set there is reused
        policy = build_table_set(system, SetConfig(starts=spec, workers=args.workers), BuildConfig(horizon=horizon),
                                 out=folder, progress=not args.quiet)
    set_starts = policy.starts.numpy()
    dims = [k for k in range(set_starts.shape[1]) if np.ptp(set_starts[:, k]) > 0]
    if getattr(system, "se2_invariant", False):
        dims = sorted({0, 1, 2, *dims})
    starts = random_starts(system, set_starts, args.random, args.seed)
    from tqdm.auto import tqdm

    rows = [measure_start(system, policy, s, horizon, args.samples, args.seed + i)
            for i, s in enumerate(tqdm(starts, desc="starts", disable=args.quiet))]
    print(f"{name} horizon {horizon}: set of {len(set_starts)} starts ({folder}), {args.samples} rollouts per "
          f"start and policy")
    print(format_rows(rows, dims))
    if args.json is not None:
        write_json(args.json, dict(system=name, params=params, horizon=horizon, set=str(folder),
                                   starts_spec=spec, rows=[asdict(r) | {"ratio": r.ratio} for r in rows],
                                   summary=summary(rows)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
