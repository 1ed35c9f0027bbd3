"""The coverage method's propagation and its gradient by hand (the adjoint), without autograd over the states.

Shapes: M_t merged states of level t, n_t cells of level t, A actions, T horizon.

The ascent spends nearly all its time in two passes over the ``M_t * A`` (state, action) pairs of every level.
Autograd records several ``[M_t, A]`` temporaries per level and step and frees them again (the page faults of
those fresh allocations cost about a fifth of the time), and the sum over a cell's states of ``[M_t, A]`` rows
(``index_add_`` along dim 0) is slow on CPU. Here the passes write into buffers allocated once, with int32
indices (half the memory traffic of int64), and the sums over cells are products with a sparse CSR matrix
``[n_t, M_t]`` of cell membership (about 4x faster than ``index_add_`` on the rows):

- forward: ``m_{t+1}[succ(s, a)] += m_t[s] * pi_t[c(s), a]``; cell masses ``P_t[c] = sum_{s in c} m_t[s]``;
- backward, for an objective ``J(P_1, ..., P_T)`` with cell gradients ``g_t = dJ/dP_t``:
  ``lam_T[s] = g_T[c(s)]``; ``lam_t[s] = g_t[c(s)] + sum_a pi_t[c(s), a] * lam_{t+1}[succ(s, a)]``;
  ``dJ/dpi_t[c, a] = sum_{s in c} m_t[s] * lam_{t+1}[succ(s, a)]``.
"""

from __future__ import annotations

import warnings
from typing import TYPE_CHECKING

import torch

if TYPE_CHECKING:
    from precompute.coverage.reachable import ReachableLevels

__all__ = ["StatePropagator"]


def cell_membership(state_cell: torch.Tensor, num_cells: int, dtype: torch.dtype) -> torch.Tensor:
    """The sparse CSR matrix ``[n, M]`` with a 1 at (cell of state s, s): its products sum states per cell."""
    counts = torch.bincount(state_cell, minlength=num_cells)
    crow = torch.cat((torch.zeros(1, dtype=torch.int64), counts.cumsum(0)))
    col = torch.argsort(state_cell, stable=True)
    with warnings.catch_warnings():  # "sparse CSR support is in beta": the product used here is long stable
        warnings.simplefilter("ignore", UserWarning)
        return torch.sparse_csr_tensor(crow, col, torch.ones(len(state_cell), dtype=dtype),
                                       size=(num_cells, len(state_cell)))


class StatePropagator:
    """Propagates per-cell action probabilities through the merged states; gradients by the adjoint."""

    def __init__(self, levels: ReachableLevels, num_actions: int, dtype: torch.dtype = torch.float32) -> None:
        self.A = num_actions
        self.dtype = dtype
        self.sizes = [len(c) for c in levels.cells]  # n_t
        self.states = list(levels.num_states)  # M_t
        self.state_cell = [sc.to(torch.int32) for sc in levels.state_cell]  # [M_t]
        self.members = [cell_membership(sc, n, dtype) for sc, n in zip(levels.state_cell, self.sizes)]  # [n_t, M_t]
        # a successor pruned by a map (-1) points at state 0 with a weight of 0: its mass and gradient are dropped
        self.alive = [None if bool((s >= 0).all()) else (s >= 0).to(dtype) for s in levels.successor]  # [M_t, A]
        self.successor = [s.clamp(min=0).reshape(-1).to(torch.int32) for s in levels.successor]  # [M_t * A]
        self.mass = [torch.zeros(M, dtype=dtype) for M in self.states]  # [M_t] of the last forward
        widest = max(M * num_actions for M in self.states[:-1]) if len(self.states) > 1 else 0
        self._pairs = (torch.empty(widest, dtype=dtype), torch.empty(widest, dtype=dtype))
        self._lam = (torch.empty(max(self.states), dtype=dtype), torch.empty(max(self.states), dtype=dtype))

    def _pair_view(self, i: int, t: int) -> torch.Tensor:
        """Buffer ``i`` as the ``[M_t, A]`` (state, action) pairs of level t."""
        M = self.states[t]
        return self._pairs[i][: M * self.A].view(M, self.A)

    def forward(self, probs: list[torch.Tensor]) -> list[torch.Tensor]:
        """Cell masses ``[n_t]`` of every level for action probabilities ``[n_t, A]`` per level t < T."""
        self.mass[0].fill_(1.0)
        for t, pi in enumerate(probs):
            q = torch.index_select(pi, 0, self.state_cell[t], out=self._pair_view(0, t))
            q.mul_(self.mass[t].unsqueeze(1))
            if self.alive[t] is not None:
                q.mul_(self.alive[t])
            self.mass[t + 1].zero_().index_add_(0, self.successor[t], q.view(-1))
        return [(C @ m.unsqueeze(1)).squeeze(1) for C, m in zip(self.members, self.mass)]

    def backward(self, probs: list[torch.Tensor], cell_grads: list[torch.Tensor]) -> list[torch.Tensor]:
        """``dJ/dpi_t`` ``[n_t, A]`` per level t < T from ``g_t = dJ/dP_t`` ``[n_t]`` per level t <= T (the
        state masses are those of the last :meth:`forward`, which must have had the same ``probs``)."""
        T = len(probs)
        lam = torch.index_select(cell_grads[T], 0, self.state_cell[T], out=self._lam[T % 2][: self.states[T]])
        grads: list[torch.Tensor] = [torch.empty(0)] * T
        for t in reversed(range(T)):
            ahead = torch.index_select(lam, 0, self.successor[t], out=self._pair_view(0, t).view(-1))
            ahead = ahead.view(-1, self.A)  # lam_{t+1} of each (state, action)'s successor [M_t, A]
            if self.alive[t] is not None:
                ahead.mul_(self.alive[t])
            weighted = torch.mul(ahead, self.mass[t].unsqueeze(1), out=self._pair_view(1, t))
            grads[t] = self.members[t] @ weighted
            if t > 0:  # lam_0 is not needed: level 0 holds the origin alone
                pis = torch.index_select(probs[t], 0, self.state_cell[t], out=self._pair_view(1, t))
                lam = torch.sum(pis.mul_(ahead), 1, out=self._lam[t % 2][: self.states[t]])
                lam.add_(cell_grads[t].index_select(0, self.state_cell[t]))
        return grads
