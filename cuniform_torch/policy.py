"""Table policy: p(u | cell, t) looked up from a C-Uniform table by packed keys, on any device.

Shapes: N states, d state dimensions, A actions, q action dimensions, C table cells, H halo cells.

When the policy is made, every (level, cell) of the table is packed into one int64 key, together with a
*halo*: every cell within one cell (the 3^d - 1 neighbours, angles wrapped) of a level set that is not itself
in that level set, mapped to its nearest cell of the level set (smallest grid distance between cell indices;
ties go to the lower table row). The keys go once into a lookup structure (``lookup=``, :class:`Lookup`): a
dense int32 index over the keys' bounding box when that is small (about 17 MB for the horizon-15 Dubins
table; one gather per lookup), else a static hash table (:class:`~cuniform_torch.grid.KeyHash`, one probe per
lookup, memory in proportion to the entries). Either way a lookup is pure tensor ops (a few gathers), the same
on CPU and GPU; sampling uses per-entry alias tables (Walker's method: one uniform, two gathers).

Fallback for a state whose cell is not in L_t (``fallback=``):

* ``"nearest"`` (default): the action row of the nearest cell of L_t when the state's cell is within one cell
  of L_t (counted in ``nearest_hits``), else uniform over the actions (counted in ``misses``);
* ``"uniform"``: uniform over the actions (counted in ``misses``).

Tables are built from the origin. For an SE(2)-invariant system (``system.se2_invariant``), states given to
``action_probs`` are in the frame of the start pose; :func:`~cuniform_torch.rollout.rollout` does that change
of frame, so one table serves every start pose (``start_relative = True``).
"""

from __future__ import annotations

import functools
import itertools
import math
import os
from typing import Any, Callable

import numpy as np
import torch
from torch import Tensor

from . import cpu_kernels
from .grid import CellKeys, CellSet, Grid, KeyHash
from .options import Option, option_label
from .rollout import check_generator, check_states
from .systems import System
from .table import Table, read_table

__all__ = ["Fallback", "Kernel", "Lookup", "TablePolicy", "UniformPolicy", "load_table"]


@option_label('fallback')
class Fallback(Option):
    """What a :class:`TablePolicy` does for a state outside the level set."""

    NEAREST = "nearest"
    UNIFORM = "uniform"


@option_label('kernel')
class Kernel(Option):
    """What runs :meth:`TablePolicy.sample`'s per-step lookup and draw."""

    AUTO = "auto"
    """numba where it applies (see :data:`NUMBA`), else torch"""
    TORCH = "torch"
    """about 24 small tensor ops per step, on any device (``compile=True`` wraps them in ``torch.compile``)"""
    NUMBA = "numba"
    """one compiled CPU loop (:mod:`~cuniform_torch.cpu_kernels`): float32 on a CPU, dense or int32-hash lookup"""


@option_label('lookup')
class Lookup(Option):
    """How a :class:`TablePolicy` finds a state's (level, cell) among the table's entries."""

    AUTO = "auto"
    """dense when its index is small (see :data:`DENSE_MIN_CELLS`, :data:`DENSE_CELLS_PER_ENTRY`), else hash"""
    DENSE = "dense"
    """an int32 index over the key box of every level: one gather per lookup, 4 bytes per box cell"""
    HASH = "hash"
    """a static hash of the entries (:class:`~cuniform_torch.grid.KeyHash`): one probe, about 16 bytes per entry"""


DENSE_MIN_CELLS = 2**23
"""``lookup="auto"`` uses a dense index of up to this many cells (32 MB) whatever the number of entries ..."""
DENSE_CELLS_PER_ENTRY = 16
"""... and beyond that while it has at most this many cells per entry (cells and halo of every level)."""


