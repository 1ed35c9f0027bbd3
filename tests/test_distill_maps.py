"""Map-conditioned policies trained on map-table data sets (python -m training.maps.distill): the map is used,
the policy's rollouts collide less than the blind table's where a wall stands ahead, resume, bad input.

The data sets here are tiny and written by this file (format of /tmp/notes/dataset_format.md, i.e.
``cuniform-map-dataset/1``): a Dubins car of 4 steps, 24 x 24 patches of 0.1 m, and safe tables made by pruning
the blind max-flow table's cells near obstacles (then actions into pruned cells, then dead ends) -- a stand-in
for the farm's safe max-flow tables, which only the targets' exact values depend on.
"""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

import training.maps.distill as distill_maps
from cuniform_torch.envs import OccupancyGrid
from cuniform_torch.grid.cells import Grid
from cuniform_torch.maps.checkpoint import load_map_policy
from cuniform_torch.maps.encoder import PatchSpec
from cuniform_torch.maps.sensing import local_map, patch_centres
from cuniform_torch.policies.table import TablePolicy
from cuniform_torch.sampling.rollout import rollout
from cuniform_torch.systems import make_system, system_to_json
from precompute.flow.builder import BuildConfig, build_table
from precompute.maps.dataset import MapDatasetError
from training.maps.data import MapDataError, load_map_data

T = 4
SYSTEM = make_system("dubins", speed=1.0, dt=0.2, num_actions=5, max_omega=math.pi / 2,
                     cell_size=[0.1, 0.1, 2 * math.pi / 16])
SPEC = PatchSpec((24, 24), 0.1, (-1.2, -1.2))
RADIUS = 0.1
# The hand-pruned tables here are not the builder's (their cell_probs are uniform per level, their dead ends found
# from the centres): the deep checks, which recompute the builder's pruning and propagation, refuse them, so every
# read of them here trusts the files explicitly (--skip-deep-checks, deep_checks=False). The farm's own tables of
# these maps collide on the wall (cells of 0.1 m pruned at their centres), which the key test below needs to avoid.
SKIP = "--skip-deep-checks"
TRAIN = ["--hidden", "64", "--layers", "2", "--embed", "16", "--channels", "4", "--epochs", "100", "--jitter", "1",
         "--batch-size", "128", "--lr", "1e-2", "--val-fraction", "0", "--quiet", SKIP]


def rect(*boxes: tuple[float, float, float, float]) -> np.ndarray:
    """uint8 [H, W] patch with the cells whose centre lies in any box (x0, x1, y0, y1), robot frame."""
    xy = patch_centres(SPEC, torch.float64).numpy()  # [H, W, 2]
    occ = np.zeros(SPEC.shape, dtype=bool)
    for x0, x1, y0, y1 in boxes:
        occ |= (xy[..., 0] >= x0) & (xy[..., 0] < x1) & (xy[..., 1] >= y0) & (xy[..., 1] < y1)
    return occ.astype(np.uint8)


WALL = rect((0.6, 0.8, -0.2, 0.2))  # ahead of the start: going straight hits it at step 3
MAPS = [WALL, rect((0.7, 0.9, -0.25, 0.25)),  # walls ahead: turn
        rect((0.0, 1.2, 0.3, 0.5), (0.0, 1.2, -0.5, -0.3)), rect((0.0, 1.2, 0.35, 0.55), (0.0, 1.2, -0.55, -0.35))]


def inflated(patch: np.ndarray) -> np.ndarray:
    """bool [H, W]: patch cells whose centre is within RADIUS of an occupied cell's centre."""
    xy = patch_centres(SPEC, torch.float64).reshape(-1, 2)
    occ = xy[torch.from_numpy(patch.reshape(-1).astype(bool))]
    if occ.shape[0] == 0:
        return np.zeros(SPEC.shape, dtype=bool)
    return (torch.cdist(xy, occ).amin(dim=1) <= RADIUS + 1e-9).reshape(SPEC.shape).numpy()


def _keys(cells: torch.Tensor) -> torch.Tensor:
    c = cells.long() + 512
    return (c[:, 0] * 1024 + c[:, 1]) * 1024 + c[:, 2]


