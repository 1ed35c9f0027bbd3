"""The coverage method: uniform where uniformity is feasible, more coverage than max-flow on real rollouts."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from cuniform_torch import TablePolicy, make_system, read_table, rollout, write_table
from cuniform_torch.metrics import coverage, uniform_ceiling
from precompute import build as build_cli
from precompute.coverage.method import CoverageConfig, build_coverage_table, enumerate_reachable
from precompute.flow.builder import BuildConfig, build_table, propagate_cell_probs


@pytest.fixture(scope="module")
def small_dubins():
    """The unapproximated method (no state budget, no early stop) beside the max-flow table."""
    system = make_system("dubins")
    cov, facts = build_coverage_table(system, CoverageConfig(horizon=6, steps=150, target_samples=500,
                                                             state_budget=0, tol=0.0))
    flow, _ = build_table(system, BuildConfig(horizon=6))
    return cov, facts, flow


def test_random_walk_is_uniform():
    # tol=0: every step; the entropy tie-breaker makes fully covered levels uniform only slowly (the early stop
    # ends the ascent once the objective, already within 0.5% of its optimum, stops moving)
    table, _ = build_coverage_table(make_system("random_walk_1d"),
                                    CoverageConfig(horizon=4, steps=400, target_samples=50, tol=0.0))
    assert table.level_sizes == [1, 5, 9, 13, 17]
    for t in range(1, table.horizon + 1):
        p = table.cell_probs[table.level(t)]
        assert 0.5 * np.abs(p - 1 / len(p)).sum() < 0.01, (t, p)


def test_level_sets_are_the_reachable_cells(small_dubins):
    cov, facts, _ = small_dubins
    system = make_system("dubins")
    levels = enumerate_reachable(system, 6)
    assert cov.level_sizes == [len(c) for c in levels.cells]
    # real rollouts stay in the level sets (up to the sub-cell merging)
    policy = TablePolicy(cov)
    states, _ = rollout(system, policy, torch.zeros(3), 2000, 6, torch.Generator().manual_seed(0))
    for t in range(7):
        assert (policy.rows(states[:, t], t) >= 0).float().mean() > 0.99


def test_table_is_valid_and_cell_probs_are_the_exact_propagation(small_dubins, tmp_path):
    cov, _, _ = small_dubins
    write_table(tmp_path / "cov.npz", cov)
    table = read_table(tmp_path / "cov.npz")
    assert table.method == "coverage"
    dist = np.ones(1)
    for t in range(table.horizon):
        sl = slice(table.transition_offsets[t], table.transition_offsets[t + 1])
        tr = table.transitions[sl]
        probs = table.action_probs[table.level(t)].astype(np.float64)
        dist = propagate_cell_probs(dist, probs, tr[:, 0] - table.level_offsets[t], tr[:, 1],
                                    tr[:, 2] - table.level_offsets[t + 1], table.transition_frac[sl],
                                    table.level_sizes[t + 1])
        np.testing.assert_allclose(dist, table.cell_probs[table.level(t + 1)], atol=1e-5)


def test_real_rollouts_cover_more_than_maxflow(small_dubins):
    cov, _, flow = small_dubins
    system = make_system("dubins")
    totals = {}
    for name, table in (("coverage", cov), ("maxflow", flow)):
        policy = TablePolicy(table)
        states, _ = rollout(system, policy, torch.zeros(3), 500, 6, torch.Generator().manual_seed(1))
        totals[name] = coverage(states, policy.grid).total
    assert totals["coverage"] > 1.2 * totals["maxflow"], totals


def test_predicted_coverage_matches_sampled(small_dubins):
    cov, facts, _ = small_dubins
    system = make_system("dubins")
    policy = TablePolicy(cov)
    N = 1000
    predicted = facts["predicted_coverage_per_level"][str(N)]
    states, _ = rollout(system, policy, torch.zeros(3), N, 6, torch.Generator().manual_seed(2))
    sampled = coverage(states, policy.grid, policy).in_level_set
    for t in range(1, 7):
        n = cov.level_sizes[t]
        tol = 4 * np.sqrt(n) + 2  # binomial-like spread of a count of n cells
        assert abs(sampled[t] - predicted[t]) <= tol, (t, sampled[t], predicted[t])
        assert sampled[t] <= uniform_ceiling(n, N) + tol


def test_cli_coverage_method(tmp_path):
    out = tmp_path / "c.npz"
    assert build_cli.main(["--system", "dubins", "--method", "coverage", "--horizon", "4", "--steps", "30",
                           "--out", str(out), "--quiet"]) == 0
    report = json.loads((tmp_path / "c.report.json").read_text())
    assert report["method"] == "coverage" and report["flow_ratio"] is None
    assert report["coverage_method"]["merged_states"][0] == 1
    out2 = tmp_path / "c2.npz"
    assert build_cli.main(["--system", "dubins", "--method", "coverage", "--horizon", "4", "--steps", "30",
                           "--state-budget", "100", "--tol", "0", "--out", str(out2), "--quiet", "--no-report"]) == 0
    facts = json.loads((tmp_path / "c2.report.json").read_text())["coverage_method"]
    assert facts["steps_run"] == 30 and facts["merge_resolutions"][-1] < 32
    info = json.loads(read_table(out2).build_info)
    assert info["state_budget"] == 100 and info["tol"] == 0.0
    assert read_table(out).method == "coverage"


def test_bad_settings_are_clear_errors():
    with pytest.raises(ValueError, match="target_samples"):
        CoverageConfig(target_samples=0)
    with pytest.raises(ValueError, match="state_budget"):
        CoverageConfig(state_budget=-1)
    with pytest.raises(ValueError, match="tol"):
        CoverageConfig(tol=float("nan"))
    with pytest.raises(ValueError, match="max_states"):
        enumerate_reachable(make_system("dubins"), 6, max_states=10)


def test_state_budget_coarsens_the_levels_that_exceed_it():
    system = make_system("dubins")
    exact = enumerate_reachable(system, 6)
    assert exact.resolution == [32] * 7
    budget = 2000
    assert max(exact.num_states) > budget  # the budget must bind for the test to mean anything
    coarse = enumerate_reachable(system, 6, state_budget=budget)
    res = coarse.resolution
    assert all(a >= b for a, b in zip(res, res[1:])) and res[-1] < 32, res
    for t in range(7):
        assert coarse.num_states[t] <= budget or res[t] == 1, (t, coarse.num_states[t], res)
        if res[t] == 32:  # levels within the budget are merged exactly as without one
            assert coarse.num_states[t] == exact.num_states[t]
            assert torch.equal(coarse.cells[t], exact.cells[t])
    # the coarsened levels still reach (almost) every reachable cell
    assert len(coarse.cells[6]) >= 0.97 * len(exact.cells[6])


def test_early_stop_and_the_exact_ascent():
    system = make_system("dubins")
    _, stopped = build_coverage_table(system, CoverageConfig(horizon=4, steps=300, tol=1e-3))
    _, full = build_coverage_table(system, CoverageConfig(horizon=4, steps=300, tol=0.0))
    assert full["steps_run"] == 300
    assert 10 < stopped["steps_run"] < 300
    first, last = stopped["objective_first_last"]
    assert first == full["objective_first_last"][0]  # the same ascent, cut short
    assert last >= 0.99 * full["objective_first_last"][1]


def test_approximations_keep_real_coverage(small_dubins):
    """A state budget that coarsens the last levels and the early stop cost at most a few % of real coverage."""
    exact, _, _ = small_dubins
    system = make_system("dubins")
    approx, facts = build_coverage_table(system, CoverageConfig(horizon=6, steps=150, target_samples=500,
                                                                 state_budget=1000, tol=1e-3))
    assert facts["merge_resolutions"][-1] < 32 and facts["steps_run"] < 150
    totals = {}
    for name, table in (("exact", exact), ("approx", approx)):
        policy = TablePolicy(table)
        totals[name] = np.mean([coverage(rollout(system, policy, torch.zeros(3), 500, 6,
                                                 torch.Generator().manual_seed(seed))[0], policy.grid).total
                                for seed in range(3)])
    assert totals["approx"] >= 0.95 * totals["exact"], totals


# the compiled loops of the coverage build (precompute/coverage/loops.py) against the torch and autograd references
def _torch_transitions(levels, probs, A):
    """The torch assembly of the recorded transitions the compiled one replaced (the slow reference)."""
    import torch

    out, state_mass = [], torch.ones(1, dtype=torch.float64)
    for t in range(len(levels.successor)):
        sc, succ = levels.state_cell[t], levels.successor[t]
        n, m = len(levels.cells[t]), len(levels.cells[t + 1])
        ok = (succ >= 0).reshape(-1)
        src = sc.unsqueeze(1).expand_as(succ).reshape(-1)[ok]
        act = torch.arange(A).repeat(len(sc))[ok]
        dst = levels.state_cell[t + 1][succ.reshape(-1)[ok]]
        weight = state_mass.unsqueeze(1).expand_as(succ).reshape(-1)[ok]
        uniq, inv = torch.unique((src * A + act) * m + dst, return_inverse=True)
        w = torch.zeros(len(uniq), dtype=torch.float64).index_add(0, inv, weight)
        cnt = torch.zeros(len(uniq), dtype=torch.float64).index_add(0, inv, torch.ones_like(weight))
        sa = uniq // m
        tot_w = torch.zeros(n * A, dtype=torch.float64).index_add(0, sa, w)
        tot_c = torch.zeros(n * A, dtype=torch.float64).index_add(0, sa, cnt)
        frac = torch.where(tot_w[sa] > 0, w / tot_w[sa].clamp(min=1e-300), cnt / tot_c[sa])
        out.append((torch.stack((sa // A, sa % A, uniq % m), 1).numpy(), frac.numpy()))
        state_mass = torch.zeros(levels.num_states[t + 1], dtype=torch.float64).index_add(
            0, succ.reshape(-1)[ok], (state_mass.unsqueeze(1) * probs[t][sc]).reshape(-1)[ok])
    return out


@pytest.mark.parametrize("pruned", [False, True])
def test_the_compiled_transitions_are_the_torch_assembly_to_the_bit(pruned):
    import torch

    from cuniform_torch.systems import make_system
    from precompute.coverage.loops import level_transitions
    from precompute.coverage.method import enumerate_reachable

    levels = enumerate_reachable(make_system("dubins"), 6, state_budget=2000)
    gen = torch.Generator().manual_seed(0)
    if pruned:  # every fifth pair lost to a map, and one level's states all without mass on action 0
        levels.successor = [torch.where(torch.rand(s.shape, generator=gen) < 0.2, -1, s) for s in levels.successor]
    A = levels.successor[0].shape[1]
    probs = [torch.softmax(3 * torch.randn(len(c), A, generator=gen, dtype=torch.float64), 1)
             for c in levels.cells[:-1]]
    if pruned:
        probs[2][:, 0] = 0.0
    state_mass = torch.ones(1, dtype=torch.float64)
    for t, (rows, frac) in enumerate(_torch_transitions(levels, probs, A)):
        sc, succ = levels.state_cell[t], levels.successor[t]
        src, act, dst, got = level_transitions(sc.numpy(), succ.reshape(-1).numpy(),
                                               levels.state_cell[t + 1].numpy(), state_mass.numpy(),
                                               len(levels.cells[t]), A)
        assert np.array_equal(np.stack((src, act, dst), 1), rows) and np.array_equal(got, frac), t
        ok = (succ >= 0).reshape(-1)
        state_mass = torch.zeros(levels.num_states[t + 1], dtype=torch.float64).index_add(
            0, succ.reshape(-1)[ok], (state_mass.unsqueeze(1) * probs[t][sc]).reshape(-1)[ok])


@pytest.mark.parametrize("pruned", [False, True])
def test_the_compiled_ascent_passes_are_the_autograd_gradient(pruned):
    """StatePropagator (compiled loops) against autograd through the torch propagation, with pruned successors."""
    import torch

    from cuniform_torch.systems import make_system
    from precompute.coverage.adjoint import StatePropagator
    from precompute.coverage.method import CoverageConfig, _propagate, coverage_objective, enumerate_reachable

    levels = enumerate_reachable(make_system("dubins"), 5)
    gen = torch.Generator().manual_seed(1)
    if pruned:
        levels.successor = [torch.where(torch.rand(s.shape, generator=gen) < 0.2, -1, s) for s in levels.successor]
    config = CoverageConfig(horizon=5, target_samples=100)
    logits = [torch.randn((len(c), 5), generator=gen, dtype=torch.float64, requires_grad=True)
              for c in levels.cells[:-1]]
    coverage_objective(_propagate(levels, logits)[1:], config).backward()
    probs = [torch.softmax(l.detach(), dim=1) for l in logits]
    propagator = StatePropagator(levels, 5, torch.float64)
    cells = propagator.forward(probs)
    for got, want in zip(cells, _propagate(levels, [l.detach() for l in logits])):
        torch.testing.assert_close(got, want)
    leaves = [c.requires_grad_() for c in cells[1:]]
    cell_grads = [torch.zeros_like(cells[0])] + list(torch.autograd.grad(coverage_objective(leaves, config), leaves))
    for t, (g, p, l) in enumerate(zip(propagator.backward(probs, cell_grads), probs, logits)):
        torch.testing.assert_close(p * (g - (g * p).sum(1, keepdim=True)), l.grad, msg=f"level {t}")
    with pytest.raises(ValueError, match="expected torch.float64 tensors, got torch.float32"):
        propagator.forward([p.float() for p in probs])
