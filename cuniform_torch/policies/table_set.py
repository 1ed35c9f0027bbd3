"""A table set as one policy: every rollout uses the table whose start is nearest to the rollout's start.

A set is a folder written by ``python -m precompute.build --starts SPEC --out DIR``: tables of one system built
from many starts, and ``tables.json`` (format ``cuniform-table-set/1``: per table its ``file`` and ``start``).
:func:`load_table_set` reads it (``load_table(DIR)`` does too) into a :class:`TableSetPolicy`.

Nearest: distance in cells (each dimension's difference over its cell size; angle dimensions the shorter way
round) over the dimensions a frame change does not move: for an SE(2)-invariant system the dimensions after (x,
y, theta), otherwise all of them. :attr:`TableSetPolicy.last_start_distance` says how far the chosen table's start
was; a start outside the chosen table's start cell warns once per table (``StartMismatchWarning``, with the miss
rate), as a single table does.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from cuniform_torch.policies.table import TablePolicy
from cuniform_torch.policies.table import load_table as load_table_file
from cuniform_torch.tables.file import TableError, read_table

__all__ = ["SET_FORMAT", "SET_INDEX", "TableSetPolicy", "load_table_set", "load_table"]

SET_FORMAT = "cuniform-table-set/1"
SET_INDEX = "tables.json"


class TableSetPolicy:
    """Tables of one system from many starts (module docstring); a Policy / ActionSampler like a table."""

    def __init__(self, members: list[TablePolicy], starts: Tensor):
        if not members or starts.shape != (len(members), members[0].grid.dim):
            raise ValueError(f"TableSetPolicy needs one start [d] per table, got {list(starts.shape)} for "
                             f"{len(members)} tables")
        self.members = members
        self.starts = starts.double()  # [S, d]
        first = members[0]
        self.system, self.grid, self.actions = first.system, first.grid, first.actions
        self.device, self.dtype, self.fallback = first.device, first.dtype, first.fallback
        self.horizon = min(m.horizon for m in members)
        self.start_relative = first.start_relative
        lo = 3 if self.start_relative else 0
        self._dims = list(range(lo, self.grid.dim))  # the dimensions that choose the table
        self._scale = torch.tensor(self.grid.cell_size, dtype=torch.float64)[self._dims]  # [k]
        self._angle = torch.tensor(self.grid.periodic, dtype=torch.bool)[self._dims]  # [k]
        self._start_cells = self.grid.cells(self.starts)[:, self._dims]  # [S, k]
        self.current = first
        self.last_index, self.last_start_distance = 0, 0.0

    def for_start(self, x0: Tensor) -> TablePolicy:
        """The table nearest to the start ``x0 [d]`` (or the first row of ``[N, d]``); sets :attr:`current`,
        :attr:`last_index` and :attr:`last_start_distance` (cells)."""
        if not self._dims:  # nothing beyond the pose: every table serves every start
            return self.current
        full = (x0 if x0.ndim == 1 else x0[0]).detach().double().cpu()  # [d]
        x = full[self._dims]  # [k]
        diff = (x[None] - self.starts[:, self._dims]).abs()  # [S, k]
        wrapped = torch.remainder(diff, 2 * math.pi)
        diff = torch.where(self._angle, torch.minimum(wrapped, 2 * math.pi - wrapped), diff)  # angles: the shorter way
        dist = torch.linalg.vector_norm(diff / self._scale, dim=1)  # [S] cells
        own = self.grid.cells(full[None])[0, self._dims]  # [k] x0's cell
        same = (self._start_cells == own).all(dim=1)  # [S]
        if bool(same.any()):  # a table built from x0's own cell describes x0's rollouts: it wins ties with neighbours
            dist = torch.where(same, dist, torch.full_like(dist, math.inf))
        i = int(torch.argmin(dist))
        self.current, self.last_index, self.last_start_distance = self.members[i], i, float(dist[i])
        return self.current

    def sample(self, x: Tensor, t: int, generator: torch.Generator | None = None) -> Tensor:
        """The current table's draw (a rollout picks the table by :meth:`for_start` first)."""
        return self.current.sample(x, t, generator)

    def action_probs(self, x: Tensor, t: int) -> Tensor:
        return self.current.action_probs(x, t)

    def watch_start(self, x0: Tensor, relative: bool) -> Callable[[], None] | None:
        return self.current.watch_start(x0, relative)

    def reset_counters(self) -> None:
        for m in self.members:
            m.reset_counters()

    @property
    def queries(self) -> int:
        return sum(m.queries for m in self.members)

    @property
    def misses(self) -> Tensor:
        return sum((m.misses for m in self.members), torch.zeros((), device=self.device))

    @property
    def nearest_hits(self) -> Tensor:
        return sum((m.nearest_hits for m in self.members), torch.zeros((), device=self.device))

    @property
    def miss_rate(self) -> float:
        """Share of lookups over every table so far that fell back to uniform actions (syncs the device)."""
        q = self.queries
        return float(self.misses) / q if q else 0.0

    @property
    def nearest_rate(self) -> float:
        """Share of lookups over every table so far answered by the nearest cell's row (syncs the device)."""
        q = self.queries
        return float(self.nearest_hits) / q if q else 0.0


