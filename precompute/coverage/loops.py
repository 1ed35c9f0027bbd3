"""The coverage ascent's two passes over the (state, action) pairs as compiled loops (numba, imported when first
used by :mod:`precompute.coverage.adjoint`). Module-level, so numba's disk cache finds them again.

Shapes: M states of level t, M' states of level t+1, n cells of level t, A actions.

One pass per level and direction reads each state's successors once and accumulates straight into the per-cell
sums, where the torch passes wrote and re-read several ``[M, A]`` temporaries.
"""

from __future__ import annotations

import numpy as np

from cuniform_torch.common.compiled import njit

__all__ = ["forward_level", "backward_level", "cell_sums", "level_transitions", "bin_box", "bin_keys"]


@njit(nogil=True)
def forward_level(mass, state_cell, successor, alive, pi, mass_next, cell_mass):
    """Level t's cell masses and level t+1's state masses.

    ``mass [M]``, ``state_cell [M]`` (int32), ``successor [M * A]`` (int32, a pruned pair points at 0),
    ``alive [M * A]`` (1 / 0; an empty array: all alive), ``pi [n, A]``; writes ``mass_next [M']`` (zeroed here)
    and ``cell_mass [n]`` (zeroed here): ``mass_next[succ(s, a)] += mass[s] pi[c(s), a]``,
    ``cell_mass[c] = sum_{s in c} mass[s]``."""
    A = pi.shape[1]
    mass_next[:] = 0
    cell_mass[:] = 0
    masked = alive.shape[0] > 0
    for s in range(mass.shape[0]):
        c = state_cell[s]
        m = mass[s]
        cell_mass[c] += m
        base = s * A
        for a in range(A):
            q = m * pi[c, a]
            if masked:
                q *= alive[base + a]
            mass_next[successor[base + a]] += q


@njit(nogil=True)
def backward_level(mass, state_cell, successor, alive, pi, lam_next, cell_grad, lam, grad):
    """The adjoint of :func:`forward_level` for one level.

    ``lam_next [M']`` (``lam_{t+1}``), ``cell_grad [n]`` (``g_t = dJ/dP_t``); writes ``grad [n, A]`` (zeroed
    here), ``dJ/dpi_t[c, a] = sum_{s in c} mass[s] lam_{t+1}[succ(s, a)]``, and ``lam [M]`` (an empty array: not
    needed), ``lam_t[s] = g_t[c(s)] + sum_a pi_t[c(s), a] lam_{t+1}[succ(s, a)]``."""
    A = pi.shape[1]
    grad[:, :] = 0
    masked = alive.shape[0] > 0
    want_lam = lam.shape[0] > 0
    for s in range(mass.shape[0]):
        c = state_cell[s]
        m = mass[s]
        base = s * A
        acc = 0.0 * m  # of the arrays' dtype; g_t is added after the sum over actions, as the torch passes did
        for a in range(A):
            ahead = lam_next[successor[base + a]]
            if masked:
                ahead *= alive[base + a]
            grad[c, a] += m * ahead
            acc += pi[c, a] * ahead
        if want_lam:
            lam[s] = acc + cell_grad[c]


@njit(nogil=True)
def cell_sums(mass, state_cell, out):
    """``out[c] = sum_{s in c} mass[s]`` (``out [n]`` zeroed here): the last level's cell masses."""
    out[:] = 0
    for s in range(mass.shape[0]):
        out[state_cell[s]] += mass[s]