def _halo(keyed: Tensor, grid: Grid) -> tuple[Tensor, Tensor]:
    """Neighbour cells of each level not in it, with the row of their nearest cell: ``([H, 1+d], [H])``.

    ``keyed [C, 1+d]`` holds (level, cell) per table row. The halo cells come out in packed-key order, each with
    the table row of least grid distance, ties to the lower row. One neighbour offset at a time, so memory stays
    in proportion to the table and the halo rather than to the 3^d - 1 neighbours of every cell.
    """
    d = grid.dim
    offsets = torch.tensor([o for o in itertools.product((-1, 0, 1), repeat=d) if any(o)], dtype=torch.int64)  # [O, d]
    dist2 = (offsets**2).sum(dim=1).tolist()  # [O] squared grid distance
    C = keyed.shape[0]
    k = grid.num_angle_cells
    box = CellKeys.covering(keyed)  # widened by the one-cell step on every non-angle dimension; angles: [0, K)
    lo, span = box.lo.clone(), box.span.clone()
    for dim in range(d):
        lo[1 + dim], span[1 + dim] = (0, k[dim]) if k[dim] else (lo[1 + dim] - 1, span[1 + dim] + 2)
    keys = CellKeys(lo, span)
    own = CellSet.build(keyed, keys)
    packed_parts, rank_parts = [], []
    rows = torch.arange(C)
    for offset, d2 in zip(offsets, dist2):
        nb = keyed.clone()  # [C, 1+d]
        nb[:, 1:] += offset
        for dim, kk in enumerate(k):
            if kk:
                nb[:, 1 + dim] = torch.remainder(nb[:, 1 + dim], kk)
        outside = own.lookup(nb) < 0  # [C]
        packed_parts.append(keys.pack(nb[outside]))
        rank_parts.append(d2 * C + rows[outside])  # ordered by (distance, source row)
    packed, rank = torch.cat(packed_parts), torch.cat(rank_parts)
    halo, inverse = torch.unique(packed, return_inverse=True)  # [H] ascending
    best = torch.full_like(halo, torch.iinfo(torch.int64).max).scatter_reduce_(0, inverse, rank, reduce="amin")
    return keys.unpack(halo), best % C


_ANGLE_CLAMP = float(2**22)  # scaled angles are clamped here first (exact integers; far beyond any real angle)


def _wrap(value: int, bits: int) -> int:
    """``value`` modulo 2^bits, read as a signed ``bits``-bit integer (what wrapping tensor arithmetic gives)."""
    value &= (1 << bits) - 1
    return value - (1 << bits) if value >= 1 << (bits - 1) else value


def _alias_tables(probs: Tensor) -> tuple[Tensor, Tensor]:
    """Walker alias tables of probability rows ``[R, A]`` (float64): thresholds ``[R, A]`` in [0, 1], aliases ``[R, A]``.

    Drawing column ``j`` uniformly, then keeping it with probability ``thr[j]`` and else taking ``alias[j]``, draws
    column ``a`` with probability ``probs[a]``. Vectorized over rows (Vose): each of the ``A - 1`` passes settles, in
    every row, the open column of least mass against the open column of most; a column of zero probability gets
    threshold 0 and a positive-probability alias, so it is never drawn.
    """
    R, A = probs.shape
    q = probs * A / probs.sum(dim=1, keepdim=True)  # [R, A] mass per column, mean 1
    thr = torch.ones_like(q)
    alias = torch.arange(A).expand(R, A).clone()  # [R, A]
    open_ = torch.ones_like(q, dtype=torch.bool)
    rows = torch.arange(R)
    for _ in range(A - 1):
        small = torch.where(open_, q, torch.inf).argmin(dim=1)  # [R]
        large = torch.where(open_, q, -torch.inf).argmax(dim=1)  # [R]
        qs = q[rows, small]
        settle = qs < 1.0  # rows whose open columns are all ~1 keep threshold 1
        thr[rows, small] = torch.where(settle, qs.clamp(min=0.0), 1.0)
        alias[rows, small] = torch.where(settle, large, small)
        q[rows, large] -= torch.where(settle, 1.0 - qs, 0.0)
        open_[rows, small] = False
    return thr, alias


