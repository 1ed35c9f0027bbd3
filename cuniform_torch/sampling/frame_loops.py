"""The compiled loops of :mod:`cuniform_torch.sampling.kernels` (numba, imported when first used). Module-level
functions, so numba's disk cache finds them again in the next process (a loop made inside a function is
compiled anew in every process).

Shapes: N samples, T horizon, d >= 3 state dimensions, P poses (sample ``i`` is moved to pose ``i // (N / P)``).
"""

from __future__ import annotations

import math

import numpy as np

from cuniform_torch.common.compiled import njit

__all__ = ["to_world", "to_world_time_major", "pose_trig"]

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
def pose_trig(poses, c, s):
    """``c[p], s[p] = cos, sin of poses[p, 2]`` (``poses [P, d]``): one scalar libm call per pose, in the poses'
    dtype, so a pose's values never depend on how many poses there are or where it stands among them. A heading equal to the previous one reuses its values (the rows
    of a batch repeat each robot's pose K times: B calls, not B*K)."""
    for p in range(poses.shape[0]):
        th = poses[p, 2]
        if p > 0 and th == poses[p - 1, 2]:
            c[p], s[p] = c[p - 1], s[p - 1]
        else:
            c[p], s[p] = math.cos(th), math.sin(th)

@njit(nogil=True, boundscheck=False)
def to_world(local, poses, c, s, pi, two_pi, out):
    """``local [T+1, d, N]`` (origin frame) -> ``out [N, T+1, d]`` (world frame of each sample's pose, ``poses
    [P, d]`` with cos and sin ``c, s [P]``)."""
    steps, d, n = local.shape
    k = n // poses.shape[0]
    for p in range(poses.shape[0]):
        px, py, pth, cp, sp = poses[p, 0], poses[p, 1], poses[p, 2], c[p], s[p]
        for i in range(p * k, (p + 1) * k):  # the output is written in order (the reads are T+1 d streams)
            for t in range(steps):
                lx, ly = local[t, 0, i], local[t, 1, i]
                out[i, t, 0] = (px + lx * cp) - ly * sp
                out[i, t, 1] = (py + lx * sp) + ly * cp
                out[i, t, 2] = heading(local[t, 2, i], pth, pi, two_pi)
                for j in range(3, d):
                    out[i, t, j] = local[t, j, i]

@njit(nogil=True, boundscheck=False)
def to_world_time_major(local, poses, c, s, pi, two_pi, out):
    """``local [T+1, d, N]`` (origin frame) -> ``out [T+1, d, N]`` (world frame of each sample's pose): every
    read and write a contiguous row; the arithmetic of ``to_world``."""
    steps, d, n = local.shape
    k = n // poses.shape[0]
    for t in range(steps):
        for p in range(poses.shape[0]):
            px, py, cp, sp = poses[p, 0], poses[p, 1], c[p], s[p]
            for i in range(p * k, (p + 1) * k):
                lx, ly = local[t, 0, i], local[t, 1, i]
                out[t, 0, i] = (px + lx * cp) - ly * sp
                out[t, 1, i] = (py + lx * sp) + ly * cp
        for p in range(poses.shape[0]):
            pth = poses[p, 2]
            for i in range(p * k, (p + 1) * k):
                out[t, 2, i] = heading(local[t, 2, i], pth, pi, two_pi)
        for j in range(3, d):
            for i in range(n):
                out[t, j, i] = local[t, j, i]
