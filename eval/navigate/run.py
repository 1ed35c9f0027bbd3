"""Closed-loop navigation benchmark: every method at every sample budget on the BARN, forest, gap, moving-disc and
sudden-obstacle suites.

    python -m eval.navigate --suite barn --budgets 256 1024 --workers 2

Runs each (task, method, budget, repeat) episode with the same cost, horizon and temperature for every method
(:mod:`eval.navigate.episode`), on the built-in robot (:mod:`eval.navigate.robot_files`; its tables are built on first use and
cached under ``--cache``) or a registered system (``--system``, ``--param``). Writes under ``--out``:
``episodes.jsonl`` (one record per episode, resumable: a rerun skips finished episodes), ``results.md`` and
``results.json`` (success / collision / timeout rates with 95% Wilson intervals, path length and time over
successes, control-cycle wall times, paired comparisons with the best Gaussian baseline), ``success.png`` and
TensorBoard scalars under ``tb/``. ``--workers N`` runs episodes in N processes, ``--ray [ADDRESS]`` as Ray
tasks; the records are the same as a serial run's.

Everything is checked before the first episode: the suite, the methods, the budgets (>= 2), the map file, every
task's start and goal (in collision or unreachable: an error naming the task), the output folder's settings.
"""

from __future__ import annotations

import dataclasses
import os
import sys
import time
import zlib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cuniform_torch.common.fileio import exclusive_lock, open_regular
from eval.common import config
from eval.common.methods import NAVIGATE, methods_of, parse_methods
from eval.navigate.cost_to_go import RESOLUTION as COST_TO_GO_RESOLUTION
from eval.navigate.dynamics import DYNAMICS, learned_model
from eval.navigate.episode import NavContext, NavJob
from eval.navigate.execute import execute
from eval.navigate.records import EpisodeStore
from eval.navigate.results import render, result, success_pivot, write_outputs
from eval.navigate.robot_files import ensure_policy, ensure_table
from precompute.cli import (
    MAX_COUNT,
    ArgumentParser,
    CLIError,
    add_config_args,
    add_dataclass_args,
    add_no_limit_arg,
    add_system_module_arg,
    check_output_folder,
    check_work,
    cli_main,
    config_text,
    dataclass_from_config,
    float_in,
    horizon_arg,
    import_system_modules,
    int_in,
    positive_float,
    positive_int,
    refuse_flags,
)
from precompute.worlds.robot import NAV_ROBOT, RobotPreset, preset_dict, suite_robot
from precompute.worlds.suites import NavTask
from precompute.worlds.tasks import SPLITS, SUITES, TIME_LIMITS, make_tasks

__all__ = ["NavConfig", "check_config", "input_digest", "prepare_sources", "NAV_TYPES", "REPEATS", "SHORT", "QUICK", "make_jobs", "run", "short_run", "render", "result",
           "success_pivot", "write_outputs", "main", "controller_seed"]

REPEATS = {"barn": 1, "forest": 1, "gaps": 5, "clutter": 1, "moving": 1, "sudden": 1, "narrow": 1}
"""controller seeds per task by default: the gap suite has few tasks (9 widths), so each runs 5 times"""


