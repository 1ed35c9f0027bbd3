"""Table sets: ``python -m precompute.build --starts SPEC --out DIR`` (precompute/table_set.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from cuniform_torch import make_system, read_table
from precompute.build import main
from precompute.table_set import parse_starts

WALK = ["--system", "random_walk_1d", "--horizon", "4", "--quiet"]


def _build(folder, *extra) -> int:
    return main([*WALK, "--starts", "0=-1:1:5", "--out", str(folder), *extra])


def _tables(folder) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.glob("start_*.npz"))}


def test_serial_and_parallel_sets_are_the_same_tables(tmp_path):
    assert _build(tmp_path / "serial") == 0
    assert _build(tmp_path / "workers", "--workers", "2") == 0
    serial = _tables(tmp_path / "serial")
    assert len(serial) == 5 and serial == _tables(tmp_path / "workers")  # byte for byte
    index = json.loads((tmp_path / "serial" / "tables.json").read_text())
    assert index["format"] == "cuniform-table-set/1" and index["system"] == "random_walk_1d"
    starts = [t["start"] for t in index["tables"]]
    assert starts == [[-1.0], [-0.5], [0.0], [0.5], [1.0]]
    for entry in index["tables"]:  # each table records its start, and level 0 is that start's cell
        table = read_table(tmp_path / "serial" / entry["file"])
        assert table.start.tolist() == entry["start"]
        assert table.cells[0].tolist() == [round(entry["start"][0] / 0.5)]
    alone = tmp_path / "alone.npz"  # a table of the set is the table built alone from its start
    assert main([*WALK, "--start", "0.5", "--out", str(alone), "--no-report"]) == 0
    assert alone.read_bytes() == serial["start_0003.npz"]


def test_a_set_resumes_per_table(tmp_path, capsys):
    assert _build(tmp_path) == 0
    (tmp_path / "start_0002.npz").unlink()
    before = {p: p.stat().st_mtime_ns for p in tmp_path.glob("start_*.npz")}
    capsys.readouterr()
    assert main([*WALK[:-1], "--starts", "0=-1:1:5", "--out", str(tmp_path)]) == 0
    assert "4 already built" in capsys.readouterr().out
    assert {p: p.stat().st_mtime_ns for p in before} == before  # the others were not rebuilt
    assert (tmp_path / "start_0002.npz").exists()


def test_ray_set_is_the_same_tables(tmp_path):
    pytest.importorskip("ray")
    assert _build(tmp_path / "serial") == 0
    assert _build(tmp_path / "ray", "--ray") == 0
    assert _tables(tmp_path / "serial") == _tables(tmp_path / "ray")


def test_random_starts_are_seeded():
    ks = make_system("ks_speed")
    a, b = parse_starts("random:6 3=0:1", ks, seed=1), parse_starts("random:6 3=0:1", ks, seed=1)
    np.testing.assert_array_equal(a, b)
    assert a.shape == (6, 4) and (a[:, :3] == 0).all() and ((0 <= a[:, 3]) & (a[:, 3] <= 1)).all()
    assert not np.array_equal(a, parse_starts("random:6 3=0:1", ks, seed=2))
    grid = parse_starts("3=0:1:3", ks)
    assert grid[:, 3].tolist() == [0.0, 0.5, 1.0]


@pytest.mark.parametrize("argv, message", [
    (["--system", "dubins", "--starts", "2=0:1:3"], "SE(2)-invariant"),
    (["--system", "random_walk_1d", "--starts", "1=0:1:3"], "dimension 1 does not exist"),
    (["--system", "random_walk_1d", "--starts", "0=0:1"], "needs :N"),
    (["--system", "random_walk_1d", "--starts", "0=1:0:3"], "LO <= HI"),
    (["--system", "random_walk_1d", "--starts", "speed"], "not DIM=LO:HI:N"),
    (["--system", "random_walk_1d", "--starts", "0=0:1:3", "--start", "0.5"], "not both"),
    (["--system", "random_walk_1d", "--workers", "2"], "give --starts too"),
])
def test_bad_set_requests_are_one_clear_error(argv, message, tmp_path, capsys):
    assert main([*argv, "--horizon", "3", "--quiet", "--out", str(tmp_path / "set")]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1
    assert not list(tmp_path.glob("set/start_*.npz"))


# ------------------------------------------------------------------------------------------------ the runtime

def test_a_set_rolls_each_start_out_with_its_nearest_table(tmp_path, start_warnings):
    from cuniform_torch import load_table
    from cuniform_torch.policies import TableSetPolicy

    assert _build(tmp_path) == 0
    policy = load_table(tmp_path)
    assert isinstance(policy, TableSetPolicy) and policy.starts[:, 0].tolist() == [-1.0, -0.5, 0.0, 0.5, 1.0]
    assert start_warnings(policy, [0.5]) == [] and policy.last_index == 3 and policy.miss_rate == 0.0
    assert start_warnings(policy, [-0.4]) == [] and policy.last_index == 1  # within the nearest start's cell
    assert policy.last_start_distance == pytest.approx(0.2)  # cells (of 0.5)
    assert len(start_warnings(policy, [6.0])) == 1 and policy.last_index == 4  # far beyond the set: said, once
    assert policy.last_start_distance == pytest.approx(10.0)


def test_a_speed_set_serves_the_speeds_between_its_starts(tmp_path, start_warnings):
    import torch

    from cuniform_torch import CUniformMPPI, load_table

    ks = ["--system", "ks_speed", "--horizon", "3", "--quiet"]
    assert main([*ks, "--starts", "3=0:1:3", "--out", str(tmp_path / "set")]) == 0
    assert main([*ks, "--out", str(tmp_path / "zero.npz"), "--no-report"]) == 0
    pose = [1.0, -2.0, 2.5, 0.5]
    one, many = load_table(tmp_path / "zero.npz"), load_table(tmp_path / "set")
    assert len(start_warnings(one, pose)) == 1  # the zero-speed table from 0.5 m/s: warned
    assert start_warnings(many, pose) == [] and many.last_index == 1 and many.miss_rate < 0.05
    ctrl = CUniformMPPI(many, lambda s, a: s[:, -1, 0] ** 2, num_samples=64, seed=0)
    u = ctrl.command(torch.tensor(pose))
    assert u.shape == (many.actions.shape[1],) and bool(torch.isfinite(u).all())


def test_a_broken_set_is_refused_naming_the_file(tmp_path):
    from cuniform_torch import load_table
    from cuniform_torch.tables import TableError

    assert _build(tmp_path) == 0
    index = json.loads((tmp_path / "tables.json").read_text())
    index["tables"][2]["start"] = [0.25]
    (tmp_path / "tables.json").write_text(json.dumps(index))
    with pytest.raises(TableError, match="start_0002.npz: built from"):
        load_table(tmp_path)
    index["tables"][2]["start"] = [0.0]
    (tmp_path / "tables.json").write_text(json.dumps(index))
    (tmp_path / "start_0004.npz").unlink()
    with pytest.raises(TableError, match="start_0004.npz: listed in .* but missing"):
        load_table(tmp_path)
    assert main(["--system", "random_walk_1d", "--horizon", "3", "--quiet", "--no-report", "--start", "1.0",
                 "--out", str(tmp_path / "start_0004.npz")]) == 0  # another horizon: another system JSON
    with pytest.raises(TableError, match="start_0004.npz: its system, actions or grid differ"):
        load_table(tmp_path)


def test_a_speed_set_gets_a_bank_per_start_and_proposes_exact_states(tmp_path):
    """CUniformMPPI(set, bank_size=M) on ks_speed: M rollouts per member at the origin pose; a command takes the
    nearest member's actions and rolls them out from the state itself (so its speed, not the member's)."""
    import torch

    from cuniform_torch import CUniformMPPI, load_table
    from cuniform_torch.sampling import rollout_actions

    ks = ["--system", "ks_speed", "--horizon", "3", "--quiet"]
    assert main([*ks, "--starts", "3=0:1:3", "--out", str(tmp_path / "set")]) == 0
    assert main([*ks, "--out", str(tmp_path / "zero.npz"), "--no-report"]) == 0
    many = load_table(tmp_path / "set")
    ctrl = CUniformMPPI(many, lambda s, a: s[:, -1, 0] ** 2, num_samples=32, bank_size=64, seed=0)
    assert ctrl.bank_states.shape == (3, 64, 4, 4) and ctrl.bank_actions.shape == (3, 64, 3, 2)
    assert ctrl.bank_states[:, :, 0, 3].tolist() == [[0.0] * 64, [0.5] * 64, [1.0] * 64]  # each member's speed
    state = torch.tensor([1.0, -2.0, 2.5, 0.9])
    states, actions = ctrl.proposal.propose(state, torch.Generator().manual_seed(1))
    assert many.last_index == 2  # 0.9 m/s: the 1 m/s member
    member = ctrl.bank_actions[2]
    assert bool((actions[:, None] == member[None]).flatten(2).all(2).any(1).all())  # rows of that member's bank
    torch.testing.assert_close(states, rollout_actions(many.system, state, actions))
    assert states[:, 0].eq(state).all()
    u = ctrl.command(state)
    assert bool(torch.isfinite(u).all())
    with pytest.raises(ValueError, match="a table set over them"):
        CUniformMPPI(load_table(tmp_path / "zero.npz"), lambda s, a: s[:, -1, 0], num_samples=32, bank_size=64)


def test_the_start_in_the_rollouts_own_cell_wins_over_an_equally_near_one(tmp_path):
    """ks_speed's speed cells are 0.2 m/s wide: 0.125 m/s is as near to the 0 and the 0.25 m/s starts, but only the
    0.25 one is in its cell (1), and only that table describes rollouts from it."""
    import torch

    from cuniform_torch import load_table

    ks = ["--system", "ks_speed", "--horizon", "2", "--quiet"]
    assert main([*ks, "--starts", "3=0:0.5:3", "--out", str(tmp_path / "set")]) == 0
    many = load_table(tmp_path / "set")
    many.for_start(torch.tensor([0.0, 0.0, 0.0, 0.125]))
    assert many.last_index == 1 and many.last_start_distance == pytest.approx(0.625)
    many.for_start(torch.tensor([0.0, 0.0, 0.0, 0.45]))  # cell 2: the 0.5 start's, though 0.25 is not much farther
    assert many.last_index == 2
    many.for_start(torch.tensor([0.0, 0.0, 0.0, 1.0]))  # no start in its cell (5): the nearest, 0.5
    assert many.last_index == 2
