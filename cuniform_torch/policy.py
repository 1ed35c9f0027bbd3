"""Table policy: p(u | cell, t) looked up from a C-Uniform table by packed keys, on any device.

Shapes: N states, d state dimensions, A actions, q action dimensions, C table cells, H halo cells.

When the policy is made, every (level, cell) of the table is packed into one int64 key, together with a
*halo*: every cell within one cell (the 3^d - 1 neighbours, angles wrapped) of a level set that is not itself
in that level set, mapped to its nearest cell of the level set (smallest grid distance between cell indices;
ties go to the lower table row). The keys are sorted once, so a lookup is pure tensor ops
(``torch.searchsorted``), the same on CPU and GPU.

Fallback for a state whose cell is not in L_t (``fallback=``):

* ``"nearest"`` (default): the action row of the nearest cell of L_t when the state's cell is within one cell
  of L_t (counted in ``nearest_hits``), else uniform over the actions (counted in ``misses``);
* ``"uniform"``: uniform over the actions (counted in ``misses``).

Tables are built from the origin. For an SE(2)-invariant system (``system.se2_invariant``), states given to
``action_probs`` are in the frame of the start pose; :func:`~cuniform_torch.rollout.rollout` does that change
of frame, so one table serves every start pose (``start_relative = True``).
"""

from __future__ import annotations

import itertools
import os

import numpy as np
import torch
from torch import Tensor

from .grid import CellKeys, CellSet, Grid
from .options import Option, option_label
from .rollout import check_states
from .systems import System
from .table import Table, read_table

__all__ = ["Fallback", "TablePolicy", "UniformPolicy", "load_table"]


@option_label('fallback')
class Fallback(Option):
    """What a :class:`TablePolicy` does for a state outside the level set."""

    NEAREST = "nearest"
    UNIFORM = "uniform"



def _halo(keyed: Tensor, grid: Grid) -> tuple[Tensor, Tensor]:
    """Neighbour cells of each level not in it, with the row of their nearest cell: ``([H, 1+d], [H])``."""
    d = grid.dim
    offsets = torch.tensor([o for o in itertools.product((-1, 0, 1), repeat=d) if any(o)], dtype=torch.int64)  # [O, d]
    dist2 = (offsets**2).sum(dim=1)  # [O] squared grid distance
    C, O = keyed.shape[0], offsets.shape[0]
    nb = keyed[:, None, 1:] + offsets[None]  # [C, O, d]
    k = grid.num_angle_cells
    for dim, kk in enumerate(k):
        if kk:
            nb[..., dim] = torch.remainder(nb[..., dim], kk)
    nb = torch.cat((keyed[:, None, :1].expand(C, O, 1), nb), dim=2).reshape(-1, 1 + d)  # [C*O, 1+d]
    src = torch.arange(C).repeat_interleave(O)  # [C*O]
    dist = dist2.repeat(C)
    keys = CellKeys.covering(torch.cat((keyed, nb)))
    own = CellSet.build(keyed, keys)
    outside = own.lookup(nb) < 0
    nb, src, dist = nb[outside], src[outside], dist[outside]
    packed = keys.pack(nb)
    # order by (key, distance, source row); keep the first entry of each key
    order = torch.sort(src, stable=True).indices
    order = order[torch.sort(dist[order], stable=True).indices]
    order = order[torch.sort(packed[order], stable=True).indices]
    packed, src, nb = packed[order], src[order], nb[order]
    first = torch.ones_like(packed, dtype=torch.bool)
    first[1:] = packed[1:] != packed[:-1]
    return nb[first], src[first]