class TablePolicy:
    """The Policy interface over a table: ``actions [A, q]`` and ``action_probs(x [N, d], t) -> [N, A]``.

    Also an :class:`~cuniform_torch.rollout.ActionSampler`: ``sample(x, t, generator)`` draws the actions with
    Walker's alias method, one uniform per state (what :func:`~cuniform_torch.rollout.rollout` uses).
    ``lookup`` picks how cells are found (:class:`Lookup`): a dense index over the table's key box where that is
    small (the Dubins tables: 5 MB at horizon 10, 17 MB at 15), else a static hash; both answer exactly the same.
    ``compile=True`` wraps the per-step lookup-and-sample kernel (about 17 small tensor ops) in
    ``torch.compile``: a few seconds of compilation, meant for GPUs, where it saves the launches of those small
    kernels (not measured here: no GPU). On a CPU the compiled kernel is a scalar loop (its gathers keep inductor
    from vectorizing it) and runs slower than eager: 8.1 against 6.4 ms for a table rollout at N = 10000,
    T = 15 on our 2-core machine.
    """

    start_relative = True
    """for SE(2)-invariant systems, states are relative to the start pose (the table is built at the origin)"""

    def __init__(
        self,
        table: Table,
        device: torch.device | str = "cpu",
        dtype: torch.dtype = torch.float32,
        fallback: str | Fallback = Fallback.NEAREST,
        compile: bool = False,
        lookup: str | Lookup = Lookup.AUTO,
        kernel: str | Kernel = Kernel.AUTO,
    ):
        self.table = table
        self.system: System = table.make_system()
        self.grid = Grid.of(self.system)
        self.horizon = table.horizon
        self.fallback = Fallback.parse(fallback)
        self.device = torch.device(device)
        self.dtype = dtype
        self.actions = torch.from_numpy(table.actions).to(device=self.device, dtype=dtype)  # [A, q]
        self.probs = torch.from_numpy(table.action_probs).to(device=self.device, dtype=dtype)  # [C, A]
        level = np.repeat(np.arange(table.horizon + 1), np.diff(table.level_offsets))
        keyed = torch.from_numpy(np.concatenate((level[:, None], table.cells), axis=1))  # [C, 1+d]: (t, cell)
        C = keyed.shape[0]
        entries, rows = keyed, torch.arange(C)
        if self.fallback is Fallback.NEAREST:
            halo_cells, halo_rows = _halo(keyed, self.grid)
            entries, rows = torch.cat((keyed, halo_cells)), torch.cat((rows, halo_rows))
        self.entry_row = rows.to(self.device)  # [C + H] table row of each entry
        self.num_cells = C
        self.num_halo = int(entries.shape[0] - C)
        self._build_lookup(entries, Lookup.parse(lookup))
        # one row per entry plus a last uniform row, which entry -1 (not found) selects by negative indexing
        uniform = torch.full((1, self.num_actions), 1.0 / self.num_actions, device=self.device, dtype=dtype)
        self._entry_probs = torch.cat((self.probs[self.entry_row], uniform))  # [C + H + 1, A]
        self._build_alias()
        self._sample = torch.compile(self._sample_kernel, dynamic=False) if compile else self._sample_kernel
        self.kernel = self._choose_kernel(Kernel.parse(kernel), compile)
        self.reset_counters()

    def _choose_kernel(self, kernel: Kernel, compile: bool) -> Kernel:
        """The kernel :meth:`sample` runs: numba when asked for (an error naming what rules it out) or, for
        ``auto``, when every condition holds; else torch. Settles the numba kernel's constants."""
        if kernel is Kernel.TORCH:
            return kernel
        unmet = [why for ok, why in (
            (self.device.type == "cpu", f"the policy is on {self.device}, not a CPU"),
            (self.dtype == torch.float32, f"the policy is {self.dtype}, not float32"),
            (self.lookup is Lookup.DENSE or self._hash.dtype == torch.int32, "the lookup is an int64 hash"),
            (self._key_dtype == torch.float32, "the table's key box needs float64 keys"),
            (not compile, "compile=True asks for the torch kernel"),
            (cpu_kernels.available(), "numba is not installed (pip install numba)"),
        ) if not ok]
        if unmet:
            if kernel is Kernel.NUMBA:
                raise ValueError(f"kernel='numba' cannot be used: {'; '.join(unmet)}")
            return Kernel.TORCH
        dims = np.array([k[0] for k in self._key_dims], dtype=np.int64)
        f32 = lambda values: np.array([float(v) for v in values], dtype=np.float32)  # noqa: E731
        scale, shift, low, high, span = (f32(k[i] for k in self._key_dims) for i in range(1, 6))
        angle = [k[6] or (0, 0.0, 0.0) for k in self._key_dims]
        period, inv_period, half = (f32(a[i] for a in angle) for i in range(3))
        shared = dict(dims=dims, consts=(scale, shift, low, high, span, period, inv_period, half),
                      thr=self._alias_thr.numpy(), pair=self._alias_pair.numpy(), code=self._entry_code.numpy())
        if self._dense is not None:
            self._numba_sample = functools.partial(cpu_kernels.sample_dense, dense=self._dense.numpy(),
                                                   top=self._index_top, **shared)
        else:
            h = self._hash
            probe = (h.multiplier, h.bucket_shift, h.bucket_mask, h.slot_shift, h.disp.numpy(), h.slot_hash.numpy(),
                     self._hash_entry.numpy())
            self._numba_sample = functools.partial(cpu_kernels.sample_hash, probe=probe, **shared)
        self._numba_base = [int(b) for b in self._level_base]
        # compile (or load from numba's disk cache) now, not in the first control cycle: one state, not counted
        self._numba_sample(np.zeros((1, self.grid.dim), dtype=np.float32), np.zeros(1, dtype=np.float32),
                           self._numba_base[0], out=np.empty(1, dtype=shared["pair"].dtype))
        return Kernel.NUMBA

    def _build_lookup(self, entries: Tensor, lookup: "Lookup") -> None:
        """Settle the lookup kernel's constants once (see :meth:`_entry_kernel`).

        Keys pack (level, cell) over a box that spans every angle index and, on the other dimensions, one cell
        more than the entries on each side. Scaled states are clamped into that box before rounding, so a
        state far outside lands on a border cell that holds no entry: a miss, never a wrong cell. The keys are
        looked up in a dense index over the box (``Lookup.DENSE``: one gather) or a
        :class:`~cuniform_torch.grid.KeyHash` (``Lookup.HASH``: one probe, memory in proportion to the entries).
        Either way a lookup ends at an *entry* (a table cell or a halo cell), or at E for "not found"; each of
        the E + 1 carries what sampling needs: an alias table of its row (Walker's method, so a draw is two
        gathers and a compare whatever the number of actions) and a fallback code.
        """
        grid = self.grid
        covering = CellKeys.covering(entries)
        lo, span = covering.lo.clone(), covering.span.clone()
        lo[1:] -= 1
        span[1:] += 2
        k = grid.num_angle_cells
        for dim, kk in enumerate(k):
            if kk:
                lo[1 + dim], span[1 + dim] = 0, kk
        keys = CellKeys(lo, span)
        total = math.prod(span.tolist())  # every query key is below this (clamped into the box)
        spans, strides = span.tolist(), keys.strides.tolist()
        E = int(entries.shape[0])
        if lookup is Lookup.AUTO:
            lookup = Lookup.DENSE if total <= max(DENSE_MIN_CELLS, DENSE_CELLS_PER_ENTRY * E) else Lookup.HASH
        if lookup is Lookup.DENSE and total >= 2**31 - 1:
            raise ValueError(f"lookup='dense': the table's key box has {total} cells, too many for an int32 index; "
                             "use lookup='hash'")
        self.lookup = lookup
        # the cell part of a key, below prod(spans[1:]), in exact integer arithmetic: float32 below 2^24, else float64
        cell_keys = math.prod(spans[1:])
        self._key_dtype = self.dtype if cell_keys < (2**24 if self.dtype == torch.float32 else 2**53) else torch.float64
        if cell_keys >= 2**53:
            raise ValueError(f"the table's key box {spans[1:]} is too large for exact float64 keys")
        packed = keys.pack(entries)  # [E] int64
        if lookup is Lookup.DENSE:
            # index 1 + key holds the entry of that key (E: none); index 0 is a "not found" sentinel that a key
            # which is not a number (a NaN state) is clamped onto
            dense = torch.full((total + 1,), E, dtype=torch.int32)
            dense[1 + packed] = torch.arange(E, dtype=torch.int32)
            self._dense = dense.to(self.device)
            self._index_top = total  # the largest index
            self._hash = None
            self._level_base = [torch.tensor(1 + (t - int(lo[0])) * strides[0], dtype=torch.int32, device=self.device)
                                for t in range(self.horizon + 1)]  # 0-d
        else:
            self._dense = None
            self._hash = KeyHash.build(packed, key_limit=total).to(self.device)
            bits = 32 if self._hash.dtype == torch.int32 else 64
            # the level part is folded into the hash: h = (level_key + cell_key) * m = level_key * m + cell_key * m
            m = self._hash.multiplier
            level_hash = [_wrap(((t - int(lo[0])) * strides[0]) * m, bits) for t in range(self.horizon + 1)]
            self._level_base = [torch.tensor(v, dtype=self._hash.dtype, device=self.device) for v in level_hash]  # 0-d
            # slot -> entry (E: empty, which no stored key reaches, or not found: the last slot S)
            slot_entry = torch.cat((self._hash.slot_rows.cpu(), torch.tensor([-1])))  # [S+1]
            self._hash_entry = torch.where(slot_entry >= 0, slot_entry, E).to(device=self.device, dtype=torch.int32)
            self._miss_slot = self._hash.num_slots
        # per dimension: scaled = x * scale + shift (relative to lo); angles mod K, others clamped into the box
        self._key_dims = []
        for dim in range(grid.dim):
            shift = torch.tensor(grid.offset[dim] - float(lo[1 + dim]), dtype=self.dtype, device=self.device)
            kk = k[dim]
            if kk:  # (c + 0.5) / K, never within 0.25 / K of an integer for |c| <= 2^22, so its floor is exact
                half = torch.tensor(0.5 / kk, dtype=self.dtype, device=self.device)
                self._key_dims.append((dim, 1.0 / grid.cell_size[dim], shift, -_ANGLE_CLAMP, _ANGLE_CLAMP,
                                       spans[1 + dim], (kk, 1.0 / kk, half)))
            else:
                self._key_dims.append((dim, 1.0 / grid.cell_size[dim], shift, 0.0, float(spans[1 + dim] - 1),
                                       spans[1 + dim], None))
        # per entry (E of them, then "not found" E): fallback code; the alias tables follow (see _build_alias)
        code = torch.zeros(E + 1, dtype=torch.int64)
        code[self.num_cells:E] = 1  # a halo entry: the nearest-cell fallback
        code[E] = 1 << 32  # not found: a miss, high word
        self._entry_code = code.to(self.device)

    def _build_alias(self) -> None:
        """Walker alias tables per entry: thresholds ``j + p`` ``[(E+1) A]`` and outcome pairs ``[(E+1) A 2]`` =
        (alias, j), as action values when q == 1, else as action indices (see :meth:`_sample_kernel`)."""
        A = self.num_actions
        # one alias table per table row and one for the uniform row (C), then per entry (halo entries repeat rows)
        probs = torch.cat((self.probs, self._entry_probs[-1:])).cpu().double()  # [C+1, A]
        thr, alias = _alias_tables(probs)
        entry_row = torch.cat((self.entry_row.cpu(), torch.tensor([self.num_cells])))  # [E+1]
        thr, alias = thr[entry_row], alias[entry_row]
        cols = torch.arange(A)
        self._alias_thr = (cols + thr).to(self.dtype).reshape(-1).to(self.device)  # [(E+1) A]
        pair = torch.stack((alias, cols.expand_as(alias)), dim=2).reshape(-1)  # [(E+1) A 2]: alias, then j
        if self.actions.shape[1] == 1:
            pair = self.actions[:, 0].cpu()[pair]
        self._alias_pair = pair.to(device=self.device, dtype=self.dtype if self.actions.shape[1] == 1 else torch.int32)

    @property
    def num_actions(self) -> int:
        return int(self.actions.shape[0])

    def reset_counters(self) -> None:
        """Zero ``queries`` (a host int), ``nearest_hits`` and ``misses`` (device tensors: counting never syncs)."""
        zero = lambda: torch.zeros((), dtype=torch.int64, device=self.device)  # noqa: E731
        self.queries, self._hits, self._misses, self._packed, self._packed_queries = 0, zero(), zero(), zero(), 0

    def level_size(self, t: int) -> int:
        return int(self.table.level_offsets[t + 1] - self.table.level_offsets[t])

    def _entries(self, x: Tensor, t: int) -> Tensor:
        self._check(x, t)
        return self._entry_kernel(x, self._level_base[t])

    def _check(self, x: Tensor, t: int) -> None:
        if isinstance(t, bool) or not isinstance(t, int) or not 0 <= t <= self.horizon:
            raise ValueError(f"level t={t!r} is outside the table's levels 0..{self.horizon} (an integer)")
        check_states(x, self.grid.dim, self.device)
        if x.dtype != self.dtype:
            raise ValueError(f"states are {x.dtype} but the policy is {self.dtype}")

    def _entry_kernel(self, x: Tensor, base: Tensor) -> Tensor:
        """Pure tensor kernel: states ``[N, d]`` and the level's base (0-d) -> entry ``[N]`` int32 (E: not found).

        One dimension at a time (ops on a ``[N]`` column beat ops on ``[N, d]`` broadcast over a short last axis):
        cell = round(x / delta + offset) - lo, clamped into the key box (angles: to +-2^22, then mod K by an exact
        floor); the cell key accumulates by Horner's rule in exact integer arithmetic, then one gather of the
        dense index, or one hash probe and a gather from its slot to the entry.
        """
        key = None
        for dim, scale, shift, lo, hi, span, angle in self._key_dims:
            c = torch.add(shift, x[:, dim], alpha=scale).clamp_(lo, hi).round_()  # [N] cell index relative to lo
            if c.dtype != self._key_dtype:  # a key box beyond 2^24 cells: exact keys need float64
                c = c.to(self._key_dtype)
            if angle is not None:  # c mod K = c - K floor((c + 0.5) / K)
                k, inv_k, half = angle
                c = c.add_(torch.add(half, c, alpha=inv_k).floor_(), alpha=-k)
            key = c if key is None else c.add_(key, alpha=span)  # [N]
        if self._dense is not None:  # key -> index of level + key; a NaN key (INT_MIN) is clamped onto the sentinel
            index = key.to(torch.int32).add_(base).clamp_(0, self._index_top)  # [N]
            return self._dense.index_select(0, index)  # [N] int32 entry, E where none
        h = torch.add(base, key.to(self._hash.dtype), alpha=self._hash.multiplier)  # [N] hash of level + cell key
        slot = self._hash.slots(h)  # [N]
        slot = slot.masked_fill_(self._hash.slot_hash.index_select(0, slot) != h, self._miss_slot)  # [N]
        return self._hash_entry.index_select(0, slot)  # [N] int32 entry, E where none

    def _sample_kernel(self, x: Tensor, base: Tensor, r: Tensor) -> tuple[Tensor, Tensor]:
        """Pure tensor kernel: ``x [N, d]``, level base, uniforms ``r [N]`` in ``[0, A)`` -> actions ``[N, q]`` and
        the fallback code of each state ``[N]`` (nearest-cell hit 1, miss 2^32; summed outside the kernel, as
        torch 2.13's inductor fails to build some int64 sum reductions on one CPU thread).

        Walker's alias method with one uniform: column ``j = floor(r)`` of the state's entry keeps ``j`` when
        ``r < j + p_j`` (one stored threshold), else takes its alias; the two outcomes sit side by side, so the
        comparison picks one by index (``2 (entry A + j) + keep``) instead of a ``where``.
        """
        entry = self._entry_kernel(x, base)  # [N]
        ix = torch.add(r.to(torch.int32), entry, alpha=self.num_actions)  # [N] entry * A + floor(r)
        pick = torch.add(r < self._alias_thr.index_select(0, ix), ix, alpha=2)  # [N]
        if self._alias_pair.dtype == self.dtype:  # q == 1: the pairs hold the action values
            u = self._alias_pair.index_select(0, pick).unsqueeze(1)  # [N, 1]
        else:
            u = self.actions.index_select(0, self._alias_pair.index_select(0, pick))  # [N, q]
        return u, self._entry_code.index_select(0, entry)

    def rows(self, x: Tensor, t: int) -> Tensor:
        """Table row of each state's cell in level ``t``: ``x [N, d]`` -> ``[N]`` int64 (-1: not in L_t)."""
        entry = self._entries(x, t).long()  # [N]
        return torch.where(entry < self.num_cells, entry, -1)  # entries below C are table rows

    def action_probs(self, x: Tensor, t: int) -> Tensor:
        """p(u | cell of x, t): ``x [N, d]`` -> ``[N, A]``, with the fallback for states outside L_t."""
        entry = self._entries(x, t)  # [N]
        self._count(x.shape[0], self._entry_code.index_select(0, entry).sum())
        return self._entry_probs.index_select(0, entry)  # [N, A]; entry E: the uniform row

    def _count(self, n: int, code: Tensor) -> None:
        """Add a batch of ``n`` lookups with fallback count ``code`` (nearest hits + 2^32 x misses, a device tensor).

        One add into a packed counter; it is split into the two counters before its low word could overflow.
        """
        if self._packed_queries + n >= 2**32:
            self._fold()
        self.queries += n  # a host int
        self._packed_queries += n
        self._packed += code

    def _fold(self) -> None:
        self._hits += self._packed & 0xFFFFFFFF
        self._misses += self._packed >> 32
        self._packed.zero_()
        self._packed_queries = 0

    @property
    def nearest_hits(self) -> Tensor:
        """Lookups answered by the nearest cell of the level set (a 0-d device tensor)."""
        return self._hits + (self._packed & 0xFFFFFFFF)

    @property
    def misses(self) -> Tensor:
        """Lookups that fell back to uniform probabilities (a 0-d device tensor)."""
        return self._misses + (self._packed >> 32)

    def sample(self, x: Tensor, t: int, generator: torch.Generator | None = None) -> Tensor:
        """Draw one action per state from its row (alias method, one uniform each): ``x [N, d]`` -> ``[N, q]``."""
        self._check(x, t)
        if generator is not None and not isinstance(generator, torch.Generator):
            check_generator(generator, self.device)  # the clear TypeError
        r = torch.empty(x.shape[0], device=self.device, dtype=self.dtype).uniform_(0, self.num_actions,
                                                                                    generator=generator)  # [N]
        if self.kernel is Kernel.NUMBA:
            out = torch.empty(x.shape[0], dtype=self._alias_pair.dtype)  # [N] action values (q = 1) or indices
            total = self._numba_sample(x.detach().numpy(), r.numpy(), self._numba_base[t], out=out.numpy())
            self._count(x.shape[0], total)
            return out.unsqueeze(1) if out.dtype == self.dtype else self.actions.index_select(0, out)  # [N, q]
        u, code = self._sample(x, self._level_base[t], r)
        self._count(x.shape[0], code.sum())
        return u

    @property
    def miss_rate(self) -> float:
        """Share of lookups so far that fell back to uniform probabilities (syncs the device)."""
        q = self.queries
        return int(self.misses) / q if q else 0.0

    @property
    def nearest_rate(self) -> float:
        """Share of lookups so far answered by the nearest cell of the level set (syncs the device)."""
        q = self.queries
        return int(self.nearest_hits) / q if q else 0.0


