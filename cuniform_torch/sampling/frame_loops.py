"""The compiled loops of :mod:`cuniform_torch.sampling.kernels` (numba, imported when first used). Module-level
functions, so numba's disk cache finds them again in the next process (a loop made inside a function is
compiled anew in every process).
"""

from __future__ import annotations

import numpy as np

from cuniform_torch.common.compiled import njit

__all__ = ["to_world", "to_world_time_major"]

@njit(nogil=True, inline="always")
def heading(lth, pth, pi, two_pi):
    """``wrap(lth + pth)`` as ``se2_to_world`` computes it: ``((a + pi) mod 2 pi) - pi`` with torch's
    ``remainder`` (fmod, then + 2 pi when negative)."""
    a = (lth + pth) + pi
    # fmod is slow, and for a in [0, 4 pi) the remainder is a or a - 2 pi, exactly (Sterbenz): only rare a's call it
    if a >= two_pi:
        m = a - two_pi if a < two_pi + two_pi else np.fmod(a, two_pi)
    elif a < 0:
        m = np.fmod(a, two_pi)
        if m < 0:
            m += two_pi
    else:
        m = a
    return m - pi

@njit(nogil=True, boundscheck=False)
def to_world(local, px, py, c, s, pth, pi, two_pi, out):
    """``local [T+1, d, N]`` (origin frame) -> ``out [N, T+1, d]`` (world frame of the pose)."""
    steps, d, n = local.shape
    for i in range(n):  # the output is written in order (the reads are T+1 d streams)
        for t in range(steps):
            lx, ly = local[t, 0, i], local[t, 1, i]
            out[i, t, 0] = (px + lx * c) - ly * s
            out[i, t, 1] = (py + lx * s) + ly * c
            out[i, t, 2] = heading(local[t, 2, i], pth, pi, two_pi)
            for j in range(3, d):
                out[i, t, j] = local[t, j, i]

@njit(nogil=True, boundscheck=False)
def to_world_time_major(local, px, py, c, s, pth, pi, two_pi, out):
    """``local [T+1, d, N]`` (origin frame) -> ``out [T+1, d, N]`` (world frame of the pose): every read and
    write a contiguous row; the arithmetic of ``to_world``."""
    steps, d, n = local.shape
    for t in range(steps):
        for i in range(n):
            lx, ly = local[t, 0, i], local[t, 1, i]
            out[t, 0, i] = (px + lx * c) - ly * s
            out[t, 1, i] = (py + lx * s) + ly * c
        for i in range(n):
            out[t, 2, i] = heading(local[t, 2, i], pth, pi, two_pi)
        for j in range(3, d):
            for i in range(n):
                out[t, j, i] = local[t, j, i]
