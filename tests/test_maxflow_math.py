"""The paper's math: the 1-D closed form (Figure 2), the max-flow lemma, probabilities from flows."""

from __future__ import annotations

import numpy as np
import pytest

from precompute.flow.closed_form import closed_form_1d, closed_form_1d_counts
from precompute.flow.maxflow import (
    action_probs_from_flow,
    maxflow_value_networkx,
    solve_maxflow,
    unique_arcs,
)

# The paper's Figure 2: n = 5 cells in L, m = 9 in L', k = 2; entries x 1/9, row i starts at column i.
FIGURE_2 = np.array(
    [
        [5, 1, 1, 1, 1, 0, 0, 0, 0],
        [0, 4, 1, 1, 1, 2, 0, 0, 0],
        [0, 0, 3, 1, 1, 1, 3, 0, 0],
        [0, 0, 0, 2, 1, 1, 1, 4, 0],
        [0, 0, 0, 0, 1, 1, 1, 1, 5],
    ]
)


def _as_transfer_matrix(counts: np.ndarray) -> np.ndarray:
    n, a = counts.shape
    out = np.zeros((n, n + a - 1), dtype=counts.dtype)
    for i in range(n):
        out[i, i : i + a] = counts[i]
    return out


def test_closed_form_reproduces_figure_2_exactly():
    counts = closed_form_1d_counts(5, 2)
    np.testing.assert_array_equal(_as_transfer_matrix(counts), FIGURE_2)
    assert (FIGURE_2.sum(axis=1) == 9).all() and (FIGURE_2.sum(axis=0) == 5).all()
    np.testing.assert_allclose(closed_form_1d(5, 2), counts / 9.0)


@pytest.mark.parametrize("n,k", [(1, 1), (3, 1), (5, 2), (8, 3), (40, 7)])
def test_closed_form_is_c_uniform(n, k):
    probs = closed_form_1d(n, k)  # [n, 2k+1]
    m = n + 2 * k
    np.testing.assert_allclose(probs.sum(axis=1), 1.0)
    # uniform L (1/n each) -> L' must be uniform (1/m each)
    np.testing.assert_allclose(_as_transfer_matrix(probs).sum(axis=0) / n, np.full(m, 1.0 / m))


def test_closed_form_rejects_bad_sizes():
    with pytest.raises(ValueError, match="n >= 1"):
        closed_form_1d(0, 2)


def _random_walk_arcs(n: int, k: int):
    src = np.repeat(np.arange(n), 2 * k + 1)
    act = np.tile(np.arange(2 * k + 1), n)
    dst = src + act
    return src, act, dst


@pytest.mark.parametrize("n,k", [(1, 2), (5, 2), (9, 2), (12, 3)])
def test_lemma_feasible_network_reaches_nm_and_every_next_cell_gets_n(n, k):
    src, act, dst = _random_walk_arcs(n, k)
    m = n + 2 * k
    arc_src, arc_dst, arc_index = unique_arcs(src, dst, m)
    flow = solve_maxflow(n, m, arc_src, arc_dst)
    assert flow.value == n * m == flow.target
    inflow = np.bincount(flow.arc_dst, weights=flow.arc_flow, minlength=m)
    outflow = np.bincount(flow.arc_src, weights=flow.arc_flow, minlength=n)
    np.testing.assert_array_equal(inflow, np.full(m, n))
    np.testing.assert_array_equal(outflow, np.full(n, m))
    # the probabilities from this flow make L' exactly uniform
    probs, zero = action_probs_from_flow(n, 2 * k + 1, src, act, arc_index, np.ones(len(src)), flow)
    assert not zero.any()
    np.testing.assert_allclose(probs.sum(axis=1), 1.0)
    next_dist = np.bincount(dst, weights=probs[src, act] / n, minlength=m)
    np.testing.assert_allclose(next_dist, np.full(m, 1.0 / m))


def test_lemma_infeasible_network_falls_short():
    # L = {0, 1}, L' = {0, 1, 2}; cell 0 reaches only next cell 0, cell 1 reaches 1 and 2.
    # Next cell 0 can receive at most 3 (one source cell) but needs n = 2: fine; next cells 1, 2 need 2 each
    # from cell 1 alone (4 > m = 3): infeasible. Max flow = 2 (cell 0 -> 0) + 3 (cell 1) = 5 < 6.
    arc_src, arc_dst = np.array([0, 1, 1]), np.array([0, 1, 2])
    flow = solve_maxflow(2, 3, arc_src, arc_dst)
    assert flow.target == 6
    assert flow.value == 5 == maxflow_value_networkx(2, 3, arc_src, arc_dst)
    assert flow.value < flow.target


