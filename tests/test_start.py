"""Tables built from a start other than the zero state (``--start``, ``BuildConfig.start``)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from cuniform_torch import TablePolicy, make_system, read_table, write_table
from cuniform_torch.common.fileio import write_npz
from cuniform_torch.tables import TableError
from precompute.build import main as build_main
from precompute.coverage.method import CoverageConfig, build_coverage_table
from precompute.flow.builder import BuildConfig, build_table


@pytest.mark.parametrize("method", ["maxflow", "coverage"])
def test_walk_table_from_a_start_is_recorded_and_serves_that_start(method, tmp_path, start_warnings):
    walk = make_system("random_walk_1d")
    if method == "maxflow":
        table, _ = build_table(walk, BuildConfig(horizon=4, start=(0.3,)))
    else:
        table, _ = build_coverage_table(walk, CoverageConfig(horizon=4, steps=5, start=(0.3,)))
    cell = int(np.round(0.3 / walk.cell_size[0] + walk.cell_offset[0]))
    assert table.cells[0].tolist() == [cell] and cell != 0
    np.testing.assert_array_equal(table.start, [0.3])
    write_table(tmp_path / "t.npz", table)
    back = read_table(tmp_path / "t.npz")
    np.testing.assert_array_equal(back.start, [0.3])
    policy = TablePolicy(back)
    assert policy.build_start.tolist() == [0.3]
    assert start_warnings(policy, [0.3]) == [] and policy.miss_rate == 0.0
    assert len(start_warnings(TablePolicy(back), [0.0])) == 1  # the zero state is now the wrong start


def test_zero_start_table_is_unchanged():
    walk = make_system("random_walk_1d")
    plain, _ = build_table(walk, BuildConfig(horizon=3))
    explicit, _ = build_table(walk, BuildConfig(horizon=3, start=(0.0,)))
    assert plain.start is None
    np.testing.assert_array_equal(plain.cells, explicit.cells)
    np.testing.assert_array_equal(plain.action_probs, explicit.action_probs)


def test_ks_speed_table_from_a_speed_serves_every_pose_at_that_speed(start_warnings):
    ks = make_system("ks_speed")
    d = len(ks.periodic)
    start = (0.0, 0.0, 0.0) + (0.5,) + (0.0,) * (d - 4)
    table, _ = build_table(ks, BuildConfig(horizon=3, start=start))
    policy = TablePolicy(table)
    pose = (1.0, -2.0, 2.5) + start[3:]
    assert start_warnings(policy, list(pose)) == [] and policy.miss_rate < 0.05
    zero_speed = TablePolicy(build_table(ks, BuildConfig(horizon=3))[0])
    assert len(start_warnings(zero_speed, list(pose))) == 1


def test_pose_start_of_an_se2_system_is_refused(capsys, tmp_path):
    with pytest.raises(ValueError, match="SE\\(2\\)-invariant.*x, y, theta must be 0"):
        build_table(make_system("dubins"), BuildConfig(horizon=2, start=(1.0, 0.0, 0.0)))
    assert build_main(["--system", "dubins", "--start", "0", "0", "0.5", "--horizon", "2", "--quiet",
                       "--out", str(tmp_path / "t.npz")]) == 2
    assert "x, y, theta must be 0" in capsys.readouterr().err
    with pytest.raises(ValueError, match="needs 1 numbers"):
        build_table(make_system("random_walk_1d"), BuildConfig(horizon=2, start=(0.1, 0.2)))
    with pytest.raises(ValueError, match="finite"):
        BuildConfig(start=(float("nan"),))


def test_a_start_that_does_not_match_level_0_is_refused(tmp_path):
    table, _ = build_table(make_system("random_walk_1d"), BuildConfig(horizon=2, start=(0.3,)))
    write_npz(tmp_path / "moved.npz", replace(table, start=np.array([2.0])).to_arrays())  # write_table would refuse
    with pytest.raises(TableError, match="level 0 must be the single start cell"):
        read_table(tmp_path / "moved.npz")
    write_npz(tmp_path / "shape.npz", replace(table, start=np.array([0.3, 0.0])).to_arrays())
    with pytest.raises(TableError, match="start"):
        read_table(tmp_path / "shape.npz")
