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
    """Eagerly (lazy=False) at load; lazily at the first use of the broken member (a missing file: at load)."""
    import torch

    from cuniform_torch import load_table
    from cuniform_torch.tables import TableError

    assert _build(tmp_path) == 0
    index = json.loads((tmp_path / "tables.json").read_text())
    index["tables"][2]["start"] = [0.25]
    (tmp_path / "tables.json").write_text(json.dumps(index))
    with pytest.raises(TableError, match="start_0002.npz: built from"):
        load_table(tmp_path, lazy=False)
    lazy = load_table(tmp_path)
    lazy.for_start(torch.tensor([1.0]))  # another member: fine
    with pytest.raises(TableError, match="start_0002.npz: built from"):
        lazy.for_start(torch.tensor([0.25]))
    index["tables"][2]["start"] = [0.0]
    (tmp_path / "tables.json").write_text(json.dumps(index))
    (tmp_path / "start_0004.npz").unlink()
    with pytest.raises(TableError, match="start_0004.npz: listed in .* but missing"):
        load_table(tmp_path)
    assert main(["--system", "random_walk_1d", "--horizon", "3", "--quiet", "--no-report", "--start", "1.0",
                 "--out", str(tmp_path / "start_0004.npz")]) == 0  # another horizon: another system JSON
    with pytest.raises(TableError, match="start_0004.npz: its system, actions or grid differ"):
        load_table(tmp_path, lazy=False)
    with pytest.raises(TableError, match="start_0004.npz: its system, actions or grid differ"):
        load_table(tmp_path).action_probs(torch.tensor([[1.0]]), 0)
    index["system"] = "double_integrator"
    (tmp_path / "tables.json").write_text(json.dumps(index))
    with pytest.raises(TableError, match="names the system 'double_integrator'"):
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


# ------------------------------------------------------------------------------------------------ issue 27

def _counts(policy) -> list[int]:
    """Lookups each member has answered (0 for a member not read yet)."""
    return [policy.members[i].queries if i in policy.loaded else 0 for i in range(len(policy.starts))]


def test_lookups_answer_from_the_member_nearest_each_trajectorys_start(tmp_path):
    """action_probs / sample on the set: each state's row from the member nearest to its trajectory's start (the
    state itself at t = 0), whatever member the latest rollout used; a state at t > 0 needs its start."""
    import torch

    from cuniform_torch import load_table

    assert _build(tmp_path) == 0  # starts -1, -0.5, 0, 0.5, 1
    policy = load_table(tmp_path)
    policy.for_start(torch.tensor([0.0]))  # the latest rollout's member: 2
    low, high = torch.tensor([[-1.0]]), torch.tensor([[0.9]])
    policy.reset_counters()
    got = policy.action_probs(low, 0)
    assert _counts(policy) == [1, 0, 0, 0, 0]  # member 0 answered -1, not the latest rollout's member 2
    torch.testing.assert_close(got, policy.members[0].action_probs(low, 0))
    policy.reset_counters()
    got = policy.action_probs(high, 0)
    assert _counts(policy) == [0, 0, 0, 0, 1]
    torch.testing.assert_close(got, policy.members[4].action_probs(high, 0))
    # one batch, rows of three members, in the rows' order; the two states are the same distance from member 2's
    # start, so a per-row answer is the only way to tell them apart
    x = torch.tensor([[0.9], [-1.0], [0.9], [0.1]])
    policy.reset_counters()
    probs = policy.action_probs(x, 0)
    assert _counts(policy) == [1, 0, 1, 0, 2]
    torch.testing.assert_close(probs[[0, 2]], policy.members[4].action_probs(x[[0, 2]], 0))
    torch.testing.assert_close(probs[1:2], policy.members[0].action_probs(x[1:2], 0))
    torch.testing.assert_close(probs[3:], policy.members[2].action_probs(x[3:], 0))
    # t > 0: the member is the trajectory's (by its start), not the state's nearest
    state = torch.tensor([[-0.5], [-0.5]])
    policy.reset_counters()
    probs = policy.action_probs(state, 1, start=torch.tensor([[-1.0], [1.0]]))
    assert _counts(policy) == [1, 0, 0, 0, 1]
    assert int(policy.members[0].nearest_hits) == 0 and int(policy.members[4].nearest_hits) == 1  # off its level
    assert not torch.equal(probs[0], probs[1])  # the same state, two trajectories: two answers
    torch.testing.assert_close(probs[1:], policy.members[4].action_probs(state[1:], 1))
    before = _counts(policy)
    u = policy.sample(state, 2, torch.Generator().manual_seed(0), start=torch.tensor([1.0]))  # both: member 4
    assert u.shape == (2, 1) and [a - b for a, b in zip(_counts(policy), before)] == [0, 0, 0, 0, 2]
    with pytest.raises(ValueError, match=r"t=1\): a set's member is chosen by the trajectory's start.*start=x0"):
        policy.action_probs(state, 1)
    with pytest.raises(ValueError, match=r"sample\(x, t=2\)"):
        policy.sample(state, 2)
    with pytest.raises(ValueError, match=r"start must be \[1\] or \[2, 1\]"):
        policy.action_probs(state, 1, start=torch.zeros(3, 1))


