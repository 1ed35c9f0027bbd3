"""Collision rates of a map policy's rollouts against the blind table's and the data set's safe tables':
python -m training.maps.evaluate --checkpoint FILE --maps DATASET --table BLIND.npz

For every entry of the data set (its patch, robot at the origin of the start frame): ``--samples`` rollouts of the
map policy (map set once), of the blind table, and of the entry's own safe table (its rows, as a table), each
from the origin with one seed. A rollout *collides* when a state at steps 1..T lies within the data set's robot
radius of an occupied patch cell's centre (the farm's pruning rule, measured at the continuous states); the
share of colliding rollouts is printed per entry and averaged over the entries. It is the measured form of
tests/test_distill_maps.py's key test on real farm data.
"""

from __future__ import annotations

import dataclasses
import json
import sys
from collections.abc import Sequence

import numpy as np
import torch

from cuniform_torch.envs import OccupancyGrid
from cuniform_torch.maps.checkpoint import load_map_policy
from cuniform_torch.maps.policy import MapPolicy
from cuniform_torch.maps.sensing import patch_centres
from cuniform_torch.policies.table import TablePolicy
from cuniform_torch.sampling.rollout import rollout
from cuniform_torch.tables.file import Table, read_table
from precompute.cli import (
    ArgumentParser,
    CLIError,
    check_output_file,
    cli_main,
    int_in,
    non_negative_int,
    positive_int,
)
from precompute.maps.dataset import MapDataset, read_map_dataset


def inflated(patch: np.ndarray, spec, radius: float) -> OccupancyGrid:
    """The patch's cells within ``radius`` of an occupied cell's centre, as a grid in the start frame."""
    xy = patch_centres(spec, torch.float64).reshape(-1, 2)  # [H W, 2]
    occ = xy[torch.from_numpy(patch.reshape(-1).astype(bool))]
    near = torch.zeros(xy.shape[0], dtype=torch.bool)
    for lo in range(0, occ.shape[0], 4096):  # chunks of occupied cells bound the distance matrix's memory
        near |= torch.cdist(xy, occ[lo:lo + 4096]).amin(dim=1) <= radius + 1e-9
    return OccupancyGrid(near.reshape(spec.shape), spec.origin, spec.resolution)


def collision_rate(states: torch.Tensor, grid: OccupancyGrid) -> float:
    """Share of rollouts ``[N, T+1, d]`` with a state at steps 1..T in ``grid``."""
    return float(grid.contains(states[:, 1:, :2].float()).any(dim=1).float().mean())


def add_input_args(parser: ArgumentParser) -> None:
    """The three inputs of map_eval and map_coverage: ``--checkpoint``, ``--maps``, ``--table`` (read by
    :func:`load_inputs`), and ``--skip-deep-checks``."""
    parser.add_argument("--checkpoint", required=True, help="the map policy (cuniform-map-policy/1)")
    parser.add_argument("--maps", required=True, help="a data set folder (cuniform-map-dataset/1)")
    parser.add_argument("--table", required=True, help="the blind table of the same system and horizon")
    parser.add_argument("--skip-deep-checks", action="store_true",
                        help="trust the data set's action rows: skip recomputing every table's propagation (rows "
                             "permuted within a level then go unnoticed; the other checks still run)")


def check_entries(entries: int, ds: MapDataset, maps: str) -> int:
    """How many entries ``--entries`` asks for (0: all); CLIError when the data set has fewer (never clamped)."""
    if entries > len(ds):
        raise CLIError(f"--entries {entries}: the data set {maps} has {len(ds)} entries (0: all)")
    return entries or len(ds)


def make_parser() -> ArgumentParser:
    parser = ArgumentParser(prog="python -m training.maps.evaluate", description=__doc__.splitlines()[0])
    add_input_args(parser)
    parser.add_argument("--samples", type=positive_int, default=1000, help="rollouts per entry and method")
    parser.add_argument("--entries", type=non_negative_int, default=0, help="first entries only (0: all)")
    parser.add_argument("--seed", type=int_in(0, 2**63 - 1), default=0)
    parser.add_argument("--json", default=None, help="also write the rates here")
    return parser


@cli_main()
def main(argv: Sequence[str] | None = None) -> int:
    args = make_parser().parse_args(argv)
    if args.json:
        check_output_file(args.json, "--json", "map_eval.json")
    policy, ds, blind = load_inputs(args.checkpoint, args.maps, args.table, deep_checks=not args.skip_deep_checks)
    total = check_entries(args.entries, ds, args.maps)
    spec, system, T = policy.patch_spec, policy.system, policy.horizon
    blind_policy, x0 = TablePolicy(blind), torch.zeros(len(system.periodic))
    rates = {"map_policy": [], "blind_table": [], "safe_table": []}
    for k, entry in enumerate(ds):
        if k >= total:
            break
        grid = inflated(entry.patch, spec, ds.radius)
        policy.set_map(OccupancyGrid(torch.from_numpy(entry.patch.astype(bool)), spec.origin, spec.resolution))
        safe = dataclasses.replace(blind, cells=entry.cells.astype(np.int64), level_offsets=entry.level_offsets,
                                   action_probs=entry.action_probs.astype(np.float32),
                                   cell_probs=entry.cell_probs.astype(np.float64),
                                   flow_value=np.zeros(T, np.int64), flow_target=np.zeros(T, np.int64))
        row = []
        for name, p in (("map_policy", policy), ("blind_table", blind_policy), ("safe_table", TablePolicy(safe))):
            states, _ = rollout(system, p, x0, args.samples, T, torch.Generator().manual_seed(args.seed))
            rates[name].append(collision_rate(states, grid))
            row.append(f"{name} {rates[name][-1]:.3f}")
        print(f"entry {k:3d} ({entry.source}): " + ", ".join(row), flush=True)
    means = {name: float(np.mean(v)) for name, v in rates.items()}
    print(f"mean over {len(rates['map_policy'])} entries: " + ", ".join(f"{n} {m:.3f}" for n, m in means.items())
          + f"; map policy miss rate {policy.miss_rate:.3f}")
    if args.json:
        from cuniform_torch.common.fileio import write_json
        write_json(args.json, {"rates": rates, "means": means, "samples": args.samples})
    return 0


def load_inputs(checkpoint: str, maps: str, table: str,
                deep_checks: bool = True) -> tuple[MapPolicy, MapDataset, Table]:
    """The map policy, the data set and the blind table, read and checked to share one system JSON (horizon
    included); ValueError naming the files otherwise. Shared with :mod:`training.maps.coverage`. ``deep_checks``:
    each shard, when read, has its tables' propagation recomputed too (``verify_all``; permuted action rows)."""
    policy = load_map_policy(checkpoint)
    ds = read_map_dataset(maps, verify_all=deep_checks)
    blind = read_table(table, graph=False)
    want = json.loads(ds.meta["system"])
    for path, kind, system in ((checkpoint, "map policy", _checkpoint_system(checkpoint)),
                               (table, "table", blind.system)):
        if json.loads(system) != want:  # name the file that differs: the three must share the system JSON
            raise ValueError(f"{path} is a {kind} of another system than the data set {maps} ({system} against "
                             f"{ds.meta['system']}): {table}, {maps} and {checkpoint} must share the system JSON")
    return policy, ds, blind


def _checkpoint_system(path: str) -> str:
    return torch.load(path, map_location="cpu", weights_only=True)["system"]


if __name__ == "__main__":
    sys.exit(main())