@dataclass(frozen=True)
class NavConfig:
    """One benchmark run (every field is a flag)."""

    suite: str = "barn"
    """barn, forest, gaps, clutter, moving (discs crossing at constant velocity), sudden (an obstacle sensed late) or
    narrow (passages 1.5-2x the robot's width, driven at 1.0 m/s by FAST_ROBOT)"""
    tasks: int | None = None
    """how many tasks (BARN: the first maps of the file; forest, clutter, moving, narrow: seeds from --seed; gaps: widths
    0.6..1.2 m; sudden: 5 appearance times per obstacle position); default: every BARN map, 50 forests, 9 gaps,
    50 moving, 100 sudden"""
    budgets: tuple[int, ...] = (256, 1024)
    """K, trajectories per control cycle (each >= 2)"""
    methods: tuple[str, ...] | None = None
    """method keys (default: all but the opt-in cu_mlp and cfu_mppi)"""
    repeats: int | None = None
    """controller seeds per task (default: 1, the gap suite 5)"""
    seed: int = 0
    """the first forest seed; controller seeds derive from it, the suite and the task"""
    split: str = "all"
    """all, or only the train / test maps (BARN map id or forest seed divisible by 5: test; the gap sweep is test):
    the map-table farm trains on train maps only, so judge map-conditioned methods on test"""
    sensing_range: float = 3.0
    """forest: obstacles are sensed within this distance of the robot (m)"""
    horizon: int = 15
    """controller horizon, steps (the built-in robot's table depth)"""
    lambda_: float = config.LAMBDA
    """MPPI temperature of every method"""
    collision_penalty: float = 1e6
    """cost of each colliding rollout state"""
    cost_resolution: float = 0.01
    """m: cell side of the rasterized cost map of BARN maps (eval.navigate.episode)"""
    cost_to_go: bool = False
    """the goal term uses the geodesic distance to the goal around the sensed obstacles (eval.navigate.cost_to_go) instead
    of the straight line: a cost without the straight line's minima behind obstacles"""
    workers: int = 1
    """local processes running episodes"""
    paths: bool = False
    """keep each episode's driven path in its record"""
    lockstep: int | None = None
    """run the episodes of each (method, K) in batches of up to this many, one batched command per control cycle
    (eval.navigate.lockstep): the same records but for the timing fields, whose cycle times are then each batch
    command's share (clock "lockstep"), not a robot's own cycle; default: one episode at a time"""
    dynamics: str = "true"
    """what the controllers plan with: true (the robot's) or learned (a 2x64 MLP trained on the robot's step, with no
    closed-form or compiled rollout: the costly-dynamics mode, eval.navigate.dynamics); the simulator steps the robot's
    own in both"""


def controller_seed(suite: str, task_id: int, repeat: int, seed: int) -> int:
    """The controller seed of a task's repeat: the same for every method and budget (paired episodes)."""
    words = np.random.SeedSequence([seed, zlib.crc32(suite.encode()), task_id, repeat]).generate_state(1)
    return int(words[0] & 0x7FFFFFFF)


def make_jobs(tasks: Sequence[NavTask], methods: Sequence[str], budgets: Sequence[int], repeats: int,
              seed: int) -> list[NavJob]:
    """Every (task, repeat, budget, method) job, tasks outermost (a partial run covers whole tasks first)."""
    return [NavJob(task, m, k, controller_seed(task.suite, task.task_id, r, seed), r)
            for task in tasks for r in range(repeats) for k in budgets for m in methods]


def check_config(cfg: NavConfig) -> None:
    """Refuse a config the benchmark cannot run (unknown suite, dynamics or method, a method the suite refuses,
    bad counts): one ``ValueError`` naming the field; the run calls it once, the atlas per suite."""
    if cfg.dynamics not in DYNAMICS:
        raise ValueError(f"unknown dynamics {cfg.dynamics!r}; choose from {', '.join(DYNAMICS)}")
    if cfg.suite not in SUITES:
        raise ValueError(f"unknown suite {cfg.suite!r}; choose from {', '.join(SUITES)}")
    if cfg.split not in SPLITS:
        raise ValueError(f"unknown split {cfg.split!r}; choose from {', '.join(SPLITS)}")
    chosen = [m.key for m in parse_methods(cfg.methods, benchmark=NAVIGATE, closed_loop=True)]
    if cfg.suite in ("moving", "sudden") and "cfu_mppi" in chosen:
        raise ValueError(f"cfu_mppi cannot drive the {cfg.suite} suite: its map policy senses a still world from the "
                         "start (moving discs and late obstacles are not in it); leave it out of --methods")
    if cfg.suite in ("moving", "sudden") and cfg.cost_to_go:
        raise ValueError(f"--cost-to-go cannot serve the {cfg.suite} suite: its planner sees a still world with every "
                         "obstacle from the start (it would miss the moving discs and know a sudden obstacle before it "
                         "appears); leave it out")
    if not cfg.budgets:
        raise ValueError("give at least one budget (--budgets)")
    bad = [k for k in cfg.budgets if isinstance(k, bool) or not isinstance(k, int) or k < 2]
    if bad:
        raise ValueError(f"every budget must be an integer >= 2 (CU-MPPI splits it in two), got {bad}")
    if len(set(cfg.budgets)) != len(cfg.budgets):
        raise ValueError(f"a budget is given twice: {list(cfg.budgets)}")
    for name in ("repeats", "tasks"):
        v = getattr(cfg, name)
        if v is not None and (isinstance(v, bool) or v < 1):
            raise ValueError(f"--{name} must be >= 1, got {v}")
    if cfg.workers < 1:
        raise ValueError(f"--workers must be >= 1, got {cfg.workers}")
    if cfg.lockstep is not None and (isinstance(cfg.lockstep, bool) or not isinstance(cfg.lockstep, int)
                                     or cfg.lockstep < 1):
        raise ValueError(f"--lockstep must be an integer >= 1 (episodes per batch), got {cfg.lockstep!r}")
    for name in ("sensing_range", "cost_resolution", "collision_penalty", "lambda_"):
        v = getattr(cfg, name)
        if not (np.isfinite(v) and v > 0):
            raise ValueError(f"--{name.rstrip('_').replace('_', '-')} must be a finite number > 0, got {v}")


