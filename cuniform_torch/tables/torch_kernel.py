"""The table policy's per-step kernel as pure tensor ops over a :class:`~cuniform_torch.tables.lookup.TableIndex`.

Shapes: N states, d state dimensions, q action dimensions, A actions, E entries.

:func:`lookup_entries` finds each state's entry (the lookup behind ``rows`` and ``action_probs``);
:func:`lookup_and_draw` also draws each state's action by Walker's alias method (``sample``). No side effects,
no host syncs: the same on CPU and GPU, and ``torch.compile`` traces them (pass the level as a 0-d tensor so
that one graph serves every level). :mod:`~cuniform_torch.tables.cpu_kernels` computes the same, value for value, as one
compiled CPU loop.
"""

from __future__ import annotations

import torch
from torch import Tensor

from cuniform_torch.tables.lookup import TableIndex

__all__ = ["lookup_entries", "lookup_and_draw", "draw"]


def lookup_entries(index: TableIndex, x: Tensor, t: int | Tensor) -> Tensor:
    """Entry of each state ``x [N, d]`` in level ``t``: ``[N]`` int32 (E: not found).

    One dimension at a time (ops on a ``[N]`` column beat ops on ``[N, d]`` broadcast over a short last axis):
    cell = round(shift + scale x), clamped into the key box (angles: to +-2^22, then mod K by an exact floor);
    the cell key accumulates by Horner's rule in exact integer arithmetic, then one gather of the dense index, or
    one hash probe and a gather from its slot to the entry.
    """
    keys = index.keys
    key: Tensor | None = None
    for dim, col in enumerate(keys.columns):
        c = torch.add(col.shift, x[:, dim], alpha=col.scale).clamp_(col.low, col.high).round_()  # [N] cell in the box
        if c.dtype != keys.key_dtype:  # a key box beyond 2^24 cells: exact keys need float64
            c = c.to(keys.key_dtype)
        if col.period:  # c mod K = c - K floor((c + 0.5) / K)
            c = c.add_(torch.add(col.half, c, alpha=col.inv_period).floor_(), alpha=-col.period)
        key = c if key is None else c.add_(key, alpha=col.span)  # [N]
    assert key is not None  # a key box has one column per state dimension, d >= 1
    base = index.level_base[t]  # 0-d
    if index.dense is not None:  # key -> index of level + key; a NaN key (INT_MIN) is clamped onto the sentinel
        top = index.dense.shape[0] - 1
        return index.dense.index_select(0, key.to(base.dtype).add_(base).clamp_(0, top))  # [N] int32 entry
    assert index.hash is not None and index.slot_entry is not None  # not dense: HASH built both
    h = torch.add(base, key.to(base.dtype), alpha=index.hash.multiplier)  # [N] hash of level + cell key
    slot = index.hash.slots(h)  # [N]
    miss = index.hash.slot_hash.index_select(0, slot) != h  # [N]
    return index.slot_entry.index_select(0, slot.masked_fill_(miss, index.hash.num_slots))  # [N] int32 entry


def draw(index: TableIndex, entry: Tensor, r: Tensor) -> Tensor:
    """Alias draw from each entry's row ``entry [N]`` with uniforms ``r [N]`` in ``[0, A)``: actions ``[N, q]``.

    Column ``j = floor(r)`` of the entry keeps ``j`` when ``r < threshold`` (``j + p_j``), else takes its alias;
    the comparison picks one of the two side-by-side outcomes by index (``2 (entry A + j) + keep``), no ``where``.
    """
    alias = index.alias
    ix = torch.add(r.to(entry.dtype), entry, alpha=index.num_actions)  # [N] entry A + floor(r)
    pick = torch.add(r < alias.threshold.index_select(0, ix), ix, alpha=2)  # [N]
    outcome = alias.outcome.index_select(0, pick)  # [N] action values (q == 1) or indices
    return outcome.unsqueeze(1) if alias.outcome_is_value else index.actions.index_select(0, outcome)  # [N, q]


def lookup_and_draw(index: TableIndex, x: Tensor, t: int | Tensor, r: Tensor) -> tuple[Tensor, Tensor]:
    """One step of ``sample``: states ``x [N, d]`` in level ``t``, uniforms ``r [N]`` in ``[0, A)`` -> actions
    ``[N, q]`` and the fallback code of each state ``[N]`` int64 (0, NEAREST or MISS of
    :mod:`~cuniform_torch.tables.lookup`; summed by the caller, as torch 2.13's inductor fails to build some int64 sum
    reductions on one CPU thread)."""
    entry = lookup_entries(index, x, t)  # [N]
    return draw(index, entry, r), index.entry_code.index_select(0, entry)

