"""The paper's flow network between consecutive level sets, its exact max-flow, and action probabilities.

Shapes: n cells in L (= L_t), m cells in L' (= L_{t+1}), A actions, E arcs (distinct cell pairs), K recorded
transitions (cell, action, next cell, fraction).

Network (DESIGN.md): source -> each cell of L (capacity m); cell of L -> cell of L' for every pair that some
action realizes (capacity m); each cell of L' -> sink (capacity n). The lemma: the max flow equals n*m iff
the level pair admits exactly C-Uniform action probabilities.

Nodes: 0 = source, 1..n = L, n+1..n+m = L', n+m+1 = sink. Capacities are divided by gcd(n, m) before solving
(an exact rescaling that keeps scipy's int32 capacities and arc flows small); flows are reported unscaled.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import maximum_flow

__all__ = ["FlowResult", "unique_arcs", "flow_network", "solve_maxflow", "maxflow_value_networkx", "action_probs_from_flow"]

_INT32_MAX = 2**31 - 1


@dataclass
class FlowResult:
    """A max flow of one level pair."""

    arc_src: np.ndarray
    """``[E]`` int64 row in L"""
    arc_dst: np.ndarray
    """``[E]`` int64 row in L'"""
    arc_flow: np.ndarray
    """``[E]`` int64 flow on each arc (unscaled units: every cell of L can push m)"""
    value: int
    """total flow"""
    target: int
    """n * m"""

    @property
    def ratio(self) -> float:
        return self.value / self.target


def unique_arcs(src: np.ndarray, dst: np.ndarray, m: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Distinct (src, dst) pairs sorted by ``src * m + dst``, and the arc index of each input pair."""
    keys = src.astype(np.int64) * m + dst
    uniq, inverse = np.unique(keys, return_inverse=True)
    return uniq // m, uniq % m, inverse.reshape(-1)


def flow_network(n: int, m: int, arc_src: np.ndarray, arc_dst: np.ndarray, scale: int = 1) -> sp.csr_array:
    """The capacity matrix of the network (int32 CSR over ``n + m + 2`` nodes), capacities divided by ``scale``."""
    if n < 1 or m < 1:
        raise ValueError(f"flow_network needs non-empty levels, got n={n}, m={m}")
    if m % scale or n % scale:
        raise ValueError(f"scale {scale} must divide n={n} and m={m}")
    source, sink = 0, n + m + 1
    E = len(arc_src)
    rows = np.concatenate((np.full(n, source), 1 + arc_src, n + 1 + np.arange(m)))
    cols = np.concatenate((1 + np.arange(n), n + 1 + arc_dst, np.full(m, sink)))
    caps = np.concatenate((np.full(n, m // scale), np.full(E, m // scale), np.full(m, n // scale))).astype(np.int32)
    return sp.csr_array((caps, (rows.astype(np.int32), cols.astype(np.int32))), shape=(n + m + 2, n + m + 2))


def solve_maxflow(n: int, m: int, arc_src: np.ndarray, arc_dst: np.ndarray) -> FlowResult:
    """Exact integer max flow (scipy's Dinic) of the network on distinct arcs ``arc_src, arc_dst [E]``."""
    g = math.gcd(n, m)
    if max(n, m) > _INT32_MAX:  # scipy keeps capacities and arc flows in int32 (its total flow is int64)
        raise ValueError(f"level pair too large for scipy's int32 capacities: n={n}, m={m}")
    net = flow_network(n, m, arc_src, arc_dst, scale=g)
    res = maximum_flow(net, 0, n + m + 1, method="dinic")
    flow = res.flow.tocoo()
    r, c, v = flow.row.astype(np.int64), flow.col.astype(np.int64), flow.data.astype(np.int64)
    mid = (r >= 1) & (r <= n) & (c >= n + 1) & (c <= n + m) & (v > 0)
    got_keys = (r[mid] - 1) * m + (c[mid] - n - 1)
    arc_keys = arc_src.astype(np.int64) * m + arc_dst  # sorted (unique_arcs)
    arc_flow = np.zeros(len(arc_keys), dtype=np.int64)
    pos = np.searchsorted(arc_keys, got_keys)
    np.add.at(arc_flow, pos, v[mid] * g)
    value = int(res.flow_value) * g
    return FlowResult(arc_src.astype(np.int64), arc_dst.astype(np.int64), arc_flow, value, n * m)


def maxflow_value_networkx(n: int, m: int, arc_src: np.ndarray, arc_dst: np.ndarray) -> int:
    """The same max-flow value by networkx (an independent, slower solver; for cross-checks on small levels)."""
    import networkx as nx

    net = flow_network(n, m, arc_src, arc_dst).tocoo()
    graph = nx.DiGraph()
    graph.add_weighted_edges_from(zip(net.row.tolist(), net.col.tolist(), net.data.tolist()), weight="capacity")
    return int(nx.maximum_flow_value(graph, 0, n + m + 1))


def action_probs_from_flow(
    n: int,
    num_actions: int,
    src: np.ndarray,
    act: np.ndarray,
    arc_index: np.ndarray,
    frac: np.ndarray,
    flow: FlowResult,
) -> tuple[np.ndarray, np.ndarray]:
    """p(u | cell) from a max flow; returns ``(probs [n, A] float64, zero_outflow [n] bool)``.

    The flow of each arc (cell -> next cell) is shared among the actions that realize it, in proportion to the
    recorded point fractions ``frac [K]`` of those (cell, action) pairs (``arc_index [K]`` maps each recorded
    transition to its arc). p(u | cell) = the cell's flow on action u / the cell's total outflow. A cell with
    zero outflow (possible only when the max flow falls short of n*m) gets uniform probabilities.
    """
    A = num_actions
    frac_per_arc = np.bincount(arc_index, weights=frac, minlength=len(flow.arc_flow))
    share = frac / frac_per_arc[arc_index]
    action_flow = flow.arc_flow[arc_index] * share  # [K]
    raw = np.bincount(src * A + act, weights=action_flow, minlength=n * A).reshape(n, A)
    out = raw.sum(axis=1)
    zero = out <= 0
    probs = np.where(zero[:, None], 1.0 / A, raw / np.where(zero, 1.0, out)[:, None])
    return probs, zero