def input_digest(path: Path | None) -> str | None:
    """A short sha256 of a file, or of a table set's index and tables. Each is opened as a regular file
    (:func:`~cuniform_torch.common.fileio.open_regular`) and read in blocks: a FIFO, a device or a link to one is one
    FileKindError (a ValueError) naming it, never a hang (``eval.navigate.replay --table FIFO`` hung here) or an
    endless read."""
    if path is None:
        return None
    import hashlib

    path = Path(path)
    files = [path / "tables.json", *sorted(path.glob("*.npz"))] if path.is_dir() else [path]
    h = hashlib.sha256()
    for f in files:
        with open_regular(f, "an input file of the benchmark") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
    return h.hexdigest()[:16]


def settings_record(cfg: NavConfig, robot: RobotPreset, barn_file: Path | None, sources: dict[str, str | None],
                    tasks: Sequence[NavTask] = ()) -> dict:
    """What changes an episode's outcome (:mod:`eval.navigate.store`): not the counts, methods, budgets or workers; for
    the gap sweep, the widths of ``tasks`` (its length sets them, so a longer sweep may be other gaps)."""
    keep = ("suite", "seed", "sensing_range", "horizon", "lambda_", "collision_penalty", "cost_resolution")
    out: dict[str, Any] = {k: getattr(cfg, k) for k in keep}
    out.update(robot=preset_dict(robot), time_limit=TIME_LIMITS[cfg.suite],
               barn_file=input_digest(barn_file) if cfg.suite == "barn" else None,
               sources={k: input_digest(Path(v)) if v else None for k, v in sources.items()})
    if cfg.cost_to_go:  # absent otherwise: the folders of runs without it stay as they were
        out["cost_to_go"] = COST_TO_GO_RESOLUTION
    if cfg.dynamics != "true":  # absent otherwise, as cost_to_go
        out["dynamics"] = cfg.dynamics
    if cfg.suite == "gaps":  # the sweep's widths depend on its length: task 3 of 4 gaps is not task 3 of 7
        if not tasks:
            raise ValueError("settings_record: a gaps run's record needs its tasks (their widths)")
        out["gap_widths"] = sorted({t.params["width"] for t in tasks})
    return out


def prepare_sources(cfg: NavConfig, robot: RobotPreset, cache: Path, given: dict[str, Path | None],
                    quiet: bool) -> dict[str, str | None]:
    """The files the methods need: given on the command line, else the robot's cached ones (built when missing)."""
    methods = {m.source for m in parse_methods(cfg.methods, benchmark=NAVIGATE, closed_loop=True)}
    _check_given(given, methods)  # before anything is built: a bad file is refused at once
    table = given.get("table") or ensure_table(robot, cache, quiet=quiet)
    coverage = given.get("coverage_table")
    if "coverage_table" in methods and coverage is None:
        coverage = ensure_table(robot, cache, method="coverage", quiet=quiet)
    policy = given.get("policy")
    if "policy" in methods and policy is None:
        policy = ensure_policy(robot, cache, quiet=quiet)
    map_policy = given.get("map_policy")
    if "map_policy" in methods:
        map_policy = map_policy_for(robot, map_policy)
    for name, p in (("table", table), ("coverage_table", coverage), ("policy", policy), ("map_policy", map_policy)):
        if p is not None and not (Path(p).is_file() or (Path(p) / "tables.json").is_file()):
            raise FileNotFoundError(f"--{name.replace('_', '-')} {p} does not exist (a table file or a table set's "
                                    "folder)")
    out = {"table": str(table), "coverage_table": str(coverage) if coverage else None,
           "policy": str(policy) if policy else None}
    if map_policy is not None:  # absent otherwise: the records of runs without it stay as they were
        out["map_policy"] = str(map_policy)
    return out


