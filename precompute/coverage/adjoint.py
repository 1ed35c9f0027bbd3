"""The coverage method's propagation and its gradient by hand (the adjoint), without autograd over the states.

Shapes: M_t merged states of level t, n_t cells of level t, A actions, T horizon.

The ascent spends nearly all its time in two passes over the ``M_t * A`` (state, action) pairs of every level.
Each pass is one compiled loop per level (:mod:`precompute.coverage.loops`) that reads every state's successors
once and accumulates straight into the per-cell sums, with int32 indices and buffers allocated once. The torch
passes they replace (gathers, products and scatters of ``[M_t, A]`` temporaries, a sparse product for the sums
per cell) took 0.5 s per ascent step of the navigation robot's 15-step table against 0.11 s here (one thread);
:func:`precompute.coverage.method._propagate` stays as the autograd reference a test checks them against:

- forward: ``m_{t+1}[succ(s, a)] += m_t[s] * pi_t[c(s), a]``; cell masses ``P_t[c] = sum_{s in c} m_t[s]``;
- backward, for an objective ``J(P_1, ..., P_T)`` with cell gradients ``g_t = dJ/dP_t``:
  ``lam_T[s] = g_T[c(s)]``; ``lam_t[s] = g_t[c(s)] + sum_a pi_t[c(s), a] * lam_{t+1}[succ(s, a)]``;
  ``dJ/dpi_t[c, a] = sum_{s in c} m_t[s] * lam_{t+1}[succ(s, a)]``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import torch

if TYPE_CHECKING:
    from precompute.coverage.reachable import ReachableLevels

__all__ = ["StatePropagator"]


class StatePropagator:
    """Propagates per-cell action probabilities through the merged states; gradients by the adjoint."""

    def __init__(self, levels: ReachableLevels, num_actions: int, dtype: torch.dtype = torch.float32) -> None:
        from precompute.coverage import loops  # numba: compiled (or loaded from its cache) on first use

        self._loops = loops
        self.A = num_actions
        self.dtype = dtype
        np_dtype = np.float32 if dtype == torch.float32 else np.float64
        self.sizes = [len(c) for c in levels.cells]  # n_t
        self.states = list(levels.num_states)  # M_t
        self.state_cell = [sc.to(torch.int32).numpy() for sc in levels.state_cell]  # [M_t]
        # a successor pruned by a map (-1) points at state 0 with a weight of 0: its mass and gradient are dropped;
        # an empty weight array: none is pruned
        self.alive = [np.zeros(0, np_dtype) if bool((s >= 0).all()) else (s >= 0).reshape(-1).numpy().astype(np_dtype)
                      for s in levels.successor]  # [M_t * A]
        self.successor = [s.clamp(min=0).reshape(-1).to(torch.int32).numpy() for s in levels.successor]  # [M_t * A]
        self.mass = [np.zeros(M, np_dtype) for M in self.states]  # [M_t] of the last forward
        self._lam = (np.empty(max(self.states), np_dtype), np.empty(max(self.states), np_dtype))
        self._empty = np.zeros(0, np_dtype)

    def _np(self, x: torch.Tensor) -> np.ndarray:
        """A tensor of this propagator's dtype as a contiguous array (shared memory when it already is one)."""
        if x.dtype != self.dtype:
            raise ValueError(f"StatePropagator: expected {self.dtype} tensors, got {x.dtype}")
        return np.ascontiguousarray(x.detach().numpy())

    def forward(self, probs: list[torch.Tensor]) -> list[torch.Tensor]:
        """Cell masses ``[n_t]`` of every level for action probabilities ``[n_t, A]`` per level t < T."""
        T = len(probs)
        self.mass[0].fill(1.0)
        cells = [np.empty(n, self.mass[0].dtype) for n in self.sizes]
        for t, pi in enumerate(probs):
            self._loops.forward_level(self.mass[t], self.state_cell[t], self.successor[t], self.alive[t],
                                      self._np(pi), self.mass[t + 1], cells[t])
        self._loops.cell_sums(self.mass[T], self.state_cell[T], cells[T])
        return [torch.from_numpy(c) for c in cells]

    def backward(self, probs: list[torch.Tensor], cell_grads: list[torch.Tensor]) -> list[torch.Tensor]:
        """``dJ/dpi_t`` ``[n_t, A]`` per level t < T from ``g_t = dJ/dP_t`` ``[n_t]`` per level t <= T (the
        state masses are those of the last :meth:`forward`, which must have had the same ``probs``)."""
        T = len(probs)
        lam_next = np.take(self._np(cell_grads[T]), self.state_cell[T], out=self._lam[T % 2][: self.states[T]])
        grads: list[torch.Tensor] = [torch.empty(0)] * T
        for t in reversed(range(T)):
            # lam_0 is not needed: level 0 holds the origin alone
            lam = self._lam[t % 2][: self.states[t]] if t > 0 else self._empty
            grad = np.empty((self.sizes[t], self.A), self.mass[0].dtype)
            self._loops.backward_level(self.mass[t], self.state_cell[t], self.successor[t], self.alive[t],
                                       self._np(probs[t]), lam_next, self._np(cell_grads[t]), lam, grad)
            grads[t] = torch.from_numpy(grad)
            lam_next = lam
        return grads