def test_lemma_isolated_next_cell_is_infeasible():
    # a next cell that no arc reaches can never get its n units
    flow = solve_maxflow(2, 3, np.array([0, 1]), np.array([0, 1]))
    assert flow.value <= 2 * 3 - 2


def test_zero_outflow_cell_gets_uniform_fallback():
    # cell 1 has no arcs at all
    arc_src, arc_dst, arc_index = unique_arcs(np.array([0, 0]), np.array([0, 1]), 2)
    flow = solve_maxflow(2, 2, arc_src, arc_dst)
    probs, zero = action_probs_from_flow(2, 2, np.array([0, 0]), np.array([0, 1]), arc_index, np.ones(2), flow)
    assert zero.tolist() == [False, True]
    np.testing.assert_allclose(probs[1], [0.5, 0.5])
    np.testing.assert_allclose(probs.sum(axis=1), 1.0)


def test_arc_flow_is_shared_among_actions_by_point_fractions():
    # one cell, two actions reaching the same next cell with fractions 1 and 1/3 (the rest of action 1 -> cell 1)
    src, act, dst = np.array([0, 0, 0]), np.array([0, 1, 1]), np.array([0, 0, 1])
    frac = np.array([1.0, 1 / 3, 2 / 3])
    arc_src, arc_dst, arc_index = unique_arcs(src, dst, 2)
    flow = solve_maxflow(1, 2, arc_src, arc_dst)  # each next cell gets 1 unit
    probs, _ = action_probs_from_flow(1, 2, src, act, arc_index, frac, flow)
    # arc (0->0) carries 1: action 0 gets 1 * 1/(1+1/3) = 0.75, action 1 gets 0.25; arc (0->1) carries 1 -> action 1
    np.testing.assert_allclose(probs[0], [0.75 / 2, 1.25 / 2])


def test_scipy_and_networkx_agree_on_real_levels(dubins_table):
    table = dubins_table
    for t in range(table.horizon):
        lo, hi = table.arc_offsets[t], table.arc_offsets[t + 1]
        n, m = table.level_sizes[t], table.level_sizes[t + 1]
        if n * m > 300_000:  # networkx is slow; the small levels are the cross-check
            break
        arcs = table.arcs[lo:hi]
        a_src = arcs[:, 0] - table.level_offsets[t]
        a_dst = arcs[:, 1] - table.level_offsets[t + 1]
        assert maxflow_value_networkx(n, m, a_src, a_dst) == table.flow_value[t]
        assert solve_maxflow(n, m, a_src, a_dst).value == table.flow_value[t]
    assert t >= 5


def test_stored_arc_flows_are_a_valid_flow(dubins_table):
    table = dubins_table
    for t in range(table.horizon):
        sl = slice(table.arc_offsets[t], table.arc_offsets[t + 1])
        n, m = table.level_sizes[t], table.level_sizes[t + 1]
        arcs, f = table.arcs[sl], table.arc_flow[sl]
        out = np.bincount(arcs[:, 0] - table.level_offsets[t], weights=f, minlength=n)
        inn = np.bincount(arcs[:, 1] - table.level_offsets[t + 1], weights=f, minlength=m)
        assert (out <= m).all() and (inn <= n).all() and (f <= m).all()
        assert out.sum() == inn.sum() == table.flow_value[t]


def test_total_flow_beyond_int32_is_exact():
    """n*m/gcd(n, m) > 2^31: scipy's capacities stay int32 but the total must not overflow."""
    n, k = 50_001, 2
    m = n + 2 * k  # gcd(n, m) = 1, n*m ~ 2.5e9
    src, _, dst = _random_walk_arcs(n, k)
    arc_src, arc_dst, _ = unique_arcs(src, dst, m)
    flow = solve_maxflow(n, m, arc_src, arc_dst)
    assert n * m > 2**31 and flow.value == n * m
    assert np.bincount(flow.arc_dst, weights=flow.arc_flow, minlength=m).min() == n
