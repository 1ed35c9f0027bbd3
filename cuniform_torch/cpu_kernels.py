"""The table policy's per-step lookup-and-sample kernel as one compiled CPU loop (numba).

Shapes: N states, d state dimensions, D key dimensions, E entries, S hash slots, B hash buckets, A actions.

On a CPU the eager kernel of :class:`~cuniform_torch.policy.TablePolicy` is about 24 small tensor ops per step,
each paying a dispatch and a pass over memory; here the same arithmetic runs in three loops over the states
(keys one dimension at a time, so the loop vectorizes; the lookup; the alias draw). It computes what the eager
kernel computes, value for value: ``shift + scale * x`` is rounded once to float32 as torch's fused
multiply-add does (the product of two float32 is exact in float64), then the same clamp, round-half-even,
exact angle wrap, Horner key, dense index or int32 hash probe (wrapping arithmetic), alias threshold and
outcome. Only float32 states are handled (a float64 multiply-add has no wider type to round from) and only
int32 hashes; the policy uses the eager kernel otherwise.

numba is imported lazily: :func:`available` says whether it can be used; the first call compiles the loops (about
a second, cached on disk next to this file when the directory is writable). :class:`TablePolicy` makes that call
when it is made, so that no control cycle pays for it.
"""

from __future__ import annotations

import functools

import numpy as np

__all__ = ["available", "sample_dense", "sample_hash"]


@functools.cache
def available() -> bool:
    """Whether numba imports (the compiled CPU kernel can be used)."""
    try:
        import numba  # noqa: F401
    except Exception:  # not installed, or broken against this numpy
        return False
    return True


@functools.cache
def _kernels():
    import numba

    jit = numba.njit(cache=True, nogil=True, boundscheck=False)

    @jit
    def keys(x, dims, scale, shift, low, high, span, period, inv_period, half, key):
        """``key [N]`` float32 cell keys of ``x [N, d]`` (NaN for a NaN state), one dimension at a time."""
        n = x.shape[0]
        for i in range(n):
            key[i] = np.float32(0.0)
        for j in range(dims.shape[0]):  # key = c_0 span_1 ... + c_{D-1}
            dim = dims[j]
            s, sh, lo, hi, sp = np.float64(scale[j]), np.float64(shift[j]), low[j], high[j], span[j]
            k, ik, hf = period[j], np.float64(inv_period[j]), np.float64(half[j])
            for i in range(n):
                v = x[i, dim]
                c = np.float32(sh + s * np.float64(v))  # torch.add(shift, x, alpha=scale): one rounding (FMA)
                c = np.rint(min(max(c, lo), hi))
                if k > 0:  # c mod K = c - K floor((c + 0.5) / K), exact (see TablePolicy._build_lookup)
                    c = c - k * np.floor(np.float32(hf + ik * np.float64(c)))
                c = c + sp * key[i]
                key[i] = c if v == v else np.float32(np.nan)

    @jit
    def draw(entry, r, thr, pair, code, num_actions, out):
        """Alias draw of each state's entry into ``out [N]``; returns the summed fallback codes."""
        total = 0
        last = num_actions - 1
        for i in range(entry.shape[0]):
            e = np.uint32(entry[i])
            total += code[e]
            rv = r[i]
            ix = e * np.uint32(num_actions) + np.uint32(min(np.int64(rv), last))
            out[i] = pair[np.uint32(2) * ix + np.uint32(rv < thr[ix])]
        return total

    @jit
    def dense_entries(key, base, dense, top, entry):
        """``entry [N]`` from the dense index at ``base + key``, clamped into it (NaN: index 0, "not found")."""
        for i in range(key.shape[0]):
            kv = key[i]
            kv = kv if kv == kv else np.float32(-2.0**31)
            entry[i] = dense[np.uint32(min(max(np.int64(kv) + base, 0), top))]

    @jit
    def hash_entries(key, base, multiplier, bucket_shift, bucket_mask, slot_shift, disp, slot_hash, slot_entry,
                     entry):
        """What KeyHash.slots and the policy's check compute in wrapping int32 arithmetic, then slot -> entry."""
        num_slots = slot_hash.shape[0]
        for i in range(key.shape[0]):
            kv = key[i]
            k = np.int64(kv) if kv == kv else np.int64(-2**31)  # torch's NaN -> int32 on x86
            h = ((base + multiplier * k + 2**31) & 0xFFFFFFFF) - 2**31  # int32 wrap, sign-extended
            low = h >> slot_shift
            slot = (low + disp[(h >> bucket_shift) & bucket_mask]) & (num_slots - 1)
            entry[i] = slot_entry[slot if slot_hash[slot] == h else num_slots]

    return keys, draw, dense_entries, hash_entries


def _prepare(x: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """States with contiguous columns, and scratch ``key [N]`` float32 and ``entry [N]`` int32."""
    if x.ndim == 2 and x.strides[0] != x.itemsize:  # row-major: columns first (the key loop vectorizes on them)
        x = np.ascontiguousarray(x.T).T
    return x, np.empty(n, dtype=np.float32), np.empty(n, dtype=np.int32)


def sample_dense(x: np.ndarray, r: np.ndarray, base: int, dims: np.ndarray, consts: tuple, dense: np.ndarray,
                 top: int, thr: np.ndarray, pair: np.ndarray, code: np.ndarray, out: np.ndarray) -> int:
    """One step of lookup and alias sampling over a dense index.

    ``x [N, d]`` float32 states (any strides), ``r [N]`` uniforms in ``[0, A)``, ``base`` the level's index offset,
    ``dims [D]`` and ``consts`` (scale, shift, low, high, span, period, inverse period, half: ``[D]`` float32 each)
    the key dimensions, ``dense`` the int32 index of entries, ``top`` its largest index, ``thr [(E+1) A]`` and
    ``pair [(E+1) A 2]`` the alias tables, ``code [E+1]`` the fallback codes. Writes the outcome of each state
    into ``out [N]`` (action values, or action indices) and returns the sum of the codes (hits + 2^32 misses).
    """
    keys, draw, dense_entries, _ = _kernels()
    x, key, entry = _prepare(x, x.shape[0])
    keys(x, dims, *consts, key)
    dense_entries(key, base, dense, top, entry)
    return int(draw(entry, r, thr, pair, code, thr.shape[0] // code.shape[0], out))


def sample_hash(x: np.ndarray, r: np.ndarray, base: int, dims: np.ndarray, consts: tuple, probe: tuple,
                thr: np.ndarray, pair: np.ndarray, code: np.ndarray, out: np.ndarray) -> int:
    """:func:`sample_dense` over an int32 :class:`~cuniform_torch.grid.KeyHash`: ``base`` is the level's hash
    base, ``probe`` = (multiplier, bucket shift, bucket mask, slot shift, displacements ``[B]``, slot hashes ``[S]``,
    slot entries ``[S+1]``)."""
    keys, draw, _, hash_entries = _kernels()
    x, key, entry = _prepare(x, x.shape[0])
    keys(x, dims, *consts, key)
    hash_entries(key, base, *probe, entry)
    return int(draw(entry, r, thr, pair, code, thr.shape[0] // code.shape[0], out))
