"""The table policy's per-step lookup-and-draw kernel as one compiled CPU loop (numba).

Shapes: N states, d state dimensions, E entries, S hash slots, B hash buckets, A actions.

On a CPU the torch kernel (:mod:`~cuniform_torch.tables.torch_kernel`) is about 24 small tensor ops per step, each
paying a dispatch and a pass over memory; here the same arithmetic over the same
:class:`~cuniform_torch.tables.lookup.TableIndex` arrays runs in three loops over the states (keys one dimension at a
time, so the loop vectorizes; the lookup; the alias draw). It computes what the torch kernel computes, value for
value: ``shift + scale * x`` is rounded once to float32 as torch's fused multiply-add does (the product of two
float32 is exact in float64), then the same clamp, round-half-even, exact angle wrap, Horner key, dense index or
int32 hash probe (wrapping arithmetic), alias threshold and outcome. Only float32 indexes with float32 keys on a
CPU are handled (a float64 multiply-add has no wider type to round from) and only int32 hashes: :func:`unmet`
says what rules an index out.

numba is imported lazily: :func:`available` says whether it can be used; the first call compiles the loops
(about a second, cached on disk next to this file when the directory is writable). :class:`NumbaKernel` makes
that call when it is made, so that no control cycle pays for it.
"""

from __future__ import annotations

import functools
import math
from typing import Any

import numpy as np
import torch

from cuniform_torch.tables.lookup import Lookup, TableIndex

__all__ = ["available", "unmet", "NumbaKernel"]


@functools.cache
def available() -> bool:
    """Whether numba imports (the compiled CPU kernel can be used)."""
    try:
        import numba  # noqa: F401
    except Exception:  # not installed, or broken against this numpy
        return False
    return True


def unmet(index: TableIndex) -> list[str]:
    """Why :class:`NumbaKernel` cannot run ``index`` (empty: it can)."""
    return [why for ok, why in (
        (index.actions.device.type == "cpu", f"the policy is on {index.actions.device}, not a CPU"),
        (index.actions.dtype == torch.float32, f"the policy is {index.actions.dtype}, not float32"),
        (index.lookup is Lookup.DENSE or (index.hash is not None and index.hash.dtype == torch.int32),
         "the lookup is an int64 hash"),
        (index.keys.key_dtype == torch.float32, "the table's key box needs float64 keys"),
        (available(), "numba is not installed (pip install numba)"),
    ) if not ok]