@njit(nogil=True)
def level_transitions(state_cell, successor, next_cell, state_mass, num_cells, num_actions):
    """The recorded transitions of one level: each (cell, action, next cell) that some state of the cell reaches,
    in ascending (cell, action, next cell) order, with the fraction of the (cell, action)'s mass that lands there.

    ``state_cell [M]``, ``successor [M * A]`` (-1: pruned by a map), ``next_cell [M']`` (the cell of each state of
    level t+1), ``state_mass [M]`` (float64, the mass of each state before acting). Returns ``src, act, dst``
    (int64 ``[K]``) and ``frac`` (float64 ``[K]``): the mass-weighted fraction, or the fraction of the states when
    the (cell, action) has no mass. The sums run over a cell's states in ascending order, as the sorted
    ``torch.unique`` and ``index_add`` of the torch assembly did, so the fractions are the same to the bit."""
    M = state_cell.shape[0]
    A = num_actions
    # the states of each cell, ascending (a stable counting sort)
    start = np.zeros(num_cells + 1, np.int64)
    for s in range(M):
        start[state_cell[s] + 1] += 1
    widest = 0
    for c in range(num_cells):
        widest = max(widest, start[c + 1])
        start[c + 1] += start[c]
    order = np.empty(M, np.int64)
    fill = start[:-1].copy()
    for s in range(M):
        c = state_cell[s]
        order[fill[c]] = s
        fill[c] += 1
    cap = M * A
    src = np.empty(cap, np.int64)
    act = np.empty(cap, np.int64)
    dst = np.empty(cap, np.int64)
    frac = np.empty(cap, np.float64)
    bd = np.empty(widest, np.int64)  # the distinct next cells of one (cell, action), their mass and state count
    bw = np.empty(widest, np.float64)
    bc = np.empty(widest, np.float64)
    k = 0
    for c in range(num_cells):
        for a in range(A):
            used = 0
            for i in range(start[c], start[c + 1]):
                s = order[i]
                nxt = successor[s * A + a]
                if nxt < 0:
                    continue
                d = next_cell[nxt]
                j = 0
                while j < used and bd[j] != d:
                    j += 1
                if j == used:
                    bd[j] = d
                    bw[j] = 0.0
                    bc[j] = 0.0
                    used += 1
                bw[j] += state_mass[s]
                bc[j] += 1.0
            for i in range(1, used):  # ascending next cell (insertion sort: a handful of entries)
                d, w, n = bd[i], bw[i], bc[i]
                j = i - 1
                while j >= 0 and bd[j] > d:
                    bd[j + 1], bw[j + 1], bc[j + 1] = bd[j], bw[j], bc[j]
                    j -= 1
                bd[j + 1], bw[j + 1], bc[j + 1] = d, w, n
            tot_w = 0.0
            tot_c = 0.0
            for j in range(used):
                tot_w += bw[j]
                tot_c += bc[j]
            for j in range(used):
                src[k] = c
                act[k] = a
                dst[k] = bd[j]
                frac[k] = bw[j] / max(tot_w, 1e-300) if tot_w > 0 else bc[j] / tot_c
                k += 1
    return src[:k].copy(), act[:k].copy(), dst[:k].copy(), frac[:k].copy()


@njit(nogil=True)
def bin_box(states, bin_size, lo, hi):
    """The box ``lo [d]``, ``hi [d]`` (int64, written here) of the bins ``round(states / bin_size)`` of ``states
    [K, d]`` (float64; rounded half to even, as ``torch.round``)."""
    d = states.shape[1]
    for k in range(d):
        lo[k] = np.iinfo(np.int64).max
        hi[k] = np.iinfo(np.int64).min
    for i in range(states.shape[0]):
        for k in range(d):
            b = np.int64(np.rint(states[i, k] / bin_size[k]))
            lo[k] = min(lo[k], b)
            hi[k] = max(hi[k], b)


@njit(nogil=True)
def bin_keys(states, bin_size, lo, span, keys):
    """``keys [K]`` (int64, written here): the mixed-radix key of each state's bin in the box ``lo``, ``span`` of
    :func:`bin_box` (the last dimension fastest)."""
    d = states.shape[1]
    for i in range(states.shape[0]):
        key = np.int64(0)
        for k in range(d):
            key = key * span[k] + np.int64(np.rint(states[i, k] / bin_size[k])) - lo[k]
        keys[i] = key
