"""One step of a Dubins car (:class:`~cuniform_torch.systems.models.Dubins`) for one rollout, as a compiled function the whole-rollout loops share (numba, imported when
first used): the map policy's (:mod:`cuniform_torch.maps.rollout_loops`) and the table's
(:mod:`cuniform_torch.tables.lookup_loops`). Module-level, so numba's disk cache finds it again.
"""

from __future__ import annotations

import math

import numpy as np

from cuniform_torch.common.compiled import njit

__all__ = ["dubins_advance"]


@njit(nogil=True, inline="always")
def dubins_advance(states, t, i, rate, dt, speed, pi, two_pi):
    """Row ``i`` of ``states [T+1, 3, N]`` (float32, start frame) from step ``t`` to ``t + 1`` at turn rate
    ``rate``: the heading ``wrap(theta + rate dt)``, then ``(x, y) += (speed cos, speed sin) dt`` of the new heading
    (the torch step's arithmetic, to float rounding)."""
    a_val = rate * dt + states[t, 2, i] + pi
    m = np.fmod(a_val, two_pi)
    if m < 0:
        m += two_pi
    th = m - pi
    states[t + 1, 2, i] = th
    states[t + 1, 0, i] = states[t, 0, i] + (np.float32(math.cos(th)) * speed) * dt
    states[t + 1, 1, i] = states[t, 1, i] + (np.float32(math.sin(th)) * speed) * dt