_READER_OF = {"coverage_table": "cu_coverage", "policy": "cu_mlp", "map_policy": "cfu_mppi"}
"""the method that reads each optional source file"""


def _check_given(given: dict[str, Path | None], sources: set) -> None:
    """Each source file given on the command line: one that no chosen method reads is refused (``--table`` is
    always read: the system of every method), and each is read and checked now (a missing path, an empty file or
    folder, a damaged file: one clear error before any table is built or any episode runs)."""
    from cuniform_torch import load_policy, load_table, read_table

    for name, path in given.items():
        if path is None:
            continue
        flag = f"--{name.replace('_', '-')}"
        if name != "table" and name not in sources:
            raise ValueError(f"{flag} {path}: no chosen method reads it (it is for {_READER_OF[name]})")
        if name == "map_policy":
            continue  # checked against the robot by map_policy_for
        p = Path(path)
        if not (p.is_file() or (p / "tables.json").is_file()):
            raise FileNotFoundError(f"{flag} {path} does not exist (a table file or a table set's folder)")
        try:  # read and checked only: the episodes build their policies themselves
            if name == "policy":
                load_policy(p)
            elif p.is_dir():
                load_table(p)  # a set opens lazily: its index and first member
            else:
                read_table(p, graph=False)
        except ValueError as exc:
            raise ValueError(f"{flag} {path}: {exc}") from None


def map_policy_for(robot: RobotPreset, given: Path | str | None) -> Path:
    """The map policy CFU-MPPI drives ``robot`` with: ``given`` (a file, or the name of a shipped policy) checked
    against the robot, or with none the shipped policy trained for this robot. A policy of another robot (system,
    speed, turn rates, time step, grid, radius, horizon) is one clear error naming what differs."""
    from cuniform_torch.controllers.cfu import check_policy_robot
    from cuniform_torch.maps.checkpoint import load_map_policy
    from cuniform_torch.maps.pretrained import pretrained_card, pretrained_names, pretrained_path, robot_mismatch

    want = preset_dict(robot)
    if given is None:
        differs = {}
        for name in pretrained_names():
            diff = robot_mismatch(pretrained_card(name)["robot"], want)
            if not diff:
                return pretrained_path(name)
            differs[name] = diff
        shipped = "; ".join(f"the shipped {n!r} was trained for another robot ({', '.join(d)})"
                            for n, d in differs.items()) or ("no policy is shipped (python -m training.maps.pretrained "
                                                              "--install builds the benchmark robot's)")
        raise ValueError(f"cfu_mppi needs a map policy for this robot: {shipped}; give --map-policy FILE "
                         "(python -m training.maps.distill trains one)")
    name = str(given)
    path = pretrained_path(name) if not Path(name).exists() and name in pretrained_names() else Path(given)
    if not path.is_file():
        raise FileNotFoundError(f"--map-policy {given}: no such file (nor a shipped policy: "
                                f"{', '.join(pretrained_names()) or 'none'})")
    policy = load_map_policy(path)
    try:
        check_policy_robot(policy, robot.make_system(), robot.horizon)
    except ValueError as exc:
        raise ValueError(f"--map-policy {given}: {exc}") from None
    trained_radius = _trained_radius(path, name)
    if trained_radius is not None and abs(trained_radius - robot.radius) > 1e-9:
        raise ValueError(f"--map-policy {given}: the map policy was trained for another robot: radius: trained "
                         f"{trained_radius}, given {robot.radius}")
    return path


def _trained_radius(path: Path, name: str) -> float | None:
    """The robot radius a map policy's tables inflated obstacles by: its card's (a shipped policy), else its
    checkpoint's ``metrics.robot_radius`` (None when the file predates that record)."""
    from cuniform_torch.maps.pretrained import pretrained_card, pretrained_names

    if name in pretrained_names():
        return float(pretrained_card(name)["robot"]["radius"])
    import torch

    metrics = torch.load(path, map_location="cpu", weights_only=True).get("metrics", {})
    radius = metrics.get("robot_radius") if isinstance(metrics, dict) else None
    return float(radius) if isinstance(radius, (int, float)) and not isinstance(radius, bool) else None


