"""The narrow-passage suite (precompute.worlds.suites.narrow) and its faster robot (precompute.worlds.robot.FAST_ROBOT).

Seeded and reproducible, a train / test split like the forest's, every task reachable (checked here by the flood fill
again and by reading each passage's width off the raw walls), passages within the declared widths and turns, and the
benchmark driving the suite with the fast robot.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from precompute.worlds.geometry import reachable
from precompute.worlds.robot import FAST_ROBOT, NAV_ROBOT, suite_robot
from precompute.worlds.suites import NARROW_TURNS, NARROW_WIDTHS, SuiteError, make_suite, narrow
from precompute.worlds.tasks import make_task, make_tasks, split_of

COUNT = 10
R = FAST_ROBOT.radius


@pytest.fixture(scope="module")
def tasks():
    return make_tasks("narrow", R, count=2 * COUNT)


def _passages_from_walls(task) -> np.ndarray:
    """``[P, 3]`` (front x, centre y, width) read off the raw walls: wall rows 2 .. 2 + P are below each passage,
    the next P above it (the generator's layout); the width is the gap between the two, not the recorded value."""
    n = task.params["num_passages"]
    below, above = task.walls[2:2 + n], task.walls[2 + n:2 + 2 * n]  # [P, 4] each
    assert np.array_equal(below[:, 0], above[:, 0]) and np.array_equal(below[:, 2], above[:, 2])  # one wall each
    return np.stack((below[:, 0], (below[:, 3] + above[:, 1]) / 2, above[:, 1] - below[:, 3]), axis=1)


def test_the_same_seed_gives_the_same_tasks(tasks):
    again = make_tasks("narrow", R, count=2 * COUNT)
    assert [t.task_id for t in again] == [t.task_id for t in tasks] == list(range(2 * COUNT))
    for a, b in zip(tasks, again):
        assert np.array_equal(a.walls, b.walls) and a.params == b.params and a.goal == b.goal
    assert not np.array_equal(tasks[0].walls, tasks[1].walls)  # seeds differ
    one = make_task("narrow", 7, R)
    assert np.array_equal(one.walls, tasks[7].walls)


def test_train_and_test_are_disjoint_and_cover_the_seeds():
    split = {s: make_tasks("narrow", R, count=COUNT, split=s) for s in ("train", "test")}
    ids = {s: [t.task_id for t in split[s]] for s in split}
    for s in split:
        assert len(ids[s]) == COUNT and {split_of(i) for i in ids[s]} == {s}
    assert not set(ids["train"]) & set(ids["test"])
    assert ids["test"] == [5 * k for k in range(COUNT)]  # every fifth seed, as the forest's
    upto = max(ids["train"]) + 1
    assert sorted(i for s in ids for i in ids[s] if i < upto) == list(range(upto))


def test_every_task_is_reachable_and_free_at_start_and_goal():
    """Checked here on the generator's tasks, not through make_tasks (which validates them again)."""
    for task in (narrow(seed) for seed in range(2 * COUNT)):
        assert reachable(task.environment, task.start[:2], task.goal, 0.05), task.task_id
        ends = torch.tensor([task.start[:2], task.goal], dtype=torch.float64)
        assert not task.environment.in_collision(ends).any()


def test_passages_are_narrow_and_off_the_line_through_the_last_one(tasks):
    lo, hi = NARROW_WIDTHS
    assert 1.5 * 2 * R - 1e-12 <= lo and hi <= 2.0 * 2 * R + 1e-12  # 1.5-2x the fast robot's width
    widths, turns = [], []
    for task in tasks:
        got = _passages_from_walls(task)  # [P, 3]
        assert np.allclose(got, np.array(task.params["passages"]), atol=1e-12)
        widths += got[:, 2].tolist()
        run = np.full(len(got), task.params["spacing"] - task.params["thickness"])
        run[0] = got[0, 0] - task.start[0]
        dy = np.diff(np.concatenate(([task.start[1]], got[:, 1])))  # [P]
        turns += np.degrees(np.arctan2(np.abs(dy), run)).tolist()
        y_room = task.params["corridor"] / 2 - got[:, 2] / 2
        assert (np.abs(got[:, 1]) <= y_room).all()  # every passage inside the corridor
    assert lo - 1e-12 <= min(widths) and max(widths) <= hi + 1e-12
    assert NARROW_TURNS[0] - 1e-9 <= min(turns) and max(turns) <= NARROW_TURNS[1] + 1e-9
    assert max(widths) - min(widths) > 0.1 and max(turns) - min(turns) > 10  # several widths and angles


def test_bad_parameters_are_one_clear_error():
    with pytest.raises(SuiteError, match="wider than the robot"):
        narrow(0, widths=(0.3, 0.5), robot_radius=0.2)
    with pytest.raises(SuiteError, match="widen it"):
        narrow(0, turns=(10.0, 60.0))
    with pytest.raises(SuiteError, match="free run"):
        narrow(0, spacing=0.6, thickness=0.4)
    with pytest.raises(SuiteError, match="min <= max"):
        narrow(0, widths=(0.8, 0.6))
    with pytest.raises(SuiteError, match="seed must be >= 0"):
        narrow(-1)


def test_make_suite_makes_narrow_tasks_from_consecutive_seeds():
    assert [t.suite for t in make_suite("narrow", 2, seed=3)] == ["narrow"] * 2
    assert [t.task_id for t in make_suite("narrow", 2, seed=3)] == [3, 4]


def test_the_benchmark_drives_narrow_with_the_fast_robot():
    from eval.navigate.run import NavConfig, _robot, make_parser
    from precompute.cli import dataclass_from_args

    assert suite_robot("narrow") is FAST_ROBOT and suite_robot("forest") is NAV_ROBOT
    assert FAST_ROBOT.params["speed"] == 2 * NAV_ROBOT.params["speed"]
    assert FAST_ROBOT.fingerprint() != NAV_ROBOT.fingerprint()  # its own tables
    # the lattice scaled by two: a step covers as many cells as the built-in robot's
    fast, slow = (r.params["speed"] * r.params["dt"] / r.params["cell_size"][0] for r in (FAST_ROBOT, NAV_ROBOT))
    assert math.isclose(fast, slow)
    p = make_parser()
    for suite, want in (("narrow", FAST_ROBOT), ("forest", NAV_ROBOT)):
        args = p.parse_args(["--suite", suite])
        assert _robot(args, dataclass_from_args(NavConfig, args)) == want


# ------------------------------------------------------------------------------------------------ the fast robot's tables

@pytest.mark.parametrize("method", ["maxflow", "coverage"])
def test_the_fast_robots_tables_ship_and_are_used_without_building(method, tmp_path, monkeypatch):
    import precompute.build  # noqa: F401  (imported first: it binds the real build_table_file, not the patch below)
    import precompute.one_table as one_table
    from cuniform_torch.tables.file import read_table
    from eval.navigate.robot_files import SHIPPED_DIR, SHIPPED_ROBOTS, ensure_table, shipped_table

    assert FAST_ROBOT in SHIPPED_ROBOTS
    path = shipped_table(FAST_ROBOT, method)  # size and sha256 checked against the manifest
    assert path is not None and path.parent == SHIPPED_DIR and path != shipped_table(NAV_ROBOT, method)
    table = read_table(path, graph=False)  # the reader checks the content digest
    assert table.method == method and table.horizon == FAST_ROBOT.horizon
    assert json.loads(table.system)["params"]["speed"] == FAST_ROBOT.params["speed"]

    def refuse(job):
        raise AssertionError(f"built {job.out}")

    monkeypatch.setattr(one_table, "build_table_file", refuse)
    assert ensure_table(FAST_ROBOT, tmp_path, method) == path
    assert list(tmp_path.iterdir()) == []


def test_shipping_one_robot_keeps_the_other_robots_tables(tmp_path):
    from dataclasses import replace

    from eval.navigate.robot_files import ship_tables, shipped_table

    slow, fast = replace(NAV_ROBOT, horizon=4), replace(FAST_ROBOT, horizon=4)  # 4-step tables: under a second
    ship_tables(slow, tmp_path, ["maxflow"])
    manifest = ship_tables(fast, tmp_path, ["maxflow"])
    assert [e["fingerprint"] for e in manifest["tables"]] == [slow.fingerprint(), fast.fingerprint()]
    first = shipped_table(slow, "maxflow", tmp_path)
    manifest = ship_tables(slow, tmp_path, ["maxflow"])  # reshipping one robot replaces only its entry
    assert [e["fingerprint"] for e in manifest["tables"]] == [fast.fingerprint(), slow.fingerprint()]
    assert shipped_table(fast, "maxflow", tmp_path) is not None and shipped_table(slow, "maxflow", tmp_path) == first
    assert sorted(p.name for p in tmp_path.glob("*.npz")) == sorted(e["file"] for e in manifest["tables"])
