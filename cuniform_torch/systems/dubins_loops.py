"""The Dubins car's compiled arithmetic (:class:`~cuniform_torch.systems.models.Dubins`), shared by the whole-rollout
loops (numba, imported when first used): the map policy's (:mod:`cuniform_torch.maps.rollout_loops`) and the table's
(:mod:`cuniform_torch.tables.lookup_loops`). Module-level, so numba's disk cache finds it again.

:func:`wrap_heading` wraps ``theta + rate dt`` into ``[-pi, pi)`` without ``fmod`` (a slow call) in the ranges a
step reaches, bit for bit what ``fmod`` gives; :func:`sincos` is a float64 polynomial that the compiler vectorizes
(libm's ``cos`` / ``sin`` are scalar calls), rounded to float32 within an ulp of the float32 cosine and sine.
"""

from __future__ import annotations

import math

import numpy as np

from cuniform_torch.common.compiled import njit

__all__ = ["dubins_advance", "sincos", "wrap_heading"]


@njit(nogil=True, inline="always")
def wrap_heading(turned, pi, two_pi):
    """``wrap(turned)`` into ``[-pi, pi)`` in float32 (``turned = theta + rate dt``): ``fmod(turned + pi, 2 pi)``,
    plus ``2 pi`` when negative, minus ``pi``; the same bits as that, with ``fmod`` only outside ``[-2 pi, 4 pi)``."""
    a = turned + pi
    # for a in [-2 pi, 4 pi) the remainder is a - 2 pi, a or a + 2 pi exactly (Sterbenz), what fmod and the + 2 pi
    # of a negative remainder give
    if a >= two_pi:
        m = a - two_pi if a < two_pi + two_pi else np.fmod(a, two_pi)
    elif a < 0:
        if a >= -two_pi:
            m = a + two_pi
        else:
            m = np.fmod(a, two_pi)
            if m < 0:
                m += two_pi
    else:
        m = a
    return m - pi


_TWO_OVER_PI = 2.0 / math.pi
_PIO2_HI = 1.57079632673412561417e+00
"""pi / 2 in two parts (fdlibm's): ``k pi/2`` for the quadrant ``k`` is ``k _PIO2_HI + k _PIO2_LO``, exact enough"""
_PIO2_LO = 6.07710050650619224932e-11
# Taylor coefficients of sin and cos on [-pi/4, pi/4]: the first term left out is below 3e-14 there
_S3, _S5, _S7, _S9, _S11, _S13 = (-1.0 / 6, 1.0 / 120, -1.0 / 5040, 1.0 / 362880, -1.0 / 39916800, 1.0 / 6227020800)
_C2, _C4, _C6, _C8, _C10, _C12, _C14 = (-0.5, 1.0 / 24, -1.0 / 720, 1.0 / 40320, -1.0 / 3628800, 1.0 / 479001600,
                                        -1.0 / 87178291200)


@njit(nogil=True, inline="always")
def sincos(x):
    """``(cos x, sin x)`` of a float64 ``|x| <= 2^20`` to about 2e-14 (rounded to float32: within an ulp of the
    exact values), branch-free, so a loop of them vectorizes: ``x = k pi/2 + r`` with ``|r| <= pi/4``, polynomials
    of ``r``, then the quadrant ``k mod 4`` picks and signs them."""
    k = np.rint(x * _TWO_OVER_PI)
    r = (x - k * _PIO2_HI) - k * _PIO2_LO
    z = r * r
    s = r + r * z * (_S3 + z * (_S5 + z * (_S7 + z * (_S9 + z * (_S11 + z * _S13)))))
    c = 1.0 + z * (_C2 + z * (_C4 + z * (_C6 + z * (_C8 + z * (_C10 + z * (_C12 + z * _C14))))))
    q = np.int64(k) & 3
    odd = (q & 1) != 0
    sv = c if odd else s
    cv = s if odd else c
    sv = -sv if (q & 2) != 0 else sv
    cv = -cv if ((q + 1) & 2) != 0 else cv
    return cv, sv


@njit(nogil=True, inline="always")
def dubins_advance(states, t, i, rate, dt, speed, pi, two_pi):
    """Row ``i`` of ``states [T+1, 3, N]`` (float32, start frame) from step ``t`` to ``t + 1`` at turn rate
    ``rate``: the heading :func:`wrap_heading` of ``theta + rate dt``, then ``(x, y) += (speed cos, speed sin) dt``
    of the new heading by :func:`sincos` (the torch step's arithmetic, to float rounding)."""
    th = wrap_heading(rate * dt + states[t, 2, i], pi, two_pi)
    states[t + 1, 2, i] = th
    c, s = sincos(np.float64(th))
    states[t + 1, 0, i] = states[t, 0, i] + (np.float32(c) * speed) * dt
    states[t + 1, 1, i] = states[t, 1, i] + (np.float32(s) * speed) * dt