def run(cfg: NavConfig, out: Path, robot: RobotPreset | None = None, cache: Path = Path("out/navigate/cache"),
        barn_file: Path | None = None, given: dict[str, Path | None] | None = None,
        ray_address: str | None = None, progress: bool = True) -> dict:
    """Run (or resume) the benchmark ``cfg`` into the folder ``out``; the result that ``results.json`` holds.
    ``cfg`` is checked here, the library's edge (:func:`main` checks its flags before any work and calls
    :func:`_run`). ``robot`` None: the suite's (:func:`~precompute.worlds.robot.suite_robot`)."""
    check_config(cfg)
    robot = suite_robot(cfg.suite) if robot is None else robot
    return _run(cfg, out, robot, cache, barn_file, given, ray_address, progress)


def _run(cfg: NavConfig, out: Path, robot: RobotPreset, cache: Path, barn_file: Path | None,
         given: dict[str, Path | None] | None, ray_address: str | None, progress: bool) -> dict:
    """:func:`run` of a checked ``cfg``: the budgets and the rest are trusted from here to the controllers (whose
    public constructors check K for other callers)."""
    methods = [m.key for m in parse_methods(cfg.methods, benchmark=NAVIGATE, closed_loop=True)]
    tasks = make_tasks(cfg.suite, robot.radius, cfg.tasks, seed=cfg.seed, barn_file=barn_file,
                       sensing_range=cfg.sensing_range, time_limits=TIME_LIMITS, split=cfg.split)
    repeats = cfg.repeats or REPEATS[cfg.suite]
    jobs = make_jobs(tasks, methods, cfg.budgets, repeats, cfg.seed)
    with exclusive_lock(Path(out) / ".lock", what=f"the benchmark folder {out}"):
        store = EpisodeStore(out)
        store.check()  # a damaged folder is refused before the tables are built
        sources = prepare_sources(cfg, robot, cache, given or {}, quiet=not progress)
        done = store.open(settings_record(cfg, robot, barn_file, sources, tasks))
        todo = [j for j in jobs if j.key not in done]
        print(f"{cfg.suite}: {len(tasks)} tasks x {repeats} repeats x {len(cfg.budgets)} budgets x {len(methods)} "
              f"methods = {len(jobs)} episodes; {len(jobs) - len(todo)} already in {store.records_file}")
        ctx = NavContext(table=sources["table"], coverage_table=sources["coverage_table"], policy=sources["policy"],
                         map_policy=sources.get("map_policy"),
                         horizon=cfg.horizon, lambda_=cfg.lambda_, collision_penalty=cfg.collision_penalty,
                         cost_resolution=cfg.cost_resolution, record_path=cfg.paths,
                         cost_to_go=COST_TO_GO_RESOLUTION if cfg.cost_to_go else None, dynamics=cfg.dynamics)
        load0, t0 = os.getloadavg()[0], time.perf_counter()

        def keep(rec: dict) -> None:
            store.append(rec)
            done[rec["key"]] = rec

        execute(todo, ctx, keep, workers=cfg.workers, ray_address=ray_address, progress=progress,
                desc=f"{cfg.suite} episodes", lockstep=cfg.lockstep)
        wall = time.perf_counter() - t0
        records = [done[j.key] for j in jobs]  # this run's episodes, in job order, whoever ran them
        return result(cfg, records, tasks, methods, wall, load0, ray_address, ran=len(todo))


SHORT = NavConfig(suite="barn", tasks=10, budgets=(64, 256))
"""the short run of ``python -m eval.report``: the first 10 BARN maps, every default method, two budgets"""
QUICK = NavConfig(suite="barn", tasks=2, budgets=(16, 64), methods=("mppi_1.0", "cu_table"), horizon=10)
"""``python -m eval.report --quick``'s: 2 maps, 2 methods, a 10-step table (2 s of build instead of 8)"""