class NumbaKernel:
    """:func:`~cuniform_torch.tables.torch_kernel.lookup_and_draw` of one index as a compiled CPU loop.

    Holds numpy views of the index's tensors (the same memory, no copies), so a call passes them to numba
    without converting anything; making one compiles the loops (or loads them from numba's disk cache).
    """

    def __init__(self, index: TableIndex):
        if unmet(index):
            raise ValueError(f"the numba kernel cannot run this index: {'; '.join(unmet(index))}")
        k, a = index.keys, index.alias
        self.keys = tuple(v.numpy() for v in (k.scale, k.shift, k.low, k.high, k.span, k.period, k.inv_period, k.half))
        self.level_base = index.level_base.numpy()
        self.alias = (a.threshold.numpy(), a.outcome.numpy(), index.entry_code.numpy())
        self.find_is_dense = index.lookup is Lookup.DENSE
        self.find: tuple[Any, ...]  # the dense array, or the hash's constants and arrays: step's arguments
        if self.find_is_dense:
            assert index.dense is not None  # DENSE builds it
            self.find = (index.dense.numpy(),)
        else:
            h = index.hash
            assert h is not None and index.slot_entry is not None  # HASH builds both
            self.find = (h.multiplier, h.bucket_shift, h.bucket_mask, h.slot_shift, h.disp.numpy(),
                         h.slot_hash.numpy(), index.slot_entry.numpy())
        self.step = _kernels()[0 if index.lookup is Lookup.DENSE else 1]
        self.actions, self.outcome_is_value = index.actions, a.outcome_is_value
        self._rates = self.actions[:, 0].to(torch.float32).contiguous().numpy()  # [A] a Dubins rollout's turn rates
        d = k.scale.shape[0]
        for n in (1, 2):  # numba's two layouts of x: C (one state, or d = 1) and F (what __call__ passes otherwise)
            self(np.zeros((n, d), dtype=np.float32), 0, np.zeros(n, dtype=np.float32),
                 np.empty(n, dtype=a.outcome.numpy().dtype))

    def __call__(self, x: np.ndarray, t: int, r: np.ndarray, out: np.ndarray) -> int:
        """States ``x [N, d]`` float32 (any strides) in level ``t``, uniforms ``r [N]`` in ``[0, A)``: writes each
        state's outcome into ``out [N]`` (action values, or action indices) and returns the sum of the fallback
        codes (nearest hits + 2^32 misses)."""
        if not x.flags.f_contiguous:  # columns first (the key loop vectorizes on them), one compiled layout
            x = np.asfortranarray(x)
        return int(self.step(x, self.level_base[t], *self.keys, *self.find, *self.alias, r, out))

    def sample(self, x: torch.Tensor, t: int, generator: torch.Generator | None) -> tuple[torch.Tensor, int]:
        """What the torch path of :meth:`~cuniform_torch.policies.table.TablePolicy.sample` does, on a CPU: the same
        uniforms (``uniform_(0, A)`` from ``generator``, one per state), then :meth:`draw`. ``x [N, d]`` ->
        actions ``[N, q]`` and the summed fallback codes (a host int)."""
        r = torch.empty(x.shape[0], dtype=torch.float32).uniform_(0, self.actions.shape[0], generator=generator)
        return self.draw(x, t, r)

    def draw(self, x: torch.Tensor, t: int, r: torch.Tensor) -> tuple[torch.Tensor, int]:
        """:meth:`sample` for given uniforms ``r [N]`` float32 in ``[0, A)``."""
        n = x.shape[0]
        r_np = r.detach().contiguous().numpy()
        if self.outcome_is_value:  # q == 1: the outcomes are the actions
            u = np.empty((n, 1), dtype=np.float32)
            total = self(x.detach().numpy(), t, r_np, u[:, 0])
            return torch.from_numpy(u), total  # [N, 1]
        out = np.empty(n, dtype=np.int32)
        total = self(x.detach().numpy(), t, r_np, out)
        return self.actions.index_select(0, torch.from_numpy(out)), total  # [N, q]


    def dubins_rollout(self, uniforms: torch.Tensor, dt: float, speed: float) -> tuple[torch.Tensor, torch.Tensor, int]:
        """A whole Dubins rollout from the origin of the start frame in one compiled call: per step the lookup and
        draw of :meth:`draw` (uniforms ``uniforms[t] * A``) and the Dubins step (the map kernel's arithmetic, equal
        to the torch step to float rounding). ``uniforms [T, N]`` float32 -> start-frame states ``[T+1, 3, N]``
        (time-major), actions ``[N, T, q]`` and the summed fallback codes (a host int)."""
        horizon, n = uniforms.shape
        states = torch.empty((horizon + 1, 3, n), dtype=torch.float32)
        states[0].zero_()  # the start frame's origin; the loop writes every later row
        if self.outcome_is_value:  # the picks are the actions: written [N, T] (viewed [T, N]), no copy after
            taken = torch.empty((n, horizon, 1), dtype=torch.float32)  # [N, T, 1]
            picks = taken[:, :, 0].numpy().T  # [T, N] view
        else:
            picks = np.empty((horizon, n), dtype=self.alias[1].dtype)
        rollout = _kernels()[2 if self.find_is_dense else 3]
        total = rollout(states.numpy(), uniforms.detach().contiguous().numpy(), picks, self.level_base, *self.keys,
                        *self.find, *self.alias, self.outcome_is_value, self._rates, np.float32(dt),
                        np.float32(speed), np.float32(math.pi), np.float32(2.0 * math.pi))
        if not self.outcome_is_value:
            taken = self.actions.index_select(0, torch.from_numpy(picks).T.reshape(-1).long()).view(n, horizon, -1)
        return states, taken, int(total)


@functools.cache
def _kernels():
    from cuniform_torch.tables import lookup_loops  # imports numba: only when a loop is used

    return lookup_loops.step_dense, lookup_loops.step_hash, lookup_loops.rollout_dense, lookup_loops.rollout_hash