def test_a_rollout_from_starts_of_different_members_is_an_error(tmp_path):
    import torch

    from cuniform_torch import load_table, rollout

    assert _build(tmp_path) == 0
    policy = load_table(tmp_path)
    assert rollout(policy.system, policy, torch.tensor([[0.45], [0.55]]), 2, 3)[0].shape == (2, 4, 1)  # one member
    assert policy.last_index == 3
    with pytest.raises(ValueError, match="nearest to different members of the table set"):
        rollout(policy.system, policy, torch.tensor([[-1.0], [1.0]]), 2, 3)


def _episode_warnings(run) -> list:
    import warnings

    from cuniform_torch.sampling import StartMismatchWarning

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        run()
    return [w for w in caught if issubclass(w.category, StartMismatchWarning)]


def test_off_start_rollouts_warn_and_count_in_every_episode(tmp_path):
    """A controller's reset() begins an episode: the set warns again (once per episode, over all its members) and
    start_misses counts every off-start rollout of that episode, also the silent ones after the warning."""
    import torch

    from cuniform_torch import CUniformMPPI, load_table

    assert _build(tmp_path) == 0
    policy = load_table(tmp_path)
    k, horizon = 32, policy.horizon
    ctrl = CUniformMPPI(policy, lambda s, a: s[:, -1, 0] ** 2, num_samples=k, seed=0)
    for episode in range(2):
        policy.reset_counters()
        assert _episode_warnings(lambda: ctrl.command(torch.tensor([0.0]))) == []  # a member's own start
        assert policy.start_misses.rollouts == 0
        warned = _episode_warnings(lambda: [ctrl.command(torch.tensor([x])) for x in (3.0, -3.0, 4.0)])
        assert len(warned) == 1, f"episode {episode}"  # two members, three off-start rollouts: one warning
        assert "once per episode" in str(warned[0].message)
        seen = policy.start_misses
        assert seen.rollouts == 3 and seen.lookups == 3 * k * horizon
        assert seen.misses == int(policy.misses) > 0 and seen.rate == pytest.approx(policy.miss_rate * 4 / 3)
        ctrl.reset()
        assert policy.start_misses.rollouts == 0 and not policy.start_misses.warned


def test_a_single_table_warns_again_after_a_controller_reset(walk_table):
    import torch

    from cuniform_torch import CUniformMPPI, TablePolicy
    from cuniform_torch.sampling.start_watch import new_episode, start_misses

    policy = TablePolicy(walk_table)
    ctrl = CUniformMPPI(policy, lambda s, a: s[:, -1, 0] ** 2, num_samples=16, seed=0)
    for _ in range(2):
        assert len(_episode_warnings(lambda: [ctrl.command(torch.tensor([20.0])) for _ in range(2)])) == 1
        assert start_misses(policy).rollouts == 2 and start_misses(policy).misses > 0
        ctrl.reset()
    assert len(_episode_warnings(lambda: ctrl.command(torch.tensor([20.0])))) == 1
    new_episode(policy)  # without a controller
    assert start_misses(policy).rollouts == 0
    assert len(_episode_warnings(lambda: ctrl.command(torch.tensor([20.0])))) == 1


def test_a_set_opens_lazily_and_reads_a_member_on_its_first_use(tmp_path, monkeypatch):
    import torch

    import cuniform_torch.policies.table_set as table_set
    from cuniform_torch import load_table

    assert _build(tmp_path) == 0
    opened: list[str] = []
    read = table_set.read_table
    monkeypatch.setattr(table_set, "read_table", lambda path, **kw: opened.append(path.name) or read(path, **kw))
    policy = load_table(tmp_path)
    assert opened == ["start_0000.npz"] and policy.loaded == [0]  # the index and the first table only
    policy.for_start(torch.tensor([0.9]))
    assert opened == ["start_0000.npz", "start_0004.npz"] and policy.loaded == [0, 4]
    policy.for_start(torch.tensor([1.0]))
    policy.action_probs(torch.tensor([[0.0], [1.0]]), 0)
    assert opened[2:] == ["start_0002.npz"] and policy.members.reads == 2  # each member read once
    assert policy.queries == 2  # the counters sum the members read
    opened.clear()
    eager = load_table(tmp_path, lazy=False)
    assert sorted(opened) == [f"start_{i:04d}.npz" for i in range(5)] and eager.loaded == [0, 1, 2, 3, 4]
    assert [m.build_start.tolist() for m in policy.members] == [[-1.0], [-0.5], [0.0], [0.5], [1.0]]


def test_a_table_or_a_start_listed_twice_is_refused(tmp_path):
    """A duplicated entry of tables.json (the same file, or another file with the same start) is one clear error."""
    from cuniform_torch import load_table
    from cuniform_torch.tables import TableError

    assert _build(tmp_path) == 0
    index = json.loads((tmp_path / "tables.json").read_text())
    good = json.loads(json.dumps(index))
    index["tables"].append(dict(index["tables"][1]))
    (tmp_path / "tables.json").write_text(json.dumps(index))
    with pytest.raises(TableError, match="start_0001.npz listed more than once"):
        load_table(tmp_path)
    index = json.loads(json.dumps(good))
    index["tables"][3]["start"] = index["tables"][1]["start"]
    (tmp_path / "tables.json").write_text(json.dumps(index))
    with pytest.raises(TableError, match="same start"):
        load_table(tmp_path)
