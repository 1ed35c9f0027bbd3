"""Grid: integer cells of a state space, packed int64 keys, and sorted-key and hashed lookups (no dense grid here;
the table policy's bounded dense index is in :mod:`cuniform_torch.policies.table`).

Shapes: N states (any leading batch shape ``...`` works), d state dimensions, C cells.

A state ``x`` lies in the cell ``round(x / delta + offset)`` per dimension, where ``offset`` is in cells
(``|offset| < 0.5``, so ``x = 0`` is in cell 0). An angle dimension has ``delta = 2 pi / K`` and its index is
taken mod K, so it lies in ``[0, K)``. The centre of a cell is ``(cell - offset) * delta`` (angles wrapped to
``[-pi, pi)``).

:func:`check_grid` is the one check of these invariants (cell sizes, offsets, angle cells of ``2 pi / K`` within
:data:`ANGLE_CELL_RTOL`); systems, :func:`~cuniform_torch.systems.check_system`, :class:`Grid` and the table
reader all call it.

Lookups pack a cell into one int64 key by mixed radix over a bounding box (``CellKeys``) and binary-search a
sorted key array (``CellSet``), or probe a static hash table of the keys once (``KeyHash``, in
:mod:`cuniform_torch.grid.key_hash`: a few gathers instead of a binary search, sized about 2-4x the number of keys);
both work the same on CPU and GPU.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from cuniform_torch.common.checks import float_tuple, wrap_angle
from cuniform_torch.grid.key_hash import KeyHash

__all__ = ["Grid", "CellKeys", "CellSet", "KeyHash", "check_grid", "ANGLE_CELL_RTOL", "TIE_TOL"]

_MAX_KEY = 2**62

TIE_TOL = 1e-4
"""a step within this many cells of a half cell is a tie, rounded away from its source (:meth:`Grid.cells_from`):
far above float32 noise on a step (about 1e-7 cells), far below any designed step that is not a tie"""

ANGLE_CELL_RTOL = 1e-3
"""how far an angle cell size ``delta`` may be from ``2 pi / K`` (``K = round(2 pi / delta)``), relative:
``|K delta - 2 pi| <= ANGLE_CELL_RTOL * 2 pi``. Loose enough for a size typed with four digits (``0.1571`` for
``2 pi / 40`` is 1.3e-4 off), which :func:`check_grid` then makes exactly ``2 pi / K``; tight enough to refuse a
size that is not meant as ``2 pi / K`` at all (``0.3``: ``2 pi / 20.94``)."""


def check_grid(cell_size, periodic, offset, who: str) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """The one check of a grid's invariants: ``(cell_size, offset)`` normalized, or ValueError naming ``who``.

    ``periodic [d]`` (bools) sets the number of dimensions; ``cell_size [d]`` must be finite and positive,
    ``offset [d]`` (in cells) finite with ``|offset| < 0.5``, and an angle dimension's size ``2 pi / K`` for an
    integer ``K >= 1`` within :data:`ANGLE_CELL_RTOL`. Returned: float tuples, each angle size exactly
    ``2 pi / K``. Sequences, tuples and numpy arrays are all accepted.
    """
    periodic = tuple(bool(p) for p in periodic)
    d = len(periodic)
    sizes = list(float_tuple(cell_size, d, "cell_size", who))
    offsets = float_tuple(offset, d, "cell_offset", who)
    if any(c <= 0 for c in sizes):
        raise ValueError(f"{who}: cell_size must be positive in every dimension, got {tuple(sizes)}")
    if any(abs(o) >= 0.5 for o in offsets):
        raise ValueError(f"{who}: cell_offset is in cells and must satisfy |offset| < 0.5, got {offsets}")
    for i, angle in enumerate(periodic):
        if angle:
            k = round(2.0 * math.pi / sizes[i])
            if k < 1 or abs(k * sizes[i] - 2.0 * math.pi) > ANGLE_CELL_RTOL * 2.0 * math.pi:
                raise ValueError(f"{who}: the angle cell size must divide 2*pi (it must be 2*pi/K for an integer K); "
                                 f"dimension {i} has {sizes[i]} (2*pi/{2.0 * math.pi / sizes[i]:.4f})")
            sizes[i] = 2.0 * math.pi / k
    return tuple(sizes), offsets


@dataclass(frozen=True)
class Grid:
    """Cell geometry of a state space, checked and normalized by :func:`check_grid` (an angle cell size within
    :data:`ANGLE_CELL_RTOL` of ``2 pi / K`` becomes exactly ``2 pi / K``)."""

    cell_size: tuple[float, ...]
    """delta per dimension ``[d]``"""
    periodic: tuple[bool, ...]
    """angle dimensions ``[d]`` (values in ``[-pi, pi)``)"""
    offset: tuple[float, ...]
    """grid offset per dimension, in cells ``[d]``"""

    def __post_init__(self) -> None:
        sizes, offsets = check_grid(self.cell_size, self.periodic, self.offset, "Grid")
        object.__setattr__(self, "cell_size", sizes)
        object.__setattr__(self, "periodic", tuple(bool(p) for p in self.periodic))
        object.__setattr__(self, "offset", offsets)

    @classmethod
    def of(cls, system) -> Grid:
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
        return self._wrap_cells(torch.round(scaled).to(torch.int64))

    def cells_from(self, source: Tensor, x: Tensor) -> Tensor:
        """Cells of states ``x [n, ..., d]`` stepped from the cells ``source [n, d]`` int64: the source cell plus
        the displacement from its centre, in cells, rounded half away from zero (:data:`TIE_TOL`).

        The same cells as :meth:`cells` except on ties. A step of exactly half a cell (the +-pi/8 heading steps
        of the default Dubins preset) is then decided by its direction, not by floating-point noise: a
        mirror-symmetric system keeps mirror-symmetric level sets, and float32 and float64 give the same cells.
        The level-set builder assigns cells this way (as the authors' release effectively does).
        """
        if source.ndim != 2 or source.shape[1] != self.dim or x.shape[0] != source.shape[0] or x.shape[-1] != self.dim:
            raise ValueError(f"Grid.cells_from: source must be [n, {self.dim}] and x [n, ..., {self.dim}], got "
                             f"{list(source.shape)} and {list(x.shape)}")
        shape = (source.shape[0],) + (1,) * (x.ndim - 2) + (self.dim,)
        centre = self.centers(source, x.dtype).view(shape)
        steps = self.wrap(x - centre) / self._vec(self.cell_size, x)  # [n, ..., d] in cells
        rounded = torch.sign(steps) * torch.floor(steps.abs() + (0.5 + TIE_TOL))
        return self._wrap_cells(source.view(shape) + rounded.to(torch.int64))

    def _wrap_cells(self, idx: Tensor) -> Tensor:
        """Angle indices mod K; other dimensions as they are."""
        k = self.num_angle_cells
        if any(k):
            mod = torch.tensor([kk if kk else 1 for kk in k], dtype=torch.int64, device=idx.device)
            per = torch.tensor(self.periodic, dtype=torch.bool, device=idx.device)
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
        return torch.where(per, wrap_angle(x), x)


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
    def covering(cls, cells: Tensor) -> CellKeys:
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

    def to(self, device: torch.device | str) -> CellKeys:
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
    def build(cls, cells: Tensor, keys: CellKeys | None = None) -> CellSet:
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

    def to(self, device: torch.device | str) -> CellSet:
        return CellSet(self.keys.to(device), self.sorted_keys.to(device), self.rows.to(device))

    def lookup_keys(self, packed: Tensor) -> Tensor:
        """Row of each packed key ``[...]`` (-1 where the key is not in the set)."""
        pos = torch.searchsorted(self.sorted_keys, packed.contiguous()).clamp_(max=max(len(self) - 1, 0))
        hit = self.sorted_keys[pos] == packed  # stored keys are >= 0, so a -1 (outside the box) never hits
        return torch.where(hit, self.rows[pos], -1)

    def lookup(self, cells: Tensor) -> Tensor:
        """Row of each cell ``[..., d]`` -> ``[...]`` int64 (-1 where the cell is not in the set)."""
        return self.lookup_keys(self.keys.pack(cells))