def load_table(
    path: str | os.PathLike,
    device: torch.device | str = "cpu",
    dtype: torch.dtype = torch.float32,
    fallback: str | Fallback = Fallback.NEAREST,
    compile: bool = False,
    lookup: str | Lookup = Lookup.AUTO,
    kernel: str | Kernel = Kernel.AUTO,
    trust_factory: str | Callable[..., Any] | None = None,
) -> TablePolicy:
    """Read and validate a table file (not its flow graph, which a policy does not use), and return its
    :class:`TablePolicy` on ``device``. The table's system comes from the registry or ``trust_factory``
    (see :func:`~cuniform_torch.systems.system_from_json`); nothing the file names is imported."""
    table = read_table(path, graph=False, trust_factory=trust_factory)
    return TablePolicy(table, device=device, dtype=dtype, fallback=fallback,
                       compile=compile, lookup=lookup, kernel=kernel)


class UniformPolicy:
    """Uniform random discrete actions: ``action_probs`` is ``1/A`` everywhere (the paper's "uniform" baseline).

    Has the Policy interface, so it drives :func:`~cuniform_torch.rollout.rollout` and
    :class:`~cuniform_torch.mppi.CUniformMPPI` like a table does; ``horizon=None`` means any horizon.
    """

    start_relative = False

    def __init__(self, system: System, horizon: int | None = None, device: torch.device | str = "cpu",
                 dtype: torch.dtype = torch.float32):
        self.system = system
        self.horizon = horizon
        self.device = torch.device(device)
        self.dtype = dtype
        self.actions = system.action_set(dtype=dtype, device=self.device)  # [A, q]

    def action_probs(self, x: Tensor, t: int) -> Tensor:
        """``x [N, d]`` -> ``[N, A]`` all ``1/A``."""
        check_states(x, len(self.system.periodic), self.device)
        A = self.actions.shape[0]
        return torch.full((x.shape[0], A), 1.0 / A, dtype=self.dtype, device=self.device)
