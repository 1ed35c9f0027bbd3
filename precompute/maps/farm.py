"""A farm of safe tables, one per (local map, start pose):  python -m precompute.maps.farm --suite barn --count 20
--poses-per-map 1 --split train --seed 0 --out out/maps_train

For each of ``--count`` maps of the suite's ``--split`` (:mod:`precompute.maps.worlds`: which maps, the split
rule, the start poses), ``--poses-per-map`` free start poses are drawn; around each, the local map patch
(default 72 x 72 cells of 0.05 m centred on the robot, in its frame) is cropped and a safe table built for the
benchmark robot (:data:`precompute.worlds.robot.NAV_ROBOT`; ``--system``, ``--param``, ``--horizon``, ``--radius``
override it). A pose whose table cannot be built (its start cell in an inflated obstacle of the patch, or a
level with no free cell: boxed in) is replaced by the next free candidate.

One shard per map, built in ``--workers`` processes or as Ray tasks (``--ray [ADDRESS]``); the data set is
written in the format ``cuniform-map-dataset/1`` (:mod:`precompute.maps.dataset`). Resumable per shard:
``DIR/farm-progress.json`` records each finished shard's sha256 and entries, and a rerun with the same settings
skips the shards whose file still has that sha256 (and rebuilds the others). Errors are one ``error:`` line and
exit code 2.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from dataclasses import field as dataclass_field
from pathlib import Path
from typing import Any

import numpy as np

from cuniform_torch.common.fileio import MAX_JSON_BYTES, exclusive_lock, read_capped_text, write_json
from cuniform_torch.systems import make_system, resolve_system, system_from_json
from precompute.cli import (
    ArgumentParser,
    CLIError,
    add_dataclass_args,
    cli_main,
    field_docs,
    flag_name,
    given_fields,
    horizon_arg,
    int_in,
    non_negative_int,
    positive_float,
    positive_int,
)
from precompute.coverage.method import CoverageConfig
from precompute.levels.safe_map import LocalMap, MapError, check_map_system
from precompute.levels.viability import SAFE_RULE
from precompute.maps.dataset import dataset_header, entry_arrays, file_sha256, write_shard
from precompute.maps.worlds import FARM_SUITES, SPLITS, candidate_poses, crop_patch, suite_worlds, world_of
from precompute.parallel import run_jobs

__all__ = ["main", "FarmConfig", "build_farm", "build_shard", "MAX_TRIES"]

PROGRESS = "farm-progress.json"
MAX_TRIES = 2000
"""candidate poses a shard may try before it gives up on its map"""


def make_parser() -> argparse.ArgumentParser:
    from precompute.worlds.robot import NAV_ROBOT

    parser = ArgumentParser(prog="python -m precompute.maps.farm",
                            description="Build a data set of safe C-Uniform tables over local map patches.")
    parser.add_argument("--suite", required=True, choices=list(FARM_SUITES))
    parser.add_argument("--count", type=positive_int, required=True, help="maps (one shard each)")
    parser.add_argument("--poses-per-map", type=positive_int, default=1, help="start poses (entries) per map")
    parser.add_argument("--split", required=True, choices=list(SPLITS),
                        help="test: the maps whose key is divisible by 5; train: the others (precompute/maps/worlds.py)")
    parser.add_argument("--seed", type=non_negative_int, default=0, help="picks the maps of the split and the start poses")
    parser.add_argument("--out", type=Path, required=True, help="the data set folder")
    parser.add_argument("--workers", type=int_in(1, 1024), default=1, help="shards built in parallel processes")
    parser.add_argument("--ray", nargs="?", const="local", default=None, metavar="ADDRESS",
                        help="shards as Ray tasks (a local runtime, or the cluster at ADDRESS)")
    parser.add_argument("--method", default="maxflow", choices=["maxflow", "coverage"])
    docs = field_docs(CoverageConfig)
    add_dataclass_args(parser, CoverageConfig, only=FARM_COVERAGE,
                       help={name: f"coverage method: {docs[name]}" for name in FARM_COVERAGE})
    parser.add_argument("--system", default=NAV_ROBOT.system, help="default: the benchmark robot's")
    parser.add_argument("--param", action="append", default=[], metavar="KEY=VALUE",
                        help="a system parameter as JSON over the benchmark robot's (repeatable)")
    parser.add_argument("--horizon", type=horizon_arg, default=NAV_ROBOT.horizon)
    parser.add_argument("--radius", type=float, default=NAV_ROBOT.radius, help="robot radius (m) to inflate by")
    parser.add_argument("--patch", type=int_in(1, 4096), nargs=2, default=[72, 72], metavar=("H", "W"),
                        help="patch cells (centred on the robot)")
    parser.add_argument("--resolution", type=positive_float, default=0.05, help="patch cell side (m)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    return parser


def _system(args: argparse.Namespace):
    from precompute.build import parse_params
    from precompute.worlds.robot import NAV_ROBOT

    name = resolve_system(args.system)
    params = dict(NAV_ROBOT.params) if name == NAV_ROBOT.system else {}
    params.update(parse_params(args.param))
    params = {k: tuple(v) if isinstance(v, list) else v for k, v in params.items()}
    system = make_system(name, **params)
    check_map_system(system)
    return system


def _check(args: argparse.Namespace) -> None:
    """The flags' own rule (the values are checked as they parse, and again by :func:`build_farm`)."""
    given = [flag_name(k) for k in _coverage_given(args)]
    if given and args.method != "coverage":
        raise CLIError(f"{', '.join(given)}: only for --method coverage")


