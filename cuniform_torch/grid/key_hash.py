"""KeyHash: a static hash table of distinct non-negative int64 keys, one probe per lookup (hash and displace), in
pure tensor ops, the same on CPU and GPU. Re-exported by :mod:`cuniform_torch.grid.cells`, beside the sorted-key
:class:`~cuniform_torch.grid.cells.CellSet` it is a faster alternative to."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = ["KeyHash"]


# odd multipliers for multiplicative hashing (golden ratio, then murmur/splitmix constants), as unsigned ints
_MULTIPLIERS = {
    32: (0x9E3779B1, 0x85EBCA6B, 0xC2B2AE35, 0x27D4EB2F, 0x165667B1, 0xCC9E2D51, 0x1B873593, 0xE6546B65),
    64: (0x9E3779B97F4A7C15, 0xBF58476D1CE4E5B9, 0x94D049BB133111EB, 0xFF51AFD7ED558CCD, 0xC4CEB9FE1A85EC53,
         0xD6E8FEB86659FD93, 0xA0761D6478BD642F, 0xE7037ED1A0B428DB),
}


def _signed(value: int, bits: int) -> int:
    """The two's-complement reading of an unsigned ``bits``-bit integer (what an int32/int64 tensor holds)."""
    return value - (1 << bits) if value >= 1 << (bits - 1) else value


