"""The compiled loops of :mod:`cuniform_torch.tables.cpu_kernels` (numba, imported when first used). Module-level
functions, so numba's disk cache finds them again in the next process (a loop made inside a function is
compiled anew in every process).

The whole-rollout loops (:func:`rollout_dense`, :func:`rollout_hash`) step the Dubins car one step at a time over
all N samples (:func:`dubins_step`): first the headings, then the positions, whose cosine and sine come from
:func:`sincos`, a float64 polynomial that the compiler vectorizes (libm's ``cosf`` / ``sinf`` are scalar calls:
they were half of a rollout's time), rounded to float32: within an ulp of the float32 cosine and sine.
"""

from __future__ import annotations

import numpy as np

from cuniform_torch.common.compiled import njit
from cuniform_torch.systems.dubins_loops import sincos, wrap_heading

__all__ = ["step_dense", "step_hash", "rollout_dense", "rollout_hash", "dubins_step", "sincos"]

jit = njit(nogil=True, boundscheck=False)

@jit
def keys(x, scale, shift, low, high, span, period, inv_period, half, key):
    """``key [N]`` float32 cell keys of ``x [N, d]`` (NaN for a NaN state), one dimension at a time."""
    n = x.shape[0]
    for i in range(n):
        key[i] = np.float32(0.0)
    for j in range(scale.shape[0]):  # key = c_0 span_1 ... + c_{d-1}
        s, sh, lo, hi, sp = np.float64(scale[j]), np.float64(shift[j]), low[j], high[j], span[j]
        k, ik, hf = period[j], np.float64(inv_period[j]), np.float64(half[j])
        for i in range(n):
            v = x[i, j]
            c = np.float32(sh + s * np.float64(v))  # torch.add(shift, x, alpha=scale): one rounding (FMA)
            c = np.rint(min(max(c, lo), hi))
            if k > 0:  # c mod K = c - K floor((c + 0.5) / K), exact (see lookup.KeyBox)
                c = c - k * np.floor(np.float32(hf + ik * np.float64(c)))
            c = c + sp * key[i]
            key[i] = c if v == v else np.float32(np.nan)

@jit
def draw(entry, r, threshold, outcome, code, out):
    """Alias draw of each state's entry into ``out [N]``; returns the summed fallback codes."""
    num_actions = threshold.shape[0] // code.shape[0]
    total = 0
    last = num_actions - 1
    for i in range(entry.shape[0]):
        e = np.uint32(entry[i])
        total += code[e]
        rv = r[i]
        ix = e * np.uint32(num_actions) + np.uint32(min(np.int64(rv), last))
        out[i] = outcome[np.uint32(2) * ix + np.uint32(rv < threshold[ix])]
    return total

@jit
def step_dense(x, base, scale, shift, low, high, span, period, inv_period, half, dense, threshold, outcome, code,
               r, out):
    """Keys, then ``entry`` from the dense index at ``base + key``, clamped into it (NaN: index 0, "not
    found"), then the draw."""
    n = x.shape[0]
    key = np.empty(n, dtype=np.float32)
    keys(x, scale, shift, low, high, span, period, inv_period, half, key)
    entry = np.empty(n, dtype=np.int32)
    top = dense.shape[0] - 1
    b = np.int64(base)
    for i in range(n):
        kv = key[i]
        kv = kv if kv == kv else np.float32(-2.0**31)
        entry[i] = dense[np.uint32(min(max(np.int64(kv) + b, 0), top))]
    return draw(entry, r, threshold, outcome, code, out)

