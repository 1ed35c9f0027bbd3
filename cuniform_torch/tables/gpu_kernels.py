"""The table policy's whole Dubins rollout as one GPU kernel (Triton): the CUDA counterpart of the numba loop.

Shapes: N samples, T steps, E entries, A actions.

On a GPU every tensor op is a kernel launch: the torch path of a table rollout is about 34 small kernels per
step (the lookup, the alias draw, the Dubins step, the fallback count), so a command is launch-bound even inside
a CUDA graph. Here one kernel runs the whole horizon, each sample's state in registers: per step the cell key
(:class:`~cuniform_torch.tables.lookup.KeyBox`'s arithmetic, the scaled value rounded once to float32 from an
exact float64 product, as :mod:`~cuniform_torch.tables.lookup_loops` does), the dense index, Walker's alias
draw with the given uniform, then the Dubins step (heading first, wrapped through ``fmod``, then the position
with the new heading). The same arrays as the numba kernel, the same draws; states equal to float rounding
(the GPU's ``cos`` and ``sin``).

Only dense float32 indexes on CUDA (a hashed table keeps the torch ops): :func:`unmet` says what rules an index
out. Triton ships with PyTorch's CUDA builds and is imported lazily; ``TRITON_INTERPRET=1`` runs the same kernel
on a CPU through Triton's interpreter (how the tests check it on a machine without a GPU).
"""

from __future__ import annotations

import functools
import math
import os
from typing import Any

import torch
from torch import Tensor

from cuniform_torch.tables.lookup import Lookup, TableIndex

__all__ = ["available", "interpreted", "unmet", "TritonRollout"]

BLOCK = 128
"""samples per Triton program"""

tl: Any = None
"""``triton.language``, bound by :func:`_kernel` (Triton resolves a kernel's globals when it compiles it)"""


@functools.cache
def available() -> bool:
    """Whether Triton imports (the GPU kernel can be used)."""
    try:
        import triton  # noqa: F401
        import triton.language  # noqa: F401
    except Exception:  # not installed (CPU builds of torch), or broken
        return False
    return True


def interpreted() -> bool:
    """Whether Triton runs kernels through its CPU interpreter (``TRITON_INTERPRET=1``)."""
    return os.environ.get("TRITON_INTERPRET", "0") not in ("", "0")


def unmet(index: TableIndex) -> list[str]:
    """Why :class:`TritonRollout` cannot run ``index`` (empty: it can)."""
    device = index.actions.device
    return [why for ok, why in (
        (device.type == "cuda" or (device.type == "cpu" and interpreted()),
         f"the policy is on {device}, not a CUDA device"),
        (index.actions.dtype == torch.float32, f"the policy is {index.actions.dtype}, not float32"),
        (index.lookup is Lookup.DENSE, "the lookup is a hash (the kernel reads a dense index)"),
        (index.keys.key_dtype == torch.float32, "the table's key box needs float64 keys"),
        (index.keys.scale.shape[0] == 3, "the table is not over (x, y, heading) states"),
        (available(), "triton is not installed"),
    ) if not ok]


