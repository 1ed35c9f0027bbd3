"""Grid: integer cells of a state space, packed int64 keys, and sorted-key lookup. No dense grid anywhere.

Shapes: N states (any leading batch shape ``...`` works), d state dimensions, C cells.

A state ``x`` lies in the cell ``round(x / delta + offset)`` per dimension, where ``offset`` is in cells
(``|offset| < 0.5``, so ``x = 0`` is in cell 0). An angle dimension has ``delta = 2 pi / K`` and its index is
taken mod K, so it lies in ``[0, K)``. The centre of a cell is ``(cell - offset) * delta`` (angles wrapped to
``[-pi, pi)``).

Lookups pack a cell into one int64 key by mixed radix over a bounding box (``CellKeys``) and binary-search a
sorted key array (``CellSet``); this works the same on CPU and GPU.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = ["Grid", "CellKeys", "CellSet"]

_MAX_KEY = 2**62


@dataclass(frozen=True)
class Grid:
    """Cell geometry of a state space."""

    cell_size: tuple[float, ...]
    """delta per dimension ``[d]``"""
    periodic: tuple[bool, ...]
    """angle dimensions ``[d]`` (values in ``[-pi, pi)``)"""
    offset: tuple[float, ...]
    """grid offset per dimension, in cells ``[d]``"""

    def __post_init__(self) -> None:
        d = len(self.cell_size)
        if len(self.periodic) != d or len(self.offset) != d:
            raise ValueError(
                f"Grid: cell_size, periodic and offset need the same length, got {d}, {len(self.periodic)}, {len(self.offset)}"
            )
        if any(not (c > 0) for c in self.cell_size):
            raise ValueError(f"Grid: cell_size must be positive, got {self.cell_size}")
        if any(not (abs(o) < 0.5) for o in self.offset):
            raise ValueError(f"Grid: offset is in cells and must satisfy |offset| < 0.5, got {self.offset}")

    @classmethod
    def of(cls, system) -> "Grid":
        """The grid of a :class:`~cuniform_torch.systems.System`."""
        return cls(tuple(system.cell_size), tuple(system.periodic), tuple(system.cell_offset))

    @property
    def dim(self) -> int:
        return len(self.cell_size)

    @property
    def num_angle_cells(self) -> tuple[int, ...]:
        """K per dimension (0 for a non-periodic dimension)."""
        return tuple(round(2.0 * math.pi / c) if p else 0 for c, p in zip(self.cell_size, self.periodic))

    def _vec(self, values, like: Tensor) -> Tensor:
        return torch.tensor(values, dtype=like.dtype, device=like.device)

    def cells(self, x: Tensor) -> Tensor:
        """Cell index of each state: ``x [..., d]`` float -> ``[..., d]`` int64."""
        if x.shape[-1] != self.dim:
            raise ValueError(f"Grid.cells: states must have {self.dim} dimensions in the last axis, got shape {list(x.shape)}")
        if not x.is_floating_point():
            raise ValueError(f"Grid.cells: states must be a floating-point tensor, got {x.dtype}")
        scaled = x / self._vec(self.cell_size, x) + self._vec(self.offset, x)
        idx = torch.round(scaled).to(torch.int64)
        k = self.num_angle_cells
        if any(k):
            mod = torch.tensor([kk if kk else 1 for kk in k], dtype=torch.int64, device=x.device)
            per = torch.tensor(self.periodic, dtype=torch.bool, device=x.device)
            idx = torch.where(per, torch.remainder(idx, mod), idx)
        return idx

    def centers(self, cells: Tensor, dtype: torch.dtype = torch.float64) -> Tensor:
        """Centre state of each cell: ``[..., d]`` int64 -> ``[..., d]`` float (angles in ``[-pi, pi)``)."""
        ref = torch.empty(0, dtype=dtype, device=cells.device)
        x = (cells.to(dtype) - self._vec(self.offset, ref)) * self._vec(self.cell_size, ref)
        return self.wrap(x)

    def wrap(self, x: Tensor) -> Tensor:
        """Wrap the angle dimensions of ``x [..., d]`` to ``[-pi, pi)``; other dimensions pass through."""
        if not any(self.periodic):
            return x
        per = torch.tensor(self.periodic, dtype=torch.bool, device=x.device)
        return torch.where(per, torch.remainder(x + math.pi, 2.0 * math.pi) - math.pi, x)


@dataclass(frozen=True)
class CellKeys:
    """Mixed-radix packing of integer cells inside a bounding box into int64 keys.

    ``key = sum_i (cell_i - lo_i) * stride_i``; a cell outside the box packs to -1.
    """

    lo: Tensor
    """smallest index per dimension ``[d]`` int64"""
    span: Tensor
    """box size per dimension ``[d]`` int64"""

    @classmethod
    def covering(cls, cells: Tensor) -> "CellKeys":
        """The tightest box around ``cells [C, d]``."""
        if cells.ndim != 2 or cells.shape[0] == 0:
            raise ValueError(f"CellKeys.covering needs a non-empty [C, d] cell array, got shape {list(cells.shape)}")
        lo = cells.min(dim=0).values
        span = cells.max(dim=0).values - lo + 1
        total = 1
        for s in span.tolist():
            total *= int(s)
        if total >= _MAX_KEY:
            raise ValueError(f"CellKeys: the cells' bounding box {span.tolist()} has too many cells to pack in int64")
        return cls(lo, span)

    @property
    def strides(self) -> Tensor:
        # last dimension varies fastest
        s = torch.ones_like(self.span)
        if self.span.numel() > 1:
            s[:-1] = torch.flip(torch.cumprod(torch.flip(self.span[1:], (0,)), 0), (0,))
        return s

    def to(self, device: torch.device | str) -> "CellKeys":
        return CellKeys(self.lo.to(device), self.span.to(device))

    def pack(self, cells: Tensor) -> Tensor:
        """``[..., d]`` int64 -> ``[...]`` int64 keys (-1 outside the box)."""
        rel = cells - self.lo
        inside = ((rel >= 0) & (rel < self.span)).all(dim=-1)
        keys = (rel * self.strides).sum(dim=-1)
        return torch.where(inside, keys, torch.full_like(keys, -1))

    def unpack(self, keys: Tensor) -> Tensor:
        """``[...]`` int64 keys (all inside the box) -> ``[..., d]`` int64 cells."""
        strides = self.strides
        return (keys.unsqueeze(-1) // strides) % self.span + self.lo


@dataclass(frozen=True)
class CellSet:
    """A set of cells with ``lookup`` from cells to their row in the original array (sorted-key search)."""

    keys: CellKeys
    sorted_keys: Tensor
    """``[C]`` int64, ascending"""
    rows: Tensor
    """``[C]`` int64: original row of each sorted key"""

    @classmethod
    def build(cls, cells: Tensor, keys: CellKeys | None = None) -> "CellSet":
        """Index ``cells [C, d]`` (distinct); ``keys`` defaults to the box around them."""
        keys = keys or CellKeys.covering(cells)
        packed = keys.pack(cells)
        if bool((packed < 0).any()):
            raise ValueError("CellSet.build: some cells lie outside the given key box")
        sorted_keys, rows = torch.sort(packed)
        if sorted_keys.numel() > 1 and bool((sorted_keys[1:] == sorted_keys[:-1]).any()):
            raise ValueError("CellSet.build: the cells are not distinct")
        return cls(keys, sorted_keys, rows)

    def __len__(self) -> int:
        return int(self.sorted_keys.numel())

    def to(self, device: torch.device | str) -> "CellSet":
        return CellSet(self.keys.to(device), self.sorted_keys.to(device), self.rows.to(device))

    def lookup_keys(self, packed: Tensor) -> Tensor:
        """Row of each packed key ``[...]`` (-1 where the key is not in the set)."""
        pos = torch.searchsorted(self.sorted_keys, packed.contiguous()).clamp_(max=max(len(self) - 1, 0))
        hit = self.sorted_keys[pos] == packed  # stored keys are >= 0, so a -1 (outside the box) never hits
        return torch.where(hit, self.rows[pos], -1)

    def lookup(self, cells: Tensor) -> Tensor:
        """Row of each cell ``[..., d]`` -> ``[...]`` int64 (-1 where the cell is not in the set)."""
        return self.lookup_keys(self.keys.pack(cells))
