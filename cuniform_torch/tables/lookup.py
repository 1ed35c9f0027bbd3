"""The lookup index of a table policy: everything a per-step kernel reads, built once from a table.

Shapes: C table cells, H halo cells, E = C + H entries, A actions, q action dimensions, d state dimensions (one
key dimension per state dimension), T horizon, K dense index cells, S hash slots.

An *entry* is a (level, cell) the index can find: a table cell (entries ``0..C-1`` are the table's rows) or a
halo cell (:mod:`~cuniform_torch.tables.halo`, answered by its nearest level cell), and ``E`` means "not found". Each
of the E + 1 carries a probability row, a fallback code and an alias table (:mod:`~cuniform_torch.tables.alias`).

A state becomes a key as :class:`KeyBox` says: per dimension ``c = round(clamp(shift + scale * x))`` (angles:
then ``c mod K`` by an exact floor), and ``key = (... (c_0 span_1 + c_1) span_2 ...) + c_{d-1}`` (Horner, exact
integer arithmetic in float). The key box spans every angle index and, on the other dimensions, one cell more
than the entries on each side, so a state far outside clamps onto a border cell that holds no entry: a miss,
never a wrong cell. The level adds ``level_base[t]``, then the key is found in a dense index over the box
(:attr:`Lookup.DENSE`: one gather) or in a :class:`~cuniform_torch.grid.cells.KeyHash` (:attr:`Lookup.HASH`: one
probe, memory in proportion to the entries). :func:`build_index` settles all of it into a :class:`TableIndex`;
the kernels (:func:`~cuniform_torch.tables.torch_kernel.lookup_and_draw`, :class:`~cuniform_torch.tables.cpu_kernels.NumbaKernel`)
only read it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from cuniform_torch.common.options import Option, option_label
from cuniform_torch.grid.cells import CellKeys, Grid, KeyHash
from cuniform_torch.tables.alias import AliasTables
from cuniform_torch.tables.file import Table
from cuniform_torch.tables.halo import halo

__all__ = ["Lookup", "KeyBox", "KeyColumn", "TableIndex", "build_index", "DENSE_MIN_CELLS", "DENSE_CELLS_PER_ENTRY",
           "NEAREST", "MISS"]


@option_label('lookup')
class Lookup(Option):
    """How a :class:`~cuniform_torch.policies.table.TablePolicy` finds a state's (level, cell) among the table's entries."""

    AUTO = "auto"
    """dense when its index is small (see :data:`DENSE_MIN_CELLS`, :data:`DENSE_CELLS_PER_ENTRY`), else hash"""
    DENSE = "dense"
    """an int32 index over the key box of every level: one gather per lookup, 4 bytes per box cell"""
    HASH = "hash"
    """a static hash of the entries (:class:`~cuniform_torch.grid.cells.KeyHash`): one probe, about 16 bytes per entry"""


DENSE_MIN_CELLS = 2**23
"""``lookup="auto"`` uses a dense index of up to this many cells (32 MB) whatever the number of entries ..."""
DENSE_CELLS_PER_ENTRY = 16
"""... and beyond that while it has at most this many cells per entry (cells and halo of every level)."""
NEAREST = 1
"""fallback code of a halo entry (answered by the nearest level cell): counts in the low 32 bits"""
MISS = 1 << 32
"""fallback code of "not found" (answered uniformly): counts in the high 32 bits"""
ANGLE_CLAMP = float(2**22)
"""scaled angles are clamped to +-this first (exact integers; far beyond any real angle)"""


class KeyColumn(NamedTuple):
    """One key dimension as the torch kernel's scalar arguments (a view of :class:`KeyBox`'s tensors)."""

    scale: float
    shift: Tensor
    low: float
    high: float
    span: float
    period: float
    inv_period: float
    half: Tensor


@dataclass(frozen=True)
class KeyBox:
    """How states become cell keys: per key dimension ``j`` (state dimension ``j``) a ``[d]`` tensor each.

    The scaled value ``shift + scale * x`` is computed in the policy's dtype (one rounding: a fused multiply-add),
    clamped into ``[low, high]`` and rounded half to even; on an angle dimension (``period`` K > 0) it then wraps:
    ``c - K floor(half + inv_period c)`` (``half = 0.5 / K``: the floor's argument is never within 0.25 / K of an
    integer for ``|c| <= 2^22``, so it is exact). Keys accumulate in :attr:`key_dtype`.
    """

    scale: Tensor
    """``[d]`` policy dtype: 1 / cell size"""
    shift: Tensor
    """``[d]`` policy dtype: grid offset - the box's lowest cell, so the scaled value is the cell relative to it"""
    low: Tensor
    """``[d]`` policy dtype: clamp bound (0; angles -2^22)"""
    high: Tensor
    """``[d]`` policy dtype: clamp bound (span - 1; angles 2^22)"""
    span: Tensor
    """``[d]`` key dtype: cells of the box along the dimension (the Horner radix)"""
    period: Tensor
    """``[d]`` key dtype: K of an angle dimension, 0 otherwise"""
    inv_period: Tensor
    """``[d]`` key dtype: 1 / K (0 for a non-angle dimension)"""
    half: Tensor
    """``[d]`` policy dtype: 0.5 / K (0 for a non-angle dimension)"""
    key_dtype: torch.dtype
    """float32 when the cell part of every key is below 2^24 (exact), else float64 (float64 policies: float64)"""
    columns: tuple[KeyColumn, ...] = field(init=False, repr=False, compare=False)
    """the same constants per dimension, as the torch kernel's scalar arguments (derived here, once)"""

    def __post_init__(self) -> None:
        scalars = [t.tolist() for t in (self.scale, self.low, self.high, self.span, self.period, self.inv_period)]
        columns = tuple(KeyColumn(s, sh, lo, hi, sp, k, ik, hf) for s, lo, hi, sp, k, ik, sh, hf in
                        zip(*scalars, self.shift.unbind(), self.half.unbind()))
        object.__setattr__(self, "columns", columns)