class TablePolicy:
    """The Policy interface over a table: ``actions [A, q]`` and ``action_probs(x [N, d], t) -> [N, A]``.

    Also an :class:`~cuniform_torch.rollout.ActionSampler`: ``sample(x, t, generator)`` draws the actions by
    inverse-CDF sampling (what :func:`~cuniform_torch.rollout.rollout` uses). ``compile=True`` wraps that
    per-step kernel in ``torch.compile`` (a one-off compilation of tens of seconds, then faster steps).
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
        self._build_lookup(entries)
        # one row per entry plus a last uniform row, which entry -1 (not found) selects by negative indexing
        uniform = torch.full((1, self.num_actions), 1.0 / self.num_actions, device=self.device, dtype=dtype)
        self._entry_probs = torch.cat((self.probs[self.entry_row], uniform))  # [C + H + 1, A]
        cdf = torch.cumsum(self._entry_probs.double(), dim=1)
        cdf[:, -1] = 1.0
        self._cdf = cdf.to(dtype)  # [C + H + 1, A]
        self._sample = torch.compile(self._sample_kernel, dynamic=False) if compile else self._sample_kernel
        self.reset_counters()

    def _build_lookup(self, entries: Tensor) -> None:
        """Settle the lookup kernel's constants once (see :meth:`_entries`).

        Keys pack (level, cell) over a box that spans every angle index and, on the other dimensions, one cell
        more than the entries on each side. Scaled states are clamped into that box before rounding, so a
        state far outside lands on a border cell that holds no entry: a miss, never a wrong cell.
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
        index = CellSet.build(entries, keys)
        big = torch.tensor([torch.iinfo(torch.int64).max])
        self._sorted_keys = torch.cat((index.sorted_keys, big)).to(self.device)  # [E+1], sentinel last
        self._sorted_entry = torch.cat((index.rows, torch.tensor([-1]))).to(self.device)  # [E+1]
        self._strides = keys.strides[1:].to(self.device)  # [d]
        self._level_base = ((torch.arange(self.horizon + 1) - lo[0]) * keys.strides[0]).to(self.device)  # [T+1]
        f64 = dict(dtype=torch.float64)
        inv = 1.0 / torch.tensor(grid.cell_size, **f64)
        shift = torch.tensor(grid.offset, **f64) - lo[1:].to(torch.float64)  # scaled coordinate relative to lo
        periodic = torch.tensor([bool(kk) for kk in k])
        inf = torch.tensor(float("inf"), **f64)
        cast = dict(dtype=self.dtype, device=self.device)
        self._scale, self._shift = inv.to(**cast), shift.to(**cast)  # [d]
        self._clamp_lo = torch.where(periodic, -inf, torch.zeros((), **f64)).to(**cast)  # [d]
        self._clamp_hi = torch.where(periodic, inf, (span[1:] - 1).to(torch.float64)).to(**cast)  # [d]
        self._angle_k = [(dim, kk) for dim, kk in enumerate(k) if kk]

    @property
    def num_actions(self) -> int:
        return int(self.actions.shape[0])

    def reset_counters(self) -> None:
        """Zero ``queries`` (a host int), ``nearest_hits`` and ``misses`` (device tensors: counting never syncs)."""
        zero = lambda: torch.zeros((), dtype=torch.int64, device=self.device)  # noqa: E731
        self.queries, self.nearest_hits, self.misses = 0, zero(), zero()

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
        """Pure tensor kernel: states ``[N, d]`` and the level's key base (0-d) -> entry ids ``[N]`` (-1: none)."""
        # cell = round(x / delta + offset) - lo, clamped into the key box; angles mod K; packed with the level
        scaled = torch.addcmul(self._shift, x, self._scale).clamp(self._clamp_lo, self._clamp_hi)  # [N, d]
        cells = torch.round(scaled).long()  # [N, d]
        for dim, k in self._angle_k:  # wrap angle indices to [0, K) (other dimensions are clamped in range)
            cells[:, dim] = torch.remainder(cells[:, dim], k)
        packed = cells @ self._strides + base  # [N]
        pos = torch.searchsorted(self._sorted_keys, packed)  # [N]; the sentinel keeps pos in range
        return torch.where(self._sorted_keys[pos] == packed, self._sorted_entry[pos], -1)  # [N] entry, -1: none

    def _sample_kernel(self, x: Tensor, base: Tensor, r: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Pure tensor kernel: ``x [N, d]``, level key base, uniforms ``r [N, 1]`` -> actions ``[N, q]`` and counts."""
        entry = self._entry_kernel(x, base)  # [N]
        idx = (self._cdf[entry] < r).sum(dim=1)  # [N]; entry -1 -> uniform row; r < 1 = cdf[:, -1]
        return self.actions[idx], (entry < 0).sum(), (entry >= self.num_cells).sum()

    def rows(self, x: Tensor, t: int) -> Tensor:
        """Table row of each state's cell in level ``t``: ``x [N, d]`` -> ``[N]`` int64 (-1: not in L_t)."""
        entry = self._entries(x, t)
        return torch.where((entry >= 0) & (entry < self.num_cells), entry, torch.full_like(entry, -1))

    def action_probs(self, x: Tensor, t: int) -> Tensor:
        """p(u | cell of x, t): ``x [N, d]`` -> ``[N, A]``, with the fallback for states outside L_t."""
        entry = self._count(self._entries(x, t))  # [N]
        return self._entry_probs[entry]  # [N, A]; entry -1 -> the uniform row

    def _count(self, entry: Tensor) -> Tensor:
        self.queries += entry.numel()  # a host int
        self.misses += (entry < 0).sum()
        self.nearest_hits += (entry >= self.num_cells).sum()
        return entry

    def sample(self, x: Tensor, t: int, generator: torch.Generator | None = None) -> Tensor:
        """Draw one action per state by inverse-CDF sampling of its row: ``x [N, d]`` -> ``[N, q]``."""
        self._check(x, t)
        r = torch.rand((x.shape[0], 1), generator=generator, device=self.device, dtype=self.dtype)  # [N, 1]
        u, misses, nearest = self._sample(x, self._level_base[t], r)
        self.queries += x.shape[0]
        self.misses += misses
        self.nearest_hits += nearest
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
) -> TablePolicy:
    """Read and validate a table file, and return its :class:`TablePolicy` on ``device``."""
    return TablePolicy(read_table(path), device=device, dtype=dtype, fallback=fallback, compile=compile)


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
