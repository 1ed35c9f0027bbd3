"""The table builder end to end: level sets, probabilities, exact propagation, report, CLI, resume."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
import torch

from cuniform_torch.grid.cells import Grid
from cuniform_torch.policies.table import TablePolicy, load_table
from cuniform_torch.sampling.rollout import rollout
from cuniform_torch.systems import make_system
from cuniform_torch.tables.file import read_table, write_table
from precompute import build as build_cli
from precompute.flow.builder import BuildConfig, build_table
from precompute.levels.sets import PointMode, next_level
from precompute.report import uniformity_report

# The authors' released code (ogpoyrazoglu/cuniform_sampling), run unchanged on the default preset.
AUTHORS_LEVEL_SIZES = [1, 5, 13, 25, 47, 89, 173, 333, 607, 1045, 1689]


def test_default_dubins_level_sets_are_the_authors(dubins_table):
    assert dubins_table.level_sizes == AUTHORS_LEVEL_SIZES


def test_default_dubins_level_sets_are_mirror_symmetric(dubins_table):
    """The preset is symmetric under (x, y, theta, omega) -> (x, -y, -theta, -omega): so is every level set."""
    K = round(2 * np.pi / dubins_table.cell_size[2])
    for t in range(dubins_table.horizon + 1):
        cells = dubins_table.cells[dubins_table.level(t)]
        mirror = np.stack([cells[:, 0], -cells[:, 1], np.remainder(-cells[:, 2], K)], axis=1)
        assert set(map(tuple, mirror.tolist())) == set(map(tuple, cells.tolist())), t


def test_the_grid_tie_rule_keeps_the_offset_deciding():
    """``ties="grid"``: a stepped state takes its own cell, so the preset's 1% angle offset breaks every half-cell
    tie the same way (the builder's only rule before the symmetric one); a resume never mixes the two."""
    table, _ = build_table(make_system("dubins"), BuildConfig(horizon=10, ties="grid"))
    assert table.level_sizes == [1, 4, 11, 23, 44, 83, 157, 291, 523, 897, 1456]
    assert json.loads(table.build_info)["ties"] == "grid"
    with pytest.raises(ValueError, match=r"unknown tie rule 'nearest'; choose one of: symmetric, grid"):
        BuildConfig(ties="nearest")


def test_a_resume_with_another_tie_rule_rebuilds_every_step(tmp_path):
    system = make_system("dubins")
    build_table(system, BuildConfig(horizon=3, ties="grid"), checkpoint_dir=tmp_path)
    _, stats = build_table(system, BuildConfig(horizon=3), checkpoint_dir=tmp_path, resume=True)
    assert stats.resumed_steps == 0


def test_level_sets_are_the_same_in_float32_and_float64():
    """Every level of the default preset stepped from float32 centres with float32 actions lands in the cells
    that the float64 build finds: the half-cell ties are decided by direction, not by rounding noise."""
    system, horizon = make_system("dubins"), 8
    grid = Grid.of(system)
    cells = torch.zeros((1, 3), dtype=torch.int64)
    for _ in range(horizon):
        reached = {}
        for dtype in (torch.float64, torch.float32):
            x = grid.centers(cells, dtype)  # [n, d]
            u = system.action_set(dtype=dtype)  # [A, 1]
            n, A = x.shape[0], u.shape[0]
            stepped = system.step(x.repeat_interleave(A, 0), u.repeat(n, 1)).reshape(n, A, 3)
            reached[dtype] = grid.cells_from(cells, stepped)
        assert torch.equal(reached[torch.float64], reached[torch.float32])
        cells = torch.unique(reached[torch.float64].reshape(-1, 3), dim=0)


def test_rows_sum_to_one_and_last_level_is_uniform(dubins_table):
    t = dubins_table
    np.testing.assert_allclose(t.action_probs.sum(axis=1, dtype=np.float64), 1.0, atol=1e-6)
    np.testing.assert_allclose(t.action_probs[t.level(t.horizon)], 1.0 / t.actions.shape[0])
    for lv in range(t.horizon + 1):
        assert t.cell_probs[t.level(lv)].sum() == pytest.approx(1.0, abs=1e-9)


def test_transition_fractions_sum_to_one_per_cell_action(dubins_table):
    t = dubins_table
    key = t.transitions[:, 0] * t.actions.shape[0] + t.transitions[:, 1]
    sums = np.bincount(key, weights=t.transition_frac)
    np.testing.assert_allclose(sums[np.unique(key)], 1.0)


def test_cell_probs_are_the_exact_propagation(dubins_table):
    """Slow reference: a dense Markov matrix per step from the stored transitions and probabilities."""
    t = dubins_table
    dist = np.ones(1)
    for lv in range(6):
        sl = slice(t.transition_offsets[lv], t.transition_offsets[lv + 1])
        n, m = t.level_sizes[lv], t.level_sizes[lv + 1]
        M = np.zeros((n, m))
        for (i, a, j), f in zip(t.transitions[sl].tolist(), t.transition_frac[sl].tolist()):
            M[i - t.level_offsets[lv], j - t.level_offsets[lv + 1]] += t.action_probs[i, a] * f
        dist = dist @ M
        np.testing.assert_allclose(t.cell_probs[t.level(lv + 1)], dist, rtol=1e-5, atol=1e-9)


def test_random_walk_is_exactly_c_uniform(walk_table):
    t = walk_table
    assert t.level_sizes == [1 + 4 * k for k in range(t.horizon + 1)]
    np.testing.assert_array_equal(t.flow_value, t.flow_target)  # flow = n*m at every level
    for lv in range(t.horizon + 1):
        np.testing.assert_allclose(t.cell_probs[t.level(lv)], 1.0 / t.level_sizes[lv], rtol=1e-9)


def test_random_walk_figure_2_step_is_c_uniform(walk_table):
    """L_1 -> L_2 is the paper's Figure 2 (n = 5, m = 9): every next cell receives exactly 5/9 x 1/5."""
    t = walk_table
    assert t.level_sizes[1:3] == [5, 9]
    sl = slice(t.arc_offsets[1], t.arc_offsets[2])
    inflow = np.bincount(t.arcs[sl, 1] - t.level_offsets[2], weights=t.arc_flow[sl], minlength=9)
    np.testing.assert_array_equal(inflow, np.full(9, 5))


def test_random_walk_rollouts_are_within_the_noise_floor(walk_table):
    report = uniformity_report(walk_table, num_rollouts=4000, seed=3)
    for lv in report.levels[1:]:
        assert lv.outside_fraction == 0.0
        assert lv.tv_rollout <= lv.tv_floor + 4 * lv.tv_floor_std + 1e-3, lv
    assert report.miss_rate == 0.0


def test_dubins_report_measures_rollouts_honestly(dubins_table):
    report = uniformity_report(dubins_table, seed=0)
    assert report.num_rollouts == 10 * max(dubins_table.level_sizes)
    assert [lv.cells for lv in report.levels] == dubins_table.level_sizes
    # the paper's network is not C-Uniform on real rollouts: far above the multinomial noise floor
    last = report.levels[-1]
    assert last.tv_rollout > last.tv_floor + 10 * last.tv_floor_std


def test_table_policy_rows_match_cells_at_centres(dubins_table):
    policy = TablePolicy(dubins_table)
    lv = 4
    cells = torch.from_numpy(dubins_table.cells[dubins_table.level(lv)])
    x = policy.grid.centers(cells, torch.float32)
    rows = policy.rows(x, lv)
    assert torch.equal(rows, torch.arange(dubins_table.level_offsets[lv], dubins_table.level_offsets[lv + 1]))
    torch.testing.assert_close(policy.action_probs(x, lv), torch.from_numpy(dubins_table.action_probs[rows.numpy()]))
    assert policy.miss_rate == 0.0


def test_rollout_matches_a_plain_step_by_step_reference(dubins_table):
    policy = TablePolicy(dubins_table)
    gen = torch.Generator().manual_seed(0)
    states, actions = rollout(policy.system, policy, torch.zeros(3), 64, 10, generator=gen)
    assert states.shape == (64, 11, 3) and actions.shape == (64, 10, 1)
    for t in range(10):
        torch.testing.assert_close(states[:, t + 1], policy.system.step(states[:, t], actions[:, t]))
    assert set(actions.flatten().tolist()) <= set(policy.actions.flatten().tolist())
    again, _ = rollout(policy.system, policy, torch.zeros(3), 64, 10, generator=torch.Generator().manual_seed(0))
    assert torch.equal(states, again)


def test_point_modes():
    system = make_system("dubins")
    cells = np.zeros((1, 3), dtype=np.int64)
    centre = next_level(system, cells, PointMode.CENTERS)
    lattice = next_level(system, cells, PointMode.LATTICE)
    assert lattice.kept_fraction == 1.0
    assert len(lattice.next_cells) >= len(centre.next_cells)
    r1 = next_level(system, cells, "random", 16, torch.Generator().manual_seed(1))
    r1b = next_level(system, cells, "random", 16, torch.Generator().manual_seed(1))
    np.testing.assert_array_equal(r1.frac, r1b.frac)
    np.testing.assert_array_equal(r1.next_cells, centre.next_cells)  # level sets from the centres
    with pytest.raises(ValueError, match="unknown point mode"):
        next_level(system, cells, "grid")


def test_resume_after_interrupt_gives_a_byte_identical_table(tmp_path):
    system = make_system("dubins")
    config = BuildConfig(horizon=6)
    full, _ = build_table(system, config)
    write_table(tmp_path / "full.npz", full)

    ckpt = tmp_path / "ckpt"

    def interrupt(t, step):
        if t == 3:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        build_table(system, config, checkpoint_dir=ckpt, progress=interrupt)
    assert len(list(ckpt.glob("step_*.npz"))) == 4
    resumed, stats = build_table(system, config, checkpoint_dir=ckpt, resume=True)
    assert stats.resumed_steps == 4
    write_table(tmp_path / "resumed.npz", resumed)
    assert (tmp_path / "full.npz").read_bytes() == (tmp_path / "resumed.npz").read_bytes()

    # a checkpoint of other settings is not reused
    other, stats = build_table(system, BuildConfig(horizon=6, points="lattice"), checkpoint_dir=ckpt, resume=True)
    assert stats.resumed_steps == 0


def test_interrupted_write_leaves_no_partial_file(tmp_path, dubins_table, monkeypatch):
    dest = tmp_path / "t.npz"
    calls = {"n": 0}
    real = np.lib.format.write_array

    def flaky(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 5:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(np.lib.format, "write_array", flaky)
    with pytest.raises(KeyboardInterrupt):
        write_table(dest, dubins_table)
    assert list(tmp_path.iterdir()) == []


def test_cli_builds_table_and_report(tmp_path, capsys):
    out = tmp_path / "walk.npz"
    code = build_cli.main(["maxflow", "--system", "random_walk_1d", "--horizon", "4", "--out", str(out), "--quiet"])
    assert code == 0
    table = read_table(out)
    assert table.level_sizes == [1, 5, 9, 13, 17]
    report = json.loads((tmp_path / "walk.report.json").read_text())
    assert [lv["cells"] for lv in report["uniformity"]["levels"]] == table.level_sizes
    assert set(report["seconds"]) >= {"levels", "arcs", "maxflow", "probabilities", "write", "total"}
    assert not (tmp_path / "walk.npz.partial").exists()
    assert load_table(out).num_actions == 5


def test_cli_system_parameters_are_params(tmp_path):
    out = tmp_path / "d.npz"
    code = build_cli.main(["maxflow", "--system", "dubins", "--horizon", "3", "--param", "num_actions=7", "--param",
                           "cell_size=[0.1, 0.1, 0.1571]", "--out", str(out), "--quiet", "--no-report"])
    assert code == 0
    table = read_table(out)
    system = table.make_system()
    assert system.num_actions == 7 and table.actions.shape == (7, 1)
    assert system.cell_size[0] == 0.1 and table.horizon == 3


def test_cli_resume_continues_from_checkpoints(tmp_path, monkeypatch, capsys):
    out = tmp_path / "d.npz"
    args = ["maxflow", "--system", "dubins", "--horizon", "5", "--out", str(out), "--quiet", "--no-report"]
    import precompute.flow.builder as builder

    real = builder._solve_step
    calls = {"n": 0}

    def interrupting(*a, **k):
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt
        return real(*a, **k)

    monkeypatch.setattr(builder, "_solve_step", interrupting)
    assert build_cli.main(args) == 130
    assert not out.exists()
    assert "--resume" in capsys.readouterr().err
    monkeypatch.setattr(builder, "_solve_step", real)
    assert build_cli.main(args + ["--resume"]) == 0
    resumed = out.read_bytes()
    os.remove(out)
    assert build_cli.main(args) == 0
    assert out.read_bytes() == resumed


def test_the_build_runs_on_one_thread_and_gives_the_caller_its_own_back(tmp_path, monkeypatch):
    """On a busy machine extra torch threads only wait for each other (README: the build's --threads)."""
    calls = []
    real = torch.set_num_threads
    monkeypatch.setattr(torch, "set_num_threads", lambda n: (calls.append(n), real(n))[1])
    before = torch.get_num_threads()
    seen = []
    monkeypatch.setattr(build_cli, "_run", lambda args, argv=(): seen.append(torch.get_num_threads()) or 0)
    assert build_cli.main(["maxflow", "--horizon", "2", "--out", str(tmp_path / "t.npz"), "--quiet"]) == 0
    assert seen == [1] and torch.get_num_threads() == before and calls == [1, before]
    calls.clear()
    assert build_cli.main(["maxflow", "--horizon", "2", "--out", str(tmp_path / "t.npz"), "--quiet", "--threads",
                           "0"]) == 0
    assert calls == [before]  # 0: torch's choice, left alone