@dataclass(frozen=True)
class TableIndex:
    """Everything the per-step kernels read, built once (:func:`build_index`); on the policy's device."""

    lookup: Lookup
    """DENSE or HASH: which of :attr:`dense` or :attr:`hash` and :attr:`slot_entry` finds the entries"""
    keys: KeyBox
    """states -> cell keys"""
    level_base: Tensor
    """``[T+1]``: what level ``t`` adds to a cell key (``t`` times the cells of one level's box): dense, int32
    ``1 + t * cells``, an index; hash, ``t * cells * multiplier`` wrapped to the hash dtype, the level's part of
    the hash ``(level key + cell key) * multiplier``"""
    dense: Tensor | None
    """``[K+1]`` int32 entry of index ``1 + key`` (E: none; index 0: the "not found" a NaN key clamps onto)"""
    hash: KeyHash | None
    """the static hash of the entries' packed keys (level and cell)"""
    slot_entry: Tensor | None
    """``[S+1]`` int32 entry of each hash slot (E: empty; slot S: "not found", where a failed probe goes)"""
    alias: AliasTables
    """per-entry alias tables, ``[(E+1) A]``"""
    entry_probs: Tensor
    """``[E+1, A]`` policy dtype: the probability row of each entry, then uniform ("not found")"""
    entry_code: Tensor
    """``[E+1]`` int64 fallback code: 0 table cell, :data:`NEAREST` halo cell, :data:`MISS` not found"""
    entry_row: Tensor
    """``[E]`` int64 table row of each entry (a halo entry: its nearest cell's)"""
    num_cells: int
    """C: entries below C are table cells, in table-row order"""
    actions: Tensor
    """``[A, q]`` policy dtype"""

    @property
    def num_entries(self) -> int:
        return int(self.entry_row.shape[0])

    @property
    def num_actions(self) -> int:
        return int(self.actions.shape[0])