def short_run(root: Path, quick: bool = False, progress: bool = True, workers: int = 1) -> dict:
    """The report's short benchmark run (:data:`SHORT`, or :data:`QUICK`) under ``root`` (its results written too),
    its episodes in ``workers`` processes."""
    cfg = dataclasses.replace(QUICK if quick else SHORT, workers=workers)
    out = Path(root) / ("barn_quick" if quick else "barn_short")
    robot = dataclasses.replace(NAV_ROBOT, horizon=cfg.horizon)
    res = run(cfg, out, robot, cache=Path(root) / "cache", progress=progress)
    write_outputs(res, out)
    return res


NAV_TYPES = {"tasks": positive_int, "budgets": int_in(2, MAX_COUNT, note=" (CU-MPPI splits it in two)"),
             "repeats": positive_int, "seed": int_in(0, 2**31 - 1), "lockstep": int_in(1, 4096), "horizon": horizon_arg, "workers": int_in(1, 1024),
             "sensing_range": positive_float, "lambda_": positive_float, "collision_penalty": positive_float,
             "cost_resolution": positive_float}
"""the :class:`NavConfig` flags' values, checked as they parse (:mod:`precompute.cli`)"""


def make_parser() -> ArgumentParser:
    p = ArgumentParser(prog="python -m eval.navigate", description=(__doc__ or "").split("\n\n")[0])
    add_dataclass_args(p, NavConfig, flags={"lambda_": "--lambda"}, choices={"suite": SUITES, "split": SPLITS, "dynamics": DYNAMICS},
                       help={"methods": f"method keys, of {', '.join(methods_of(NAVIGATE))} (default: all but the opt-in cu_mlp and cfu_mppi)"},
                       arg_types=NAV_TYPES)
    p.add_argument("--ray", nargs="?", const="local", default=None, metavar="ADDRESS",
                   help="run episodes as Ray tasks: a local Ray runtime, or the cluster at ADDRESS ('auto', "
                        "'ray://host:10001'); needs pip install -e '.[ray]'")
    p.add_argument("--out", type=Path, default=None, help="output folder (default: out/navigate/<suite>)")
    p.add_argument("--cache", type=Path, default=Path("out/navigate/cache"),
                   help="where the robot's tables are built and kept (default: out/navigate/cache)")
    p.add_argument("--barn-file", type=Path, default=None,
                   help="BARN maps in the shipped format (precompute/worlds/barn.py); --suite barn only")
    p.add_argument("--barn-worlds", type=Path, default=None,
                   help="a folder of BARN Gazebo world_<id>.world files (or one file), converted to --out/barn.npz; "
                        "--suite barn only")
    p.add_argument("--table", type=Path, default=None, help="use this max-flow table (default: the robot's, cached)")
    p.add_argument("--coverage-table", type=Path, default=None, help="use this coverage table (cu_coverage)")
    p.add_argument("--policy", type=Path, default=None, help="use this distilled MLP (cu_mlp)")
    p.add_argument("--map-policy", type=Path, default=None,
                   help="cfu_mppi's map-conditioned policy: a file (python -m training.maps.distill) or the name of a "
                        "shipped one (default: the shipped policy trained for this robot, e.g. unicycle-0.5)")
    p.add_argument("--system", default=None, help="drive a registered system instead of the built-in robot")
    p.add_argument("--param", action="append", default=[], metavar="KEY=VALUE",
                   help="a parameter of --system as JSON (repeatable)")
    p.add_argument("--robot-radius", type=float_in(0.0, 100.0), default=NAV_ROBOT.radius, help="m (default: 0.2)")
    p.add_argument("--starts", default=None, metavar="SPEC",
                   help="with --system: the robot's tables are a set over these starts (precompute.build --starts), "
                        "e.g. '3=0:1:6' for ks_speed's speed")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    add_no_limit_arg(p)
    add_system_module_arg(p)
    add_config_args(p, "the run's settings (suite, tasks, budgets, methods, ...: the flags of NavConfig)")
    return p


