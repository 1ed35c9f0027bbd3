"""Rebuild a shipped pretrained map policy from scratch:  python -m training.maps.pretrained [--workers 2]

One command for the whole recipe of a policy that ships with the package (:mod:`cuniform_torch.maps.pretrained`):
the map-table farms of its data (the train splits only: BARN's shipped half, forests, clutter), then the training,
then the shipped file and its model card. Every stage resumes: a farm keeps its finished shards, the training its
last epoch (``training.maps.distill --resume``), so an interrupted run continues where it stopped.

Outputs: the data sets and the training run under ``--work`` (default ``out/pretrained/<name>``); with
``--install`` the checkpoint and its card are copied into ``cuniform_torch/maps/weights/`` (what the package
ships); without it they stay in ``--work``. ``--quick`` runs the same pipeline at toy sizes (a smoke test: its
policy is not one to ship).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import shutil
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cuniform_torch.common.fileio import MAX_JSON_BYTES, read_capped_text, write_json
from cuniform_torch.maps.checkpoint import load_map_policy
from cuniform_torch.maps.pretrained import CARD_FORMAT, PRETRAINED_DIR
from precompute.cli import ArgumentParser, CLIError, cli_main, int_in
from precompute.maps.farm import FarmConfig, build_farm
from precompute.worlds.robot import NAV_ROBOT, RobotPreset, preset_dict
from training.maps.data import dataset_digest
from training.maps.distill import MapDistillConfig, distill_maps

__all__ = ["Farm", "Recipe", "RECIPES", "rebuild", "main"]


@dataclass(frozen=True)
class Farm:
    """One data set of a recipe: ``count`` train maps of ``suite``, ``poses`` start poses each."""

    suite: str
    count: int
    poses: int
    seed: int = 0


@dataclass(frozen=True)
class Recipe:
    """Everything that makes a shipped policy: the robot, the data, the training settings."""

    name: str
    robot: RobotPreset
    farms: tuple[Farm, ...]
    coverage: dict[str, Any]
    """the farms' coverage-method settings (coverage tables: the builder that keeps each map's free space)"""
    distill: dict[str, Any]
    """:class:`~training.maps.distill.MapDistillConfig` fields"""


RECIPES: dict[str, Recipe] = {r.name: r for r in [
    Recipe(
        name="unicycle-0.5",
        robot=NAV_ROBOT,  # 0.5 m/s, 7 turn rates in [-1.5, 1.5] rad/s, dt 0.2 s, r = 0.2 m, horizon 15
        farms=(Farm("barn", 10, 3, seed=0), Farm("forest", 10, 3, seed=1), Farm("clutter", 6, 3, seed=0)),
        coverage=dict(tol=1e-3, state_budget=400_000, merge_resolution=16),
        distill=dict(local_features=4, hidden=64, epochs=3, jitter=1, val_fraction=0.1, seed=0),
    ),
]}
"""the shipped policies' recipes, by name"""


def _quick(recipe: Recipe) -> Recipe:
    farms = tuple(dataclasses.replace(f, count=1, poses=2) for f in recipe.farms[:2])
    return dataclasses.replace(recipe, farms=farms, coverage={**recipe.coverage, "state_budget": 100_000},
                               distill={**recipe.distill, "epochs": 1, "val_fraction": 0.5})