def build_index(table: Table, grid: Grid, *, nearest: bool, lookup: Lookup, dtype: torch.dtype,
                device: torch.device) -> TableIndex:
    """The :class:`TableIndex` of ``table`` on ``device``: with the halo when ``nearest``; ``lookup`` AUTO picks
    DENSE or HASH (see :class:`Lookup`). ValueError when the key box is too large for the lookup asked for."""
    level = np.repeat(np.arange(table.horizon + 1), np.diff(table.level_offsets))
    keyed = torch.from_numpy(np.concatenate((level[:, None], table.cells), axis=1))  # [C, 1+d]: (t, cell)
    C = keyed.shape[0]
    entries, entry_row = keyed, torch.arange(C)
    if nearest:
        halo_cells, halo_rows = halo(keyed, grid)
        entries, entry_row = torch.cat((keyed, halo_cells)), torch.cat((entry_row, halo_rows))
    E = int(entries.shape[0])

    # the key box: every angle index, one cell more than the entries on each side of the other dimensions
    covering = CellKeys.covering(entries)
    lo, span = covering.lo.clone(), covering.span.clone()
    lo[1:] -= 1
    span[1:] += 2
    k = grid.num_angle_cells
    for dim, kk in enumerate(k):
        if kk:
            lo[1 + dim], span[1 + dim] = 0, kk
    box = CellKeys(lo, span)
    total = math.prod(span.tolist())  # every query key is below this (clamped into the box)
    spans, level_stride = span.tolist(), int(box.strides[0])
    if lookup is Lookup.AUTO:
        lookup = Lookup.DENSE if total <= max(DENSE_MIN_CELLS, DENSE_CELLS_PER_ENTRY * E) else Lookup.HASH
    if lookup is Lookup.DENSE and total >= 2**31 - 1:
        raise ValueError(f"lookup='dense': the table's key box has {total} cells, too many for an int32 index; "
                         "use lookup='hash'")
    # the cell part of a key, below prod(spans[1:]), in exact integer arithmetic: float32 below 2^24, else float64
    cell_keys = math.prod(spans[1:])
    if cell_keys >= 2**53:
        raise ValueError(f"the table's key box {spans[1:]} is too large for exact float64 keys")
    key_dtype = dtype if cell_keys < (2**24 if dtype == torch.float32 else 2**53) else torch.float64

    packed = box.pack(entries)  # [E] int64
    levels = [(t - int(lo[0])) * level_stride for t in range(table.horizon + 1)]  # the level part of each key
    dense = hash_ = slot_entry = None
    if lookup is Lookup.DENSE:
        dense = torch.full((total + 1,), E, dtype=torch.int32)
        dense[1 + packed] = torch.arange(E, dtype=torch.int32)
        dense = dense.to(device)
        level_base = torch.tensor([1 + key for key in levels], dtype=torch.int32)
    else:
        hash_ = KeyHash.build(packed, key_limit=total).to(device)
        bits = 32 if hash_.dtype == torch.int32 else 64
        # the level part is folded into the hash: h = (level_key + cell_key) m = level_key m + cell_key m
        level_base = torch.tensor([_wrap(key * hash_.multiplier, bits) for key in levels], dtype=hash_.dtype)
        rows = torch.cat((hash_.slot_rows.cpu(), torch.tensor([-1])))  # [S+1]
        slot_entry = torch.where(rows >= 0, rows, E).to(device=device, dtype=torch.int32)

    keys = _key_box(grid, lo, spans, dtype, key_dtype, device)
    code = torch.zeros(E + 1, dtype=torch.int64)
    code[C:E] = NEAREST
    code[E] = MISS
    actions = torch.from_numpy(table.actions).to(device=device, dtype=dtype)  # [A, q]
    A = actions.shape[0]
    probs = torch.from_numpy(table.action_probs).to(dtype=dtype)  # [C, A]
    uniform = torch.full((1, A), 1.0 / A, dtype=dtype)
    # one alias table per table row and one for the uniform row C, laid out per entry (halo entries repeat rows)
    alias = AliasTables.build(torch.cat((probs, uniform)).double(), torch.cat((entry_row, torch.tensor([C]))),
                              actions, dtype, device)
    return TableIndex(lookup=lookup, keys=keys, level_base=level_base.to(device), dense=dense, hash=hash_,
                      slot_entry=slot_entry, alias=alias,
                      entry_probs=torch.cat((probs[entry_row], uniform)).to(device), entry_code=code.to(device),
                      entry_row=entry_row.to(device), num_cells=C, actions=actions)


def _key_box(grid: Grid, lo: Tensor, spans: list[int], dtype: torch.dtype, key_dtype: torch.dtype,
             device: torch.device) -> KeyBox:
    """The per-dimension key constants of a box with lowest cell ``lo [1+d]`` and ``spans [1+d]`` (level first)."""
    k = grid.num_angle_cells
    d = grid.dim
    low = [-ANGLE_CLAMP if k[j] else 0.0 for j in range(d)]
    high = [ANGLE_CLAMP if k[j] else float(spans[1 + j] - 1) for j in range(d)]
    as_ = lambda values, dt: torch.tensor(values, dtype=dt, device=device)  # noqa: E731
    return KeyBox(scale=as_([1.0 / c for c in grid.cell_size], dtype),
                  shift=as_([grid.offset[j] - float(lo[1 + j]) for j in range(d)], dtype),
                  low=as_(low, dtype), high=as_(high, dtype), span=as_([float(s) for s in spans[1:]], key_dtype),
                  period=as_([float(kk) for kk in k], key_dtype),
                  inv_period=as_([1.0 / kk if kk else 0.0 for kk in k], key_dtype),
                  half=as_([0.5 / kk if kk else 0.0 for kk in k], dtype), key_dtype=key_dtype)


def _wrap(value: int, bits: int) -> int:
    """``value`` modulo 2^bits, read as a signed ``bits``-bit integer (what wrapping tensor arithmetic gives)."""
    value &= (1 << bits) - 1
    return value - (1 << bits) if value >= 1 << (bits - 1) else value