FARM_COVERAGE = ("steps", "tol", "state_budget", "merge_resolution")
"""the coverage builder's settings a farm takes as flags (:class:`precompute.coverage.method.CoverageConfig`)"""


def _coverage_given(args: argparse.Namespace) -> dict[str, Any]:
    """The :data:`FARM_COVERAGE` flags given (``--horizon`` and ``--radius`` are fields too, but the farm's own)."""
    return {k: v for k, v in given_fields(CoverageConfig, args).items() if k in FARM_COVERAGE}


def coverage_settings(args: argparse.Namespace) -> dict[str, Any]:
    """The coverage builder's settings the flags give (checked by CoverageConfig: one clear error)."""
    settings = _coverage_given(args)
    try:
        CoverageConfig(**settings)
    except ValueError as e:
        raise CLIError(f"coverage settings: {e}") from None
    return settings


def build_shard(spec_json: str, k: int, out: str) -> dict[str, Any]:
    """Build shard ``k`` of the farm ``spec_json`` into the folder ``out``; its sha256 and entries."""
    import torch

    from precompute.coverage.method import build_coverage_table
    from precompute.flow.builder import BuildConfig, build_table

    torch.set_num_threads(1)
    spec = json.loads(spec_json)
    head, (suite, key) = spec["header"], spec["maps"][k]
    system, horizon = system_from_json(head["system"])
    radius, patch = head["radius"], head["patch"]
    world = world_of(suite, key, radius)
    rng = np.random.default_rng([head["seed"], key])
    entries, patches, poses, tries = [], [], [], 0
    while len(entries) < spec["poses_per_map"]:
        for pose in candidate_poses(world, rng, radius, margin=patch["resolution"]):
            tries += 1
            grid = crop_patch(world, pose, tuple(patch["shape"]), patch["resolution"], tuple(patch["origin"]))
            local = LocalMap(grid, tuple(patch["origin"]), patch["resolution"])
            try:
                if head["method"] == "coverage":
                    table = build_coverage_table(system, CoverageConfig(horizon=horizon, local_map=local,
                                                                        radius=radius, **head.get("coverage", {})))[0]
                else:
                    table = build_table(system, BuildConfig(horizon=horizon, local_map=local, radius=radius))[0]
            except MapError:  # the rasterized start is blocked, or the pose is boxed in: the next candidate
                continue
            entries.append(entry_arrays(table))
            patches.append(grid)
            poses.append(pose)
            if len(entries) == spec["poses_per_map"]:
                break
        if tries > MAX_TRIES and len(entries) < spec["poses_per_map"]:
            raise MapError(f"{world.source}: only {len(entries)} of {spec['poses_per_map']} start poses with a safe "
                           f"table after {tries} candidates")
    sha = write_shard(Path(out) / _shard_name(k), np.stack(patches), np.stack(poses), entries)
    return {"sha256": sha, "entries": [{"source": world.source, "pose": [float(v) for v in p]} for p in poses],
            "tries": tries}


