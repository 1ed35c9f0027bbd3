"""The fallback counters every C-Uniform policy keeps (a table, an MLP, a map policy): :class:`FallbackCounts`,
and :class:`CountsFallbacks`, the mixin that gives a policy their read-outs.

A lookup of a state outside the policy's support falls back: to the nearest cell (a *nearest hit*) or to the
uniform row (a *miss*). Counting never syncs the device: ``queries`` is a host int, the two counts are 0-d device
tensors, added to as one packed count ``hits + 2^32 misses`` (one add per batch) and split before its low word
could overflow; a compiled CPU loop adds host ints. Reading a rate syncs.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["FallbackCounts", "CountsFallbacks", "LOW_WORD"]

LOW_WORD = 0xFFFFFFFF
"""a packed fallback count: nearest hits in the low 32 bits, misses above"""

_FOLD_AT = 2**31
"""queries after which the packed count is split (its low word holds at most one hit per query)"""


class FallbackCounts:
    """``queries`` (host int), ``nearest_hits`` and ``misses`` (0-d int64 tensors on ``device``)."""

    _hits: Tensor
    _misses: Tensor
    _packed: Tensor

    def __init__(self, device: torch.device | str = "cpu"):
        self.reset(device)

    def reset(self, device: torch.device | str | None = None) -> None:
        """Zero every count (on ``device``, default the current one)."""
        device = torch.device(device) if device is not None else self._hits.device
        zero = lambda: torch.zeros((), dtype=torch.int64, device=device)  # noqa: E731
        self.queries, self._packed_queries, self._host = 0, 0, 0
        self._hits, self._misses, self._packed = zero(), zero(), zero()

    def add(self, n: int, code: Tensor | int) -> None:
        """``n`` lookups with packed fallback count ``code`` (``hits + 2^32 misses``: a 0-d device tensor, or a host
        int from a compiled loop)."""
        if self._packed_queries + n >= _FOLD_AT:
            self._fold()
        self.queries += n
        self._packed_queries += n
        if isinstance(code, int):
            self._host += code
        else:
            if code.device != self._packed.device:  # the policy moved: the counts follow it
                self.to(code.device)
            self._packed += code

    def add_split(self, n: int, near: Tensor | int, miss: Tensor | int) -> None:
        """``n`` lookups with ``near`` nearest hits and ``miss`` misses, counted apart."""
        self.queries += n
        self._hits += near
        self._misses += miss

    def _fold(self) -> None:
        self._hits += (self._packed & LOW_WORD) + (self._host & LOW_WORD)
        self._misses += (self._packed >> 32) + (self._host >> 32)
        self._packed.zero_()
        self._host = self._packed_queries = 0

    def to(self, device: torch.device | str) -> FallbackCounts:
        """The counts moved to ``device`` (kept)."""
        self._fold()
        self._hits, self._misses = self._hits.to(device), self._misses.to(device)
        self._packed = self._packed.to(device)
        return self

    @property
    def nearest_hits(self) -> Tensor:
        return self._hits + (self._packed & LOW_WORD) + (self._host & LOW_WORD)

    @property
    def misses(self) -> Tensor:
        return self._misses + (self._packed >> 32) + (self._host >> 32)


class CountsFallbacks:
    """A policy's read-outs of its :class:`FallbackCounts` (``self.counts``)."""

    counts: FallbackCounts

    def reset_counters(self) -> None:
        """Zero ``queries`` (a host int), ``nearest_hits`` and ``misses`` (device tensors: counting never syncs)."""
        self.counts.reset()

    @property
    def queries(self) -> int:
        """Lookups so far (a host int)."""
        return self.counts.queries

    @property
    def nearest_hits(self) -> Tensor:
        """Lookups answered by the nearest cell of the support (a 0-d device tensor)."""
        return self.counts.nearest_hits

    @property
    def misses(self) -> Tensor:
        """Lookups given the uniform row (outside the support, NaN or infinite; a 0-d device tensor)."""
        return self.counts.misses

    @property
    def miss_rate(self) -> float:
        """Share of lookups so far given the uniform row (syncs the device)."""
        q = self.counts.queries
        return int(self.counts.misses) / q if q else 0.0

    @property
    def nearest_rate(self) -> float:
        """Share of lookups so far answered by the nearest cell (syncs the device)."""
        q = self.counts.queries
        return int(self.counts.nearest_hits) / q if q else 0.0