def safe_rows(table, patch: np.ndarray) -> dict[str, np.ndarray]:
    """One entry's rows: the blind table pruned by ``patch`` (module docstring), in the data set's dtypes."""
    grid = Grid.of(SYSTEM)
    cells = torch.from_numpy(table.cells)
    centres = grid.centers(cells)  # [C, 3]
    bad = torch.from_numpy(inflated(patch))
    i, j, inside = OccupancyGrid(bad, SPEC.origin, SPEC.resolution).cell_index(centres[:, :2])
    keep = ~(bad[i, j] & inside)
    level = torch.from_numpy(np.repeat(np.arange(T + 1), np.diff(table.level_offsets)))
    keep[level == 0] = True
    probs = torch.from_numpy(table.action_probs).double().clone()
    actions = SYSTEM.action_set(torch.float64)  # [A, 1]
    A = actions.shape[0]
    succ = grid.cells(SYSTEM.step(centres.repeat_interleave(A, 0), actions.repeat(len(cells), 1)))  # [C*A, 3]
    for t in range(T - 1, -1, -1):  # backwards: actions into removed cells go, then cells left without one
        nxt = (level == t + 1) & keep
        alive = torch.isin(_keys(succ), _keys(cells[nxt])).reshape(-1, A)  # [C, A]
        rows = level == t
        probs[rows] = probs[rows] * alive[rows]
        keep[rows & (probs.sum(dim=1) <= 0)] = False
    assert bool(keep[level == 0].all()), "the start has no safe action on this test map"
    probs = probs[keep] / probs[keep].sum(dim=1, keepdim=True)
    kept_level = level[keep]
    offsets = np.concatenate(([0], np.cumsum(np.bincount(kept_level.numpy(), minlength=T + 1))))
    return {"cells": table.cells[keep.numpy()].astype(np.int32), "level_offsets": offsets.astype(np.int64),
            "action_probs": probs.numpy().astype(np.float16),
            "cell_probs": (1.0 / np.bincount(kept_level.numpy())[kept_level.numpy()]).astype(np.float32)}


def write_dataset(folder: Path, table, patches: list[np.ndarray]) -> Path:
    """A one-shard data set of ``patches`` (each entry's start at the world origin), as the format says."""
    folder.mkdir(parents=True, exist_ok=True)
    rows = [safe_rows(table, p) for p in patches]
    counts = [len(r["cells"]) for r in rows]
    shard = {"patches": np.stack(patches).astype(np.uint8), "poses": np.zeros((len(patches), 3)),
             "entry_offsets": np.concatenate(([0], np.cumsum(counts))).astype(np.int64),
             "level_offsets": np.stack([r["level_offsets"] for r in rows]),
             **{k: np.concatenate([r[k] for r in rows]) for k in ("cells", "action_probs", "cell_probs")}}
    np.savez_compressed(folder / "shard-00000.npz", **shard)
    grid = Grid.of(SYSTEM)
    meta = {"format": "cuniform-map-dataset/1", "system": system_to_json(SYSTEM, T), "horizon": T,
            "method": "maxflow", "grid": {"cell_size": list(grid.cell_size), "cell_offset": list(grid.offset),
                                          "periodic": list(grid.periodic)},
            "actions": SYSTEM.action_set().tolist(), "radius": RADIUS, "patch": SPEC.to_dict(), "split": "train",
            "seed": 0, "entries": [{"source": f"test:{k}", "pose": [0.0, 0.0, 0.0], "shard": 0, "index": k}
                                   for k in range(len(patches))],
            "shards": [{"file": "shard-00000.npz", "entries": len(patches),
                        "sha256": hashlib.sha256((folder / "shard-00000.npz").read_bytes()).hexdigest()}]}
    (folder / "dataset.json").write_text(json.dumps(meta))
    return folder


pytestmark = pytest.mark.usefixtures("restore_threads")  # conftest: main sets torch's thread count


@pytest.fixture(scope="module")
def table():
    return build_table(SYSTEM, BuildConfig(horizon=T))[0]


@pytest.fixture(scope="module")
def dataset(table, tmp_path_factory) -> Path:
    return write_dataset(tmp_path_factory.mktemp("maps") / "walls", table, MAPS)