def _shard_name(k: int) -> str:
    return f"shard-{k:05d}.npz"


def _load_progress(out: Path, spec: dict) -> dict[str, dict]:
    """Finished shards of a previous run with the same ``spec`` whose files still match; CLIError for a folder
    of a data set with other settings."""
    path = out / PROGRESS
    if not path.is_file():
        if (out / "dataset.json").exists():
            raise CLIError(f"--out {out} holds a data set without {PROGRESS}; choose another --out")
        return {}
    try:
        saved = json.loads(read_capped_text(path, MAX_JSON_BYTES, "the farm's progress file"))
        same = saved["spec"] == spec
        done = saved["done"]
    except (OSError, ValueError, KeyError, TypeError):
        return {}  # a damaged record: rebuild every shard
    if not same:
        raise CLIError(f"--out {out} holds a data set of other settings ({PROGRESS}); choose another --out, or "
                       "delete it to start over")
    return {k: v for k, v in done.items() if (out / _shard_name(int(k))).is_file()
            and file_sha256(out / _shard_name(int(k))) == v.get("sha256")}


@dataclass(frozen=True)
class FarmConfig:
    """One farm (module docstring): the typed form of the command's flags."""

    suite: str
    count: int
    """maps (one shard each)"""
    split: str
    """``train`` or ``test`` (:mod:`precompute.maps.worlds`)"""
    out: Path
    """the data set folder"""
    system: Any = None
    """the robot's system (None: the benchmark robot's, :data:`~precompute.worlds.robot.NAV_ROBOT`)"""
    poses_per_map: int = 1
    seed: int = 0
    horizon: int = 15
    radius: float = 0.2
    patch: tuple[int, int] = (72, 72)
    resolution: float = 0.05
    method: str = "maxflow"
    coverage: dict[str, Any] = dataclass_field(default_factory=dict)
    """the coverage builder's settings (:data:`FARM_COVERAGE` fields of :class:`CoverageConfig`)"""
    workers: int = 1
    ray_address: str | None = None
    quiet: bool = False