@dataclass(frozen=True)
class KeyHash:
    """A static hash table of distinct non-negative keys: every lookup is one probe (hash and displace).

    ``h = key * multiplier`` wraps in the key dtype, so it is a bijection and the table holds and compares ``h``
    (a caller can fold a constant into it: ``(key + c) * m = key * m + c * m``). Bucket ``b`` = the top bits of
    ``h``, ``slot = ((h >> slot_shift) + disp[b]) & (S - 1)``: the displacement of each bucket is chosen at build
    time so that no two keys share a slot. A lookup is then two gathers and a compare, with no probe sequence and
    no branch: pure tensor ops, the same on CPU and GPU. Keys below 2^31 are held as int32 (cheaper arithmetic).
    ``S`` is a power of two at least twice the number of keys; there are about half as many buckets as keys.
    """

    slot_hash: Tensor
    """``[S]`` the hashed key held in each slot (empty slots hold the hash of a key above every stored one)"""
    slot_rows: Tensor
    """``[S]`` int64: the row (position in the built key array) of each slot's key (-1: empty)"""
    disp: Tensor
    """``[B]`` displacement per bucket, in the key dtype"""
    multiplier: int
    """odd, signed, in the key dtype's range"""
    bucket_shift: int
    bucket_mask: int
    slot_shift: int
    key_limit: int
    """stored keys (and the queries of a caller that passed it) are below this; empty slots hold its hash"""

    @property
    def dtype(self) -> torch.dtype:
        return self.slot_hash.dtype

    @property
    def num_slots(self) -> int:
        return int(self.slot_hash.numel())

    @classmethod
    def build(cls, keys: Tensor, key_limit: int | None = None, seed: int = 0, load: float = 0.5) -> KeyHash:
        """Hash ``keys [E]`` (distinct, >= 0, int64) so that ``lookup_keys(keys[i]) == i``.

        ``key_limit`` (default: the largest key + 1) bounds the keys a caller of :meth:`slots` will ever probe;
        the int32 layout is used when it is at most 2^31 - 1.

        Buckets are placed largest first, all buckets of a size at once: each round draws a random displacement
        for every bucket still waiting and keeps the buckets whose keys all land on free slots claimed by no other
        bucket. A bucket whose keys share a slot under every displacement (possible in small tables) makes the
        build retry with another multiplier and, every other try, twice the slots; after 8 tries it raises.
        """
        keys = torch.as_tensor(keys).reshape(-1).cpu()
        if keys.dtype != torch.int64:
            raise ValueError(f"KeyHash.build needs int64 keys, got {keys.dtype}")
        E = keys.numel()
        if E and int(keys.min()) < 0:
            raise ValueError("KeyHash.build: keys must be non-negative")
        if E > 1 and bool((torch.sort(keys).values.diff() == 0).any()):
            raise ValueError("KeyHash.build: the keys are not distinct")
        top = int(keys.max()) + 1 if E else 0
        top = top if key_limit is None else int(key_limit)
        if E and int(keys.max()) >= top:
            raise ValueError(f"KeyHash.build: keys must be below key_limit={top}")
        bits = 32 if top < 2**31 else 64
        if top >= 2**63 - 1:
            raise ValueError("KeyHash.build: keys must be below 2^63 - 1")
        dtype = torch.int32 if bits == 32 else torch.int64
        k = keys.to(dtype)
        gen = torch.Generator().manual_seed(seed)
        base_slots = max(8, 1 << math.ceil(math.log2(max(E / load, 1))))
        B = max(2, 1 << math.ceil(math.log2(max(E / 2, 1))))
        for attempt in range(8):
            S = base_slots << (attempt // 2)
            log_s, log_b = S.bit_length() - 1, B.bit_length() - 1
            mult = _signed(_MULTIPLIERS[bits][attempt], bits)
            bucket_shift, slot_shift = bits - log_b, max(0, bits - log_b - log_s)
            h = k * mult  # [E] wraps: a bijection of the key
            bucket = ((h >> bucket_shift) & (B - 1)).long()  # [E]
            low = h >> slot_shift if slot_shift else h  # [E]
            disp = _place(low, bucket, B, S, gen)
            if disp is None:
                continue
            slot = ((low + disp[bucket]) & (S - 1)).long()  # [E]
            empty = torch.tensor([top], dtype=dtype) * mult  # the hash of key_limit, which no query below it has
            slot_hash = empty.expand(S).clone()
            slot_rows = torch.full((S,), -1, dtype=torch.int64)
            slot_hash[slot] = h
            slot_rows[slot] = torch.arange(E)
            return cls(slot_hash, slot_rows, disp, mult, bucket_shift, B - 1, slot_shift, top)
        raise RuntimeError(f"KeyHash.build: no collision-free placement of {E} keys found in 8 tries")

    def to(self, device: torch.device | str) -> KeyHash:
        return KeyHash(self.slot_hash.to(device), self.slot_rows.to(device), self.disp.to(device), self.multiplier,
                       self.bucket_shift, self.bucket_mask, self.slot_shift, self.key_limit)

    def hash(self, keys: Tensor) -> Tensor:
        """``keys * multiplier``, wrapping in :attr:`dtype`: ``[...]`` -> ``[...]``."""
        return keys * self.multiplier

    def slots(self, h: Tensor) -> Tensor:
        """The one slot each hashed key ``h [N]`` can be in: ``[N]``; it holds ``h`` iff the key is stored."""
        low = h >> self.slot_shift if self.slot_shift else h
        disp = self.disp.index_select(0, (h >> self.bucket_shift) & self.bucket_mask)  # [N]
        return (low + disp) & (self.num_slots - 1)  # [N]

    def lookup_keys(self, keys: Tensor) -> Tensor:
        """Row of each key ``[...]`` (any int dtype; -1 where the key is not stored, negative keys included)."""
        shape = keys.shape
        keys = keys.reshape(-1)
        keys = torch.where((keys >= 0) & (keys < self.key_limit), keys, self.key_limit).to(self.dtype)
        h = self.hash(keys)
        slot = self.slots(h)
        hit = self.slot_hash.index_select(0, slot) == h
        return torch.where(hit, self.slot_rows.index_select(0, slot), -1).reshape(shape)


def _place(low: Tensor, bucket: Tensor, B: int, S: int, gen: torch.Generator, max_rounds: int = 2000):
    """Displacements ``[B]`` that send every key to its own slot ``(low + disp[bucket]) & (S - 1)``, or None.

    Vectorized over buckets: largest buckets first; in each round every waiting bucket of the current size draws a
    displacement and keeps it when all its keys land on free slots that no other waiting key claims.
    """
    dtype = low.dtype
    disp = torch.zeros(B, dtype=dtype)
    occupied = torch.zeros(S, dtype=torch.bool)
    size = torch.bincount(bucket, minlength=B)  # [B]
    # a bucket with two keys equal mod S can never be placed
    rel = low & (S - 1)
    pair = bucket * S + rel.long() if B * S < 2**62 else None
    if pair is not None and bool((torch.sort(pair).values.diff() == 0).any()):
        return None
    rounds = 0
    for k in torch.unique(size[size > 0]).flip(0).tolist():
        waiting = torch.nonzero(size == k).squeeze(1)  # [W] buckets of size k
        while waiting.numel():
            rounds += 1
            if rounds > max_rounds:
                return None
            in_wait = torch.zeros(B, dtype=torch.bool)
            in_wait[waiting] = True
            member = torch.nonzero(in_wait[bucket]).squeeze(1)  # keys of waiting buckets
            cand = torch.randint(0, S, (B,), generator=gen).to(dtype)  # a displacement per bucket
            slot = ((low[member] + cand[bucket[member]]) & (S - 1)).long()  # [M]
            _, inverse, counts = torch.unique(slot, return_inverse=True, return_counts=True)
            ok = ~occupied[slot] & (counts[inverse] == 1)  # [M]
            bad = torch.zeros(B, dtype=torch.bool)
            bad[bucket[member][~ok]] = True
            keep = ~bad[bucket[member]]  # [M] keys of buckets that fit
            occupied[slot[keep]] = True
            placed = bucket[member][keep]
            disp[placed] = cand[placed]
            waiting = waiting[bad[waiting]]
    return disp