class TritonRollout:
    """The fused Dubins rollout of one dense index (see the module docstring)."""

    def __init__(self, index: TableIndex):
        if unmet(index):
            raise ValueError(f"the Triton kernel cannot run this index: {'; '.join(unmet(index))}")
        assert index.dense is not None  # DENSE builds it
        self.index = index
        self.outcome_is_value = index.alias.outcome_is_value
        self.actions = index.actions[:, 0].contiguous()  # [A] turn rates
        self.num_actions = int(index.actions.shape[0])
        self._kernel = _kernel(interpreted())
        if index.actions.device.type == "cuda":  # compile for the table's horizon now, not in the first command
            self(torch.zeros((index.level_base.shape[0] - 1, 1), device=index.actions.device), 0.1, 0.1)

    def __call__(self, uniforms: Tensor, dt: float, speed: float) -> tuple[Tensor, Tensor, Tensor]:
        """``uniforms [T, N]`` float32 in ``[0, 1)`` on the index's device -> start-frame states ``[T+1, 3, N]``
        (time-major, from the origin), actions ``[N, T, 1]`` and the summed fallback codes (a 0-d int64 device
        tensor: nearest hits + 2^32 misses). No host sync."""
        horizon, n = uniforms.shape
        ix, keys, alias = self.index, self.index.keys, self.index.alias
        states = uniforms.new_zeros((horizon + 1, 3, n))
        picks = torch.empty((horizon, n), dtype=alias.outcome.dtype, device=uniforms.device)
        codes = torch.empty(n, dtype=torch.int64, device=uniforms.device)
        assert ix.dense is not None
        grid = (max(1, -(-n // BLOCK)),)
        self._kernel[grid](
            states, uniforms.contiguous(), picks, codes, ix.level_base, keys.scale, keys.shift, keys.low, keys.high,
            keys.span, keys.period, keys.inv_period, keys.half, ix.dense, alias.threshold, alias.outcome,
            ix.entry_code, self.actions, n, ix.dense.shape[0] - 1, float(dt), float(speed), math.pi, 2.0 * math.pi,
            HORIZON=horizon, NUM_ACTIONS=self.num_actions, OUTCOME_IS_VALUE=self.outcome_is_value, BLOCK=BLOCK)
        if self.outcome_is_value:
            taken = picks.T.unsqueeze(2)  # [N, T, 1]
        else:
            taken = self.index.actions.index_select(0, picks.T.reshape(-1).long()).view(n, horizon, -1)
        return states, taken, codes.sum()


def _rollout(states, uniforms, picks, codes, levels, scale, shift, low, high, span, period, inv_period, half,  # type: ignore[no-untyped-def]
             dense, threshold, outcome, code, actions, n, top, dt, speed, pi, two_pi,
             HORIZON: tl.constexpr, NUM_ACTIONS: tl.constexpr, OUTCOME_IS_VALUE: tl.constexpr, BLOCK: tl.constexpr):
    """One program: ``BLOCK`` samples through the whole horizon (Triton source)."""
    i = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    live = i < n
    x = tl.full([BLOCK], 0.0, tl.float32)
    y = tl.full([BLOCK], 0.0, tl.float32)
    th = tl.full([BLOCK], 0.0, tl.float32)
    total = tl.full([BLOCK], 0, tl.int64)
    for t in tl.static_range(HORIZON):
        key = tl.full([BLOCK], 0.0, tl.float32)
        nan = x != x
        for j in tl.static_range(3):
            if j == 0:
                v = x
            elif j == 1:
                v = y
            else:
                v = th
            nan = nan | (v != v)
            c = (tl.load(shift + j).to(tl.float64) + tl.load(scale + j).to(tl.float64) * v.to(tl.float64))
            c = tl.minimum(tl.maximum(c.to(tl.float32), tl.load(low + j)), tl.load(high + j))
            f = tl.floor(c)  # round half to even, spelled out: the same in the interpreter and on the GPU
            d = c - f
            c = tl.where(d > 0.5, f + 1.0, tl.where(d < 0.5, f, f + (f - 2.0 * tl.floor(f * 0.5))))
            k = tl.load(period + j)
            if k > 0:  # c mod K = c - K floor(half + c / K), exact (see lookup.KeyBox)
                w = (tl.load(half + j).to(tl.float64) + tl.load(inv_period + j).to(tl.float64) * c.to(tl.float64))
                c = c - k * tl.floor(w.to(tl.float32))
            key = c + tl.load(span + j) * key
        kv = tl.where(nan, -2147483648.0, key)
        slot = tl.minimum(tl.maximum(kv.to(tl.int64) + tl.load(levels + t).to(tl.int64), 0), top)
        entry = tl.load(dense + slot, mask=live, other=0).to(tl.int64)
        total += tl.load(code + entry, mask=live, other=0)
        r = tl.load(uniforms + t * n + i, mask=live, other=0.0) * NUM_ACTIONS
        col = tl.minimum(r.to(tl.int64), NUM_ACTIONS - 1)
        ax = entry * NUM_ACTIONS + col
        keep = (r < tl.load(threshold + ax, mask=live, other=0.0)).to(tl.int64)
        pick = tl.load(outcome + 2 * ax + keep, mask=live, other=0)
        tl.store(picks + t * n + i, pick, mask=live)
        if OUTCOME_IS_VALUE:
            rate = pick
        else:
            rate = tl.load(actions + pick, mask=live, other=0.0)
        a = rate * dt + th + pi
        m = a % two_pi  # fmod
        th = tl.where(m < 0, m + two_pi, m) - pi
        x = x + (tl.cos(th) * speed) * dt
        y = y + (tl.sin(th) * speed) * dt
        row = states + (t + 1) * 3 * n + i
        tl.store(row, x, mask=live)
        tl.store(row + n, y, mask=live)
        tl.store(row + 2 * n, th, mask=live)
    tl.store(codes + i, total, mask=live)


@functools.cache
def _kernel(interpret: bool) -> Any:
    """:func:`_rollout` made a Triton kernel: compiled for the GPU, or run by the interpreter."""
    import triton
    import triton.language

    global tl
    tl = triton.language
    fn = _rollout
    if interpret:
        from triton.runtime.interpreter import InterpretedFunction
        return InterpretedFunction(fn)
    return triton.jit(fn)