def build_farm(cfg: FarmConfig) -> Path:
    """Build (or resume) the data set ``cfg`` describes; its folder. A clear error (CLIError / ValueError) for bad
    settings or a folder of another data set; Ctrl-C keeps the finished shards."""
    from precompute.worlds.robot import NAV_ROBOT

    if cfg.suite not in FARM_SUITES or cfg.split not in SPLITS or cfg.method not in ("maxflow", "coverage"):
        raise CLIError(f"farm: suite {cfg.suite!r} (of {', '.join(FARM_SUITES)}), split {cfg.split!r} (of "
                       f"{', '.join(SPLITS)}) and method {cfg.method!r} (maxflow, coverage) must all be known")
    for name, value, low in (("count", cfg.count, 1), ("poses_per_map", cfg.poses_per_map, 1),
                             ("workers", cfg.workers, 1), ("horizon", cfg.horizon, 1), ("patch", min(cfg.patch), 1)):
        if value < low:
            raise CLIError(f"{flag_name(name)} must be >= {low}, got {value}")
    if not (cfg.resolution > 0 and np.isfinite(cfg.resolution)):
        raise CLIError(f"--resolution must be > 0 (m), got {cfg.resolution}")
    if not (cfg.radius >= 0 and np.isfinite(cfg.radius)):
        raise CLIError(f"--radius must be >= 0 (m), got {cfg.radius}")
    out = Path(cfg.out)
    if out.exists() and not out.is_dir():
        raise CLIError(f"--out {out}: not a folder")
    unknown = sorted(set(cfg.coverage) - set(FARM_COVERAGE))
    if unknown or (cfg.coverage and cfg.method != "coverage"):
        raise CLIError(f"coverage settings {sorted(cfg.coverage)}: only {', '.join(FARM_COVERAGE)}, and only for "
                       "--method coverage")
    try:
        CoverageConfig(**cfg.coverage)
    except ValueError as e:
        raise CLIError(f"coverage settings: {e}") from None
    system = cfg.system if cfg.system is not None else NAV_ROBOT.make_system()
    check_map_system(system)
    H, W = cfg.patch
    origin = (-W * cfg.resolution / 2, -H * cfg.resolution / 2)
    worlds = suite_worlds(cfg.suite, cfg.count, cfg.split, cfg.seed, cfg.radius)
    header = dataset_header(system, cfg.horizon, cfg.method, cfg.radius, (H, W), cfg.resolution, origin,
                            cfg.split, cfg.seed)
    if cfg.coverage:  # absent with the defaults: older farms still resume
        header["coverage"] = dict(cfg.coverage)
    spec = {"header": header, "maps": [[w.suite, w.key] for w in worlds], "poses_per_map": cfg.poses_per_map,
            "rule": SAFE_RULE}  # shards of another pruning rule are not resumed into this data set
    out.mkdir(parents=True, exist_ok=True)
    with exclusive_lock(out / ".lock", what=f"the data set {out}"):
        done = _load_progress(out, spec)
        todo = [k for k in range(len(worlds)) if str(k) not in done]
        bar = None
        if not cfg.quiet:
            from tqdm import tqdm

            bar = tqdm(total=len(worlds), initial=len(worlds) - len(todo), desc="shards", unit="map", file=sys.stdout)

        def saved(i: int, result: dict) -> None:
            done[str(todo[i])] = result
            write_json(out / PROGRESS, {"spec": spec, "done": dict(sorted(done.items(), key=lambda kv: int(kv[0])))})
            if bar is not None:
                bar.update(1)

        try:
            spec_json = json.dumps(spec)
            run_jobs(build_shard, [(spec_json, k, str(out)) for k in todo], workers=cfg.workers,
                     ray_address=cfg.ray_address, on_done=saved)
        finally:
            if bar is not None:
                bar.close()
        entries = [{**e, "shard": k, "index": i} for k in range(len(worlds)) for i, e in enumerate(done[str(k)]["entries"])]
        shards = [{"file": _shard_name(k), "sha256": done[str(k)]["sha256"], "entries": len(done[str(k)]["entries"])}
                  for k in range(len(worlds))]
        write_json(out / "dataset.json", {**header, "entries": entries, "shards": shards})
    if not cfg.quiet:
        print(f"wrote {len(entries)} entries in {len(shards)} shards to {out} ({len(todo)} built, "
              f"{len(worlds) - len(todo)} kept)")
    return out


@cli_main(interrupted="interrupted: the finished shards are kept; rerun the same command to continue")
def main(argv: Sequence[str] | None = None) -> int:
    """Build the data set from the flags ``argv`` (module docstring): 0, or 2 after one ``error:`` line."""
    args = make_parser().parse_args(sys.argv[1:] if argv is None else list(argv))
    _check(args)
    build_farm(FarmConfig(suite=args.suite, count=args.count, split=args.split, out=args.out, system=_system(args),
                          poses_per_map=args.poses_per_map, seed=args.seed, horizon=args.horizon, radius=args.radius,
                          patch=tuple(args.patch), resolution=args.resolution, method=args.method,
                          coverage=coverage_settings(args) if args.method == "coverage" else {},
                          workers=args.workers, ray_address=args.ray, quiet=args.quiet))
    return 0


if __name__ == "__main__":
    sys.exit(main())