def rebuild(recipe: Recipe, work: Path, workers: int = 1, ray_address: str | None = None, install: bool = False,
            quiet: bool = False) -> Path:
    """Farms, training, card (module docstring); the checkpoint's path (in the package with ``install``)."""
    work = Path(work)
    robot = recipe.robot
    system = robot.make_system()
    t0 = time.perf_counter()
    folders = []
    for farm in recipe.farms:
        folder = work / f"{farm.suite}-train-{farm.count}x{farm.poses}-s{farm.seed}"
        if not quiet:
            print(f"== farm {folder.name}", flush=True)
        build_farm(FarmConfig(suite=farm.suite, count=farm.count, split="train", out=folder, system=system,
                              poses_per_map=farm.poses, seed=farm.seed, horizon=robot.horizon, radius=robot.radius,
                              method="coverage", coverage=recipe.coverage, workers=workers, ray_address=ray_address,
                              quiet=quiet))
        folders.append(folder)
    farm_seconds = time.perf_counter() - t0
    checkpoint = work / f"{recipe.name}.map_policy.pt"
    if not quiet:
        print(f"== training {checkpoint}", flush=True)
    resume = checkpoint.with_name(checkpoint.name + ".train.pt").exists()
    distill_maps(MapDistillConfig(maps=[str(f) for f in folders], out=str(checkpoint), logdir=str(work / "runs"),
                                  quiet=quiet, resume=resume, threads=max(1, workers), **recipe.distill))
    card = model_card(recipe, checkpoint, folders, farm_seconds)
    write_json(work / f"{recipe.name}.json", card)
    if not install:
        return checkpoint
    PRETRAINED_DIR.mkdir(exist_ok=True)
    target = PRETRAINED_DIR / checkpoint.name
    shutil.copyfile(checkpoint, target)
    write_json(PRETRAINED_DIR / f"{recipe.name}.json", card)
    if not quiet:
        print(f"installed {target} ({target.stat().st_size / 1024:.0f} KiB) and its card", flush=True)
    return target


def model_card(recipe: Recipe, checkpoint: Path, folders: Sequence[Path], farm_seconds: float) -> dict[str, Any]:
    """The card the runtime checks a shipped file against, and the docs print: robot, data, training, digests."""
    load_map_policy(str(checkpoint))  # validated (digest, shapes, weights) before it is described
    metrics = dict(_load_policy_dict(checkpoint).get("metrics", {}))
    data = []
    for farm, folder in zip(recipe.farms, folders):
        head = json.loads(read_capped_text(Path(folder) / "dataset.json", MAX_JSON_BYTES, "the data-set manifest"))
        data.append({"suite": farm.suite, "split": "train", "maps": farm.count, "poses_per_map": farm.poses,
                     "seed": farm.seed, "entries": len(head["entries"]), "method": head["method"],
                     "keys": sorted({e["source"] for e in head["entries"]}), "dataset_sha256": dataset_digest(folder)})
    raw = checkpoint.read_bytes()
    return {
        "format": CARD_FORMAT, "name": recipe.name, "robot": preset_dict(recipe.robot),
        "file": checkpoint.name, "file_sha256": hashlib.sha256(raw).hexdigest(), "bytes": len(raw),
        "data": data, "split_rule": "train maps only: BARN map ids, forest and clutter seeds not divisible by 5",
        "coverage": recipe.coverage, "training": {**recipe.distill, **metrics},
        "farm_seconds_this_run": round(farm_seconds, 1),
    }


def _load_policy_dict(path: Path) -> dict:
    import torch

    return torch.load(path, map_location="cpu", weights_only=True)


def make_parser() -> ArgumentParser:
    p = ArgumentParser(prog="python -m training.maps.pretrained", description=__doc__.splitlines()[0])
    p.add_argument("--name", default="unicycle-0.5", choices=sorted(RECIPES), help="which shipped policy")
    p.add_argument("--work", type=Path, default=None, help="folder of the data sets and the run "
                                                          "(default: out/pretrained/<name>)")
    p.add_argument("--workers", type=int_in(1, 1024), default=1, help="farm shards built in parallel processes")
    p.add_argument("--ray", nargs="?", const="local", default=None, metavar="ADDRESS",
                   help="farm shards as Ray tasks (a local runtime, or the cluster at ADDRESS)")
    p.add_argument("--install", action="store_true", help="copy the result into the package (what ships)")
    p.add_argument("--quick", action="store_true", help="toy sizes: a smoke test of the pipeline (never --install)")
    p.add_argument("--quiet", action="store_true")
    return p


@cli_main(interrupted="interrupted: the finished shards and epochs are kept; rerun the same command to continue")
def main(argv: Sequence[str] | None = None) -> int:
    args = make_parser().parse_args(sys.argv[1:] if argv is None else list(argv))
    if args.quick and args.install:
        raise CLIError("--quick builds a toy policy: it is never installed (drop --install)")
    recipe = RECIPES[args.name]
    if args.quick:
        recipe = _quick(recipe)
    work = args.work or Path("out") / "pretrained" / (recipe.name + ("-quick" if args.quick else ""))
    path = rebuild(recipe, work, args.workers, args.ray, args.install, args.quiet)
    print(f"wrote {path} and its card {work / (recipe.name + '.json')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
