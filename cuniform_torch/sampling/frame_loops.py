"""The compiled loops of :mod:`cuniform_torch.sampling.kernels` (numba, imported when first used). Module-level
functions, so numba's disk cache finds them again in the next process (a loop made inside a function is
compiled anew in every process).

Shapes: N samples, T horizon, d >= 3 state dimensions, P poses (sample ``i`` is moved to pose ``i // (N / P)``),
R runs of equal consecutive poses.
"""

from __future__ import annotations

import math

import numpy as np

from cuniform_torch.common.compiled import njit

__all__ = ["to_world", "to_world_time_major", "pose_runs"]

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
def pose_runs(poses, k, runs, c, s, bounds):
    """The runs of equal consecutive poses of ``poses [P, d]`` (pose ``p`` owning samples ``p k .. (p+1) k - 1``):
    writes each run's ``x, y, theta`` to ``runs [R, 3]``, its cos and sin to ``c, s [R]`` and its samples' bounds
    to ``bounds [R+1]``; returns R. One scalar libm call per run, in the poses' dtype, so a pose's values never
    depend on how many poses there are or where it stands among them (a batch's ``[B*K, d]`` start rows are B
    runs: B calls, and loops as long as for ``[B, d]`` poses)."""
    r = 0
    bounds[0] = 0
    for p in range(poses.shape[0]):
        x, y, th = poses[p, 0], poses[p, 1], poses[p, 2]
        if r == 0 or x != runs[r - 1, 0] or y != runs[r - 1, 1] or th != runs[r - 1, 2]:
            runs[r, 0], runs[r, 1], runs[r, 2] = x, y, th
            c[r], s[r] = math.cos(th), math.sin(th)
            r += 1
        bounds[r] = (p + 1) * k
    return r

@njit(nogil=True, boundscheck=False)
def to_world(local, runs, c, s, bounds, pi, two_pi, out):
    """``local [T+1, d, N]`` (origin frame) -> ``out [N, T+1, d]`` (world frame: samples ``bounds[r] ..
    bounds[r+1] - 1`` moved to pose ``runs[r]`` with cos and sin ``c[r], s[r]``)."""
    steps, d, n = local.shape
    for r in range(bounds.shape[0] - 1):
        px, py, pth, cp, sp = runs[r, 0], runs[r, 1], runs[r, 2], c[r], s[r]
        for i in range(bounds[r], bounds[r + 1]):  # the output is written in order (the reads are T+1 d streams)
            for t in range(steps):
                lx, ly = local[t, 0, i], local[t, 1, i]
                out[i, t, 0] = (px + lx * cp) - ly * sp
                out[i, t, 1] = (py + lx * sp) + ly * cp
                out[i, t, 2] = heading(local[t, 2, i], pth, pi, two_pi)
                for j in range(3, d):
                    out[i, t, j] = local[t, j, i]

@njit(nogil=True, boundscheck=False)
def to_world_time_major(local, runs, c, s, bounds, pi, two_pi, out):
    """``local [T+1, d, N]`` (origin frame) -> ``out [T+1, d, N]`` (world frame, the runs of ``to_world``): every
    read and write a contiguous row; the arithmetic of ``to_world``."""
    steps, d, n = local.shape
    for t in range(steps):
        for r in range(bounds.shape[0] - 1):
            px, py, cp, sp = runs[r, 0], runs[r, 1], c[r], s[r]
            for i in range(bounds[r], bounds[r + 1]):
                lx, ly = local[t, 0, i], local[t, 1, i]
                out[t, 0, i] = (px + lx * cp) - ly * sp
                out[t, 1, i] = (py + lx * sp) + ly * cp
        for r in range(bounds.shape[0] - 1):
            pth = runs[r, 2]
            for i in range(bounds[r], bounds[r + 1]):
                out[t, 2, i] = heading(local[t, 2, i], pth, pi, two_pi)
        for j in range(3, d):
            for i in range(n):
                out[t, j, i] = local[t, j, i]