@jit
def step_hash(x, base, scale, shift, low, high, span, period, inv_period, half, multiplier, bucket_shift,
              bucket_mask, slot_shift, disp, slot_hash, slot_entry, threshold, outcome, code, r, out):
    """Keys, then what KeyHash.slots and the torch kernel's check compute in wrapping int32 arithmetic, then
    slot -> entry, then the draw."""
    n = x.shape[0]
    key = np.empty(n, dtype=np.float32)
    keys(x, scale, shift, low, high, span, period, inv_period, half, key)
    entry = np.empty(n, dtype=np.int32)
    num_slots = slot_hash.shape[0]
    b = np.int64(base)
    for i in range(n):
        kv = key[i]
        k = np.int64(kv) if kv == kv else np.int64(-2**31)  # torch's NaN -> int32 on x86
        h = ((b + multiplier * k + 2**31) & 0xFFFFFFFF) - 2**31  # int32 wrap, sign-extended
        low_bits = h >> slot_shift
        slot = (low_bits + disp[(h >> bucket_shift) & bucket_mask]) & (num_slots - 1)
        entry[i] = slot_entry[slot if slot_hash[slot] == h else num_slots]
    return draw(entry, r, threshold, outcome, code, out)


@jit
def dubins_step(t, picked, outcome_is_value, actions, states, dt, speed, pi, two_pi):
    """The Dubins step of ``states[t]`` into ``states[t + 1]`` (``[T+1, 3, N]``, float32) with the turn rates
    ``picked`` (action values, or indices into ``actions`` when not ``outcome_is_value``): the heading
    ``wrap(theta + rate dt)`` (bit for bit the map kernel's), then ``(x, y) += (speed cos, speed sin) dt`` of the new
    heading, the cosine and sine from :func:`sincos` in a loop of their own (vectorized)."""
    n = picked.shape[0]
    head, new = states[t, 2], states[t + 1, 2]
    for i in range(n):
        rate = picked[i] if outcome_is_value else actions[np.int64(picked[i])]
        new[i] = wrap_heading(rate * dt + head[i], pi, two_pi)
    x0, y0, x1, y1 = states[t, 0], states[t, 1], states[t + 1, 0], states[t + 1, 1]
    for i in range(n):
        c, s = sincos(np.float64(new[i]))
        x1[i] = x0[i] + (np.float32(c) * speed) * dt
        y1[i] = y0[i] + (np.float32(s) * speed) * dt


@jit
def rollout_dense(states, uniforms, picks, levels, scale, shift, low, high, span, period, inv_period, half, dense,
                  threshold, outcome, code, outcome_is_value, actions, dt, speed, pi, two_pi):
    """A whole Dubins rollout through a dense table: per step :func:`step_dense` on ``states[t]`` (``[T+1, 3, N]``,
    start frame) with ``uniforms[t] * A``, the picks into ``picks [T, N]``, then :func:`dubins_step`. Returns the
    summed fallback codes."""
    horizon, n = uniforms.shape
    num_actions = threshold.shape[0] // code.shape[0]
    r = np.empty(n, dtype=np.float32)
    total = 0
    for t in range(horizon):
        for i in range(n):
            r[i] = uniforms[t, i] * np.float32(num_actions)
        total += step_dense(states[t].T, levels[t], scale, shift, low, high, span, period, inv_period, half, dense,
                            threshold, outcome, code, r, picks[t])
        dubins_step(t, picks[t], outcome_is_value, actions, states, dt, speed, pi, two_pi)
    return total


@jit
def rollout_hash(states, uniforms, picks, levels, scale, shift, low, high, span, period, inv_period, half, multiplier,
                 bucket_shift, bucket_mask, slot_shift, disp, slot_hash, slot_entry, threshold, outcome, code,
                 outcome_is_value, actions, dt, speed, pi, two_pi):
    """:func:`rollout_dense` through a hashed table (:func:`step_hash`)."""
    horizon, n = uniforms.shape
    num_actions = threshold.shape[0] // code.shape[0]
    r = np.empty(n, dtype=np.float32)
    total = 0
    for t in range(horizon):
        for i in range(n):
            r[i] = uniforms[t, i] * np.float32(num_actions)
        total += step_hash(states[t].T, levels[t], scale, shift, low, high, span, period, inv_period, half,
                           multiplier, bucket_shift, bucket_mask, slot_shift, disp, slot_hash, slot_entry, threshold,
                           outcome, code, r, picks[t])
        dubins_step(t, picks[t], outcome_is_value, actions, states, dt, speed, pi, two_pi)
    return total