def _check_flags(p: ArgumentParser, args, cfg: NavConfig, out: Path) -> None:
    """The flags that do not apply to ``cfg``'s suite, a run too large, an ``--out`` that cannot be a folder (a
    device, a FIFO, a file), and ``--paths`` on a folder whose episodes were kept without their paths: refused
    before any work (:func:`precompute.cli.refuse_flags`)."""
    if cfg.suite != "barn":
        refuse_flags(p, args, ["barn_file", "barn_worlds"], f"to --suite {cfg.suite} (BARN maps: --suite barn)")
    if cfg.suite not in ("forest", "clutter"):
        refuse_flags(p, args, ["sensing_range"], f"to --suite {cfg.suite} (obstacles are sensed in forest and "
                                                 "clutter)")
    counts = {"tasks": cfg.tasks, "repeats": cfg.repeats, "budgets": len(cfg.budgets),
              "methods": len(cfg.methods) if cfg.methods is not None else None}
    check_work({k: v for k, v in counts.items() if v is not None}, "episodes", args.no_limit)
    check_output_folder(out, "--out")  # a link to /dev/null: one line now, not "File exists" after the tasks
    if cfg.paths:
        store = EpisodeStore(out)
        if store.records_file.is_file():
            without = sum("path" not in rec for rec in store.read().values())
            if without:
                raise CLIError(f"--paths: {without} episode(s) in {store.records_file} were run without --paths; "
                               "a resumed run would keep them without their paths: give another --out")


def _robot(args, cfg: NavConfig) -> RobotPreset:
    if args.system is None and args.param:
        raise ValueError("--param needs --system (the built-in robot's parameters are fixed: eval/navigate/robot_files.py)")
    from precompute.build import parse_params

    base = suite_robot(cfg.suite)  # the narrow suite's robot is the faster FAST_ROBOT
    params = dict(base.params) if args.system is None else parse_params(args.param)
    radius = args.robot_radius
    if not (np.isfinite(radius) and radius >= 0):
        raise ValueError(f"--robot-radius must be a finite number >= 0, got {radius}")
    if args.starts is not None and args.system is None:
        raise ValueError("--starts needs --system (the built-in robot's state is a pose: one table serves it)")
    robot = RobotPreset(system=args.system or base.system, params=params, radius=radius, horizon=cfg.horizon,
                        starts=args.starts)
    system = robot.make_system()  # a bad system or parameter fails here, before any work
    if cfg.dynamics == "learned":
        learned_model(system)  # a robot it cannot model, too
    if args.starts is not None:
        from precompute.table_set import parse_starts

        parse_starts(args.starts, system)  # a bad SPEC too
    return robot


@cli_main()
def main(argv: Sequence[str] | None = None) -> int:
    p = make_parser()
    args = p.parse_args(argv)
    import_system_modules(args.system_module)
    cfg = dataclass_from_config(NavConfig, args)
    check_config(cfg)
    if args.print_config:  # the run's settings as a --config file, nothing run
        print(config_text(cfg))
        return 0
    out = args.out or Path("out/navigate") / cfg.suite
    _check_flags(p, args, cfg, out)
    robot = _robot(args, cfg)
    barn_file = args.barn_file
    if args.barn_worlds is not None:
        if barn_file is not None:
            raise ValueError("give --barn-file or --barn-worlds, not both")
        from precompute.worlds.barn import convert_worlds, write_barn

        barn_file = out / "barn.npz"
        write_barn(barn_file, convert_worlds(args.barn_worlds))
        print(f"converted {args.barn_worlds} into {barn_file}")
    given = {"table": args.table, "coverage_table": args.coverage_table, "policy": args.policy,
             "map_policy": args.map_policy}
    res = _run(cfg, out, robot, args.cache, barn_file, given, args.ray, progress=not args.quiet)  # checked above
    print(render(res))
    for path in write_outputs(res, out):
        print(f"wrote {path}")
    if cfg.lockstep is not None:  # its cycle times are a batched command's shares (eval.navigate.lockstep)
        print("no equal-compute view (budget.md) for a --lockstep run: its cycle times are each batched command's "
              "share, not a robot's own control cycle; rerun without --lockstep to judge at equal compute")
        sys.stdout.flush()
        return 0
    from eval.navigate.budget import judge_folder, write_budget
    from eval.navigate.budget import render as render_budget

    budget = judge_folder(out)  # the folder's episodes judged at equal cycle time (eval.navigate.budget)
    print(render_budget(budget), end="")
    for path in write_budget(budget, out / "budget.md", out / "budget.png"):
        print(f"wrote {path}")
    sys.stdout.flush()
    return 0