def load_table_set(folder: str | os.PathLike, device: torch.device | str = "cpu", **kwargs: Any) -> TableSetPolicy:
    """The set in ``folder`` (its ``tables.json`` and tables, each checked like a single table; ``kwargs`` go to
    every :class:`TablePolicy`). A missing table, a table whose start is not the index's, or tables that disagree
    on system, actions or grid: a :class:`TableError` naming the file."""
    folder = Path(folder)
    index_path = folder / SET_INDEX
    try:
        index = json.loads(index_path.read_text())
    except (OSError, ValueError) as exc:
        raise TableError(f"{index_path}: not a readable table-set index ({exc})") from None
    if not isinstance(index, dict) or index.get("format") != SET_FORMAT or not isinstance(index.get("tables"), list) \
            or not index["tables"]:
        raise TableError(f"{index_path}: not a {SET_FORMAT!r} index with a non-empty list of tables")
    trust = kwargs.pop("trust_factory", None)
    members, starts, first = [], [], None
    for entry in index["tables"]:
        if not isinstance(entry, dict) or not isinstance(entry.get("file"), str) or "/" in entry["file"]:
            raise TableError(f"{index_path}: each table needs a file name in the folder, got {entry!r}")
        path = folder / entry["file"]
        if not path.is_file():
            raise TableError(f"{path}: listed in {index_path} but missing")
        table = read_table(path, graph=False, trust_factory=trust)
        start = np.asarray(entry.get("start"), dtype=np.float64)
        own = table.start if table.start is not None else np.zeros(len(table.cell_size))
        if start.shape != own.shape or not np.array_equal(start, own):
            raise TableError(f"{path}: built from {own.tolist()}, but {index_path} says {np.asarray(entry.get('start')).tolist()}")
        if first is None:
            first = table
        elif (table.system != first.system or not np.array_equal(table.actions, first.actions)
              or not np.array_equal(table.cell_size, first.cell_size) or not np.array_equal(table.periodic, first.periodic)
              or not np.array_equal(table.cell_offset, first.cell_offset)):
            raise TableError(f"{path}: its system, actions or grid differ from {folder / index['tables'][0]['file']}'s; "
                             f"a set holds tables of one system")
        members.append(TablePolicy(table, device=device, **kwargs))
        starts.append(own)
    return TableSetPolicy(members, torch.from_numpy(np.stack(starts)))


def load_table(path: str | os.PathLike, device: torch.device | str = "cpu", **kwargs: Any) -> TablePolicy | TableSetPolicy:
    """``cuniform_torch.load_table``: a table file's :class:`TablePolicy`
    (:func:`cuniform_torch.policies.table.load_table`, ``kwargs`` as there), or a table-set folder's
    :class:`TableSetPolicy` (:func:`load_table_set`)."""
    if Path(path).is_dir():
        return load_table_set(path, device=device, **kwargs)
    return load_table_file(path, device=device, **kwargs)