@pytest.fixture(scope="module")
def trained(dataset, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("policy") / "walls.map_policy.pt"
    assert distill_maps.main(["--maps", str(dataset), "--out", str(out), "--logdir", str(out.parent / "runs"),
                              *TRAIN]) == 0
    return out


def collision_rate(states: torch.Tensor, patch: np.ndarray) -> float:
    """Share of rollouts ``[N, T+1, 3]`` (start frame) with a state at steps 1..T within RADIUS of an obstacle."""
    grid = OccupancyGrid(torch.from_numpy(inflated(patch)), SPEC.origin, SPEC.resolution)
    return float(grid.contains(states[:, 1:, :2].float()).any(dim=1).float().mean())


def test_the_data_set_reads_back(dataset, table):
    data = load_map_data([dataset], deep_checks=False)
    assert data.num_entries == len(MAPS) and data.spec == SPEC and data.horizon == T
    assert torch.allclose(data.probs.sum(dim=1), torch.ones(data.probs.shape[0]))
    assert data.centres.shape[0] < len(MAPS) * len(table.cells)  # cells were pruned


def wall_collision_rates(policy, table) -> tuple[float, float]:
    """Collision rates with the wall ahead of 2000 rollouts of ``policy`` (its map set to the wall) and of the
    blind ``table``, from the origin with one seed."""
    world = OccupancyGrid(torch.from_numpy(WALL.astype(bool)), SPEC.origin, SPEC.resolution)
    policy.set_map(local_map(world, torch.zeros(3), SPEC))
    x0 = torch.zeros(3)
    mine, _ = rollout(SYSTEM, policy, x0, 2000, T, torch.Generator().manual_seed(0))
    blind, _ = rollout(SYSTEM, TablePolicy(table), x0, 2000, T, torch.Generator().manual_seed(0))
    return collision_rate(mine, WALL), collision_rate(blind, WALL)


def test_a_trained_policy_avoids_the_wall_the_blind_table_hits(trained, table):
    """The key test: rollouts of the map policy for the wall ahead collide far less than the blind table's."""
    policy = load_map_policy(trained)
    rate_map, rate_blind = wall_collision_rates(policy, table)
    print(f"collision rate: map policy {rate_map:.3f}, blind table {rate_blind:.3f}")
    assert rate_blind > 0.3
    assert rate_map < 0.5 * rate_blind  # map zeroed in the encoder: 0.53 of 0.63; with the map: about 0.2
    assert policy.miss_rate == 0.0


def test_map_eval_measures_the_same_on_the_data_set(trained, dataset, table, tmp_path, capsys):
    """python -m training.maps.evaluate: per entry, the map policy against the blind table and the safe table."""
    import training.maps.evaluate as map_eval
    from cuniform_torch.tables.file import write_table
    write_table(tmp_path / "blind.npz", table)
    out = tmp_path / "rates.json"
    assert map_eval.main([SKIP, "--checkpoint", str(trained), "--maps", str(dataset), "--table",
                          str(tmp_path / "blind.npz"),
                          "--samples", "500", "--json", str(out)]) == 0
    rates = json.loads(out.read_text())["rates"]
    assert rates["blind_table"][0] > 0.3 and rates["map_policy"][0] < 0.5 * rates["blind_table"][0]
    assert rates["safe_table"][0] < 0.1  # the pruned table itself (dead ends removed)
    assert "mean over 4 entries" in capsys.readouterr().out


def test_two_maps_give_different_probabilities(trained, dataset):
    """At the start, a wall ahead (turn hard) and a corridor (mostly straight): each map gets its own row."""
    policy, data = load_map_policy(trained), load_map_data([dataset], deep_checks=False)
    x = torch.zeros(1, 3)
    probs, targets = [], []
    for k in (0, 2):
        policy.set_map(OccupancyGrid(torch.from_numpy(MAPS[k].astype(bool)), SPEC.origin, SPEC.resolution))
        probs.append(policy.action_probs(x, 0)[0])
        targets.append(data.probs[(data.entry == k) & (data.level == 0)][0])
    assert float((targets[0] - targets[1]).abs().sum()) > 0.5  # the two safe tables differ at the start
    assert float((probs[0] - probs[1]).abs().sum()) > 0.5, probs
    for p, q in zip(probs, targets):
        assert float((p - q).abs().sum()) < 0.25, (p, q)


def test_training_resumes_to_the_same_weights(dataset, tmp_path):
    """An interrupted run (Ctrl-C after 2 of 4 epochs) resumed with --resume ends at the uninterrupted weights."""
    args = ["--maps", str(dataset), "--logdir", str(tmp_path / "runs"), *TRAIN, "--val-fraction", "0.25"]
    args[args.index("--epochs") + 1] = "4"
    full, cut = tmp_path / "full.pt", tmp_path / "cut.pt"
    assert distill_maps.main([*args, "--out", str(full)]) == 0
    original, calls = distill_maps.Trainer.epoch, {"n": 0}

    def epoch_then_stop(self, gen):
        calls["n"] += 1
        if calls["n"] > 2:
            raise KeyboardInterrupt("stopped")
        return original(self, gen)

    distill_maps.Trainer.epoch = epoch_then_stop
    try:
        assert distill_maps.main([*args, "--out", str(cut)]) == 130
    finally:
        distill_maps.Trainer.epoch = original
    assert not cut.exists()
    assert torch.load(cut.with_name(cut.name + ".train.pt"), weights_only=True)["epoch"] == 2
    assert distill_maps.main([*args, "--out", str(cut), "--resume"]) == 0
    a, b = torch.load(full, weights_only=True), torch.load(cut, weights_only=True)
    for key in a["state_dict"]:
        assert torch.equal(a["state_dict"][key], b["state_dict"][key]), key
    assert a["metrics"]["best_epoch"] == b["metrics"]["best_epoch"]


def test_a_resume_with_other_settings_is_refused(dataset, tmp_path, capsys):
    args = ["--maps", str(dataset), "--out", str(tmp_path / "p.pt"), "--logdir", str(tmp_path / "runs"), "--quiet",
            SKIP, "--epochs", "1", "--hidden", "8", "--embed", "4", "--channels", "2", "--val-fraction", "0"]
    assert distill_maps.main(args) == 0
    assert distill_maps.main([*args[:-6], "--hidden", "16", "--embed", "4", "--channels", "2", "--val-fraction",
                              "0", "--resume"]) == 2
    assert "hidden: saved 8, now 16" in capsys.readouterr().err


def test_data_sets_of_other_patches_are_not_pooled(dataset, table, tmp_path):
    meta = json.loads((dataset / "dataset.json").read_text())
    other = write_dataset(tmp_path / "other", table, MAPS[:1])
    changed = json.loads((other / "dataset.json").read_text())
    # another patch of the same world: one more free cell on every side, so every table still fits its patch
    with np.load(other / "shard-00000.npz") as z:
        shard = {k: z[k] for k in z.files}
    shard["patches"] = np.pad(shard["patches"], ((0, 0), (1, 1), (1, 1)))
    np.savez_compressed(other / "shard-00000.npz", **shard)
    H, W = shard["patches"].shape[1:]
    res = changed["patch"]["resolution"]
    changed["patch"].update(shape=[H, W], origin=[-W * res / 2, -H * res / 2])
    changed["shards"][0]["sha256"] = hashlib.sha256((other / "shard-00000.npz").read_bytes()).hexdigest()
    (other / "dataset.json").write_text(json.dumps(changed))
    assert meta["patch"] != changed["patch"]
    with pytest.raises(MapDataError, match="its patch differs"):
        load_map_data([dataset, other], deep_checks=False)


def test_broken_data_sets_are_one_clear_error(dataset, tmp_path, capsys):
    import shutil
    bad = tmp_path / "bad"
    shutil.copytree(dataset, bad)
    shard = bad / "shard-00000.npz"
    shard.write_bytes(shard.read_bytes()[:-10])
    with pytest.raises(MapDatasetError, match="sha256 does not match"):
        load_map_data([bad])
    assert distill_maps.main(["--maps", str(bad), "--out", str(tmp_path / "x.pt"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "sha256" in err and len(err.splitlines()) == 1
    assert distill_maps.main(["--maps", str(tmp_path / "nowhere"), "--out", str(tmp_path / "x.pt")]) == 2
    assert "no map-table data set" in capsys.readouterr().err
