"""The compiled loops of :mod:`cuniform_torch.maps.kernels` (numba, imported when first used). Module-level
functions, so numba's disk cache finds them again in the next process (a loop made inside a function is
compiled anew in every process).
"""

from __future__ import annotations

import math

import numpy as np

from cuniform_torch.common.compiled import njit
from cuniform_torch.systems.dubins_loops import dubins_advance, sincos

__all__ = ["features", "draw_and_step", "draw_step_features"]

@njit(nogil=True, inline="always")
def read_channels(fmap, ix, iy, feat, i, k):
    """Bilinear reads of every channel of ``fmap [C, H, W]`` at pixel coordinates ``(ix, iy)`` (column, row) into
    ``feat[i, k:k + C]``; zero off the map. The taps, whether each is on the map, and their weights are found once
    for all channels (not per channel: that was most of a read); each channel's sum takes the taps in the same
    order, with the same products ``(x weight * y weight) * value``, as one read of a single channel."""
    H, W = fmap.shape[1], fmap.shape[2]
    x0f, y0f = math.floor(ix), math.floor(iy)
    wx, wy = ix - x0f, iy - y0f
    x0, y0 = int(x0f), int(y0f)
    x1, y1 = x0 + 1, y0 + 1
    one = np.float32(1.0)
    in_x0, in_x1, in_y0, in_y1 = 0 <= x0 < W, 0 <= x1 < W, 0 <= y0 < H, 0 <= y1 < H
    a00, a01, a10, a11 = in_y0 and in_x0, in_y0 and in_x1, in_y1 and in_x0, in_y1 and in_x1  # row, column
    w00, w01 = (one - wx) * (one - wy), wx * (one - wy)
    w10, w11 = (one - wx) * wy, wx * wy
    for ch in range(fmap.shape[0]):
        v = np.float32(0.0)
        if a00:
            v += w00 * fmap[ch, y0, x0]
        if a01:
            v += w01 * fmap[ch, y0, x1]
        if a10:
            v += w10 * fmap[ch, y1, x0]
        if a11:
            v += w11 * fmap[ch, y1, x1]
        feat[i, k + ch] = v

@njit(nogil=True, boundscheck=False)
def features(t, states, feat, ok, counts, fmap, probes, geo):
    """The first layer's inputs of the states at step ``t`` (``states [T+1, 3, N]``) into ``feat [N, F]``,
    ``ok [N]`` (inside the support box and finite) and the near / miss counters ``counts [2]``."""
    n_states = states.shape[2]
    channels = fmap.shape[0]
    ox, oy, res, half_x, half_y, cell_x, cell_y = geo[2], geo[3], geo[4], geo[5], geo[6], geo[7], geo[8]
    for i in range(n_states):
        x, y, th = states[t, 0, i], states[t, 1, i], states[t, 2, i]
        cv, sv = sincos(np.float64(th))  # the step's polynomial, not two libm calls
        c, s = np.float32(cv), np.float32(sv)
        feat[i, 0], feat[i, 1], feat[i, 2], feat[i, 3] = x, y, c, s
        excess = max((abs(x) - half_x) / cell_x, (abs(y) - half_y) / cell_y)
        finite = math.isfinite(x) and math.isfinite(y) and math.isfinite(th)
        miss = not finite or not excess <= 1.0
        ok[i] = not miss
        if miss:
            counts[1] += 1
        elif excess > 0.0:
            counts[0] += 1
        k = 4
        for p in range(probes.shape[0]):
            if finite:
                ahead, left = probes[p, 0], probes[p, 1]
                px = (x + c * ahead) - s * left
                py = (y + s * ahead) + c * left
                ix = (px - ox) / res - np.float32(0.5)
                iy = (py - oy) / res - np.float32(0.5)
                read_channels(fmap, ix, iy, feat, i, k)
            else:
                for ch in range(channels):
                    feat[i, k + ch] = np.float32(0.0)
            k += channels

@njit(nogil=True, boundscheck=False)
def draw_and_step(t, logits, uniforms, states, picks, actions, ok, geo, pi, two_pi):
    """Step ``t``'s draw from ``logits [N, A]`` (uniform where not ``ok``) with ``uniforms[t]``, into
    ``picks [T, N]``, and the Dubins step of ``states[t]`` into ``states[t + 1]``."""
    n_actions = logits.shape[1]
    dt, speed = geo[0], geo[1]
    weights = np.empty(n_actions, dtype=np.float32)  # a row's exp(logit - max), made once for its two sums
    for i in range(logits.shape[0]):
        if ok[i]:
            top = logits[i, 0]
            for a in range(1, n_actions):
                top = max(top, logits[i, a])
            total = np.float32(0.0)
            for a in range(n_actions):
                weights[a] = np.float32(math.exp(logits[i, a] - top))
                total += weights[a]
            target = uniforms[t, i] * total
            cdf = np.float32(0.0)
            pick = n_actions - 1
            for a in range(n_actions):
                cdf += weights[a]
                if cdf > target:
                    pick = a
                    break
        else:
            pick = min(int(uniforms[t, i] * n_actions), n_actions - 1)
        picks[t, i] = pick
        dubins_advance(states, t, i, actions[pick], dt, speed, pi, two_pi)


@njit(nogil=True, boundscheck=False)
def draw_step_features(t, logits, uniforms, states, picks, actions, ok, geo, pi, two_pi, feat, counts, fmap, probes):
    """:func:`draw_and_step` of step ``t``, then (before the last step) :func:`features` of the states it reached:
    one call per step instead of two (a call's dispatch costs microseconds, as much as the work at small N)."""
    draw_and_step(t, logits, uniforms, states, picks, actions, ok, geo, pi, two_pi)
    if t + 1 < states.shape[0] - 1:  # states [T+1, 3, N]: the last step needs no features
        features(t + 1, states, feat, ok, counts, fmap, probes, geo)
