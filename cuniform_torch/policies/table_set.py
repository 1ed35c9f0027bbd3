"""A table set as one policy: every trajectory uses the table whose start is nearest to the trajectory's start.

A set is a folder written by ``python -m precompute.build --starts SPEC --out DIR``: tables of one system built
from many starts, and ``tables.json`` (format ``cuniform-table-set/1``: per table its ``file`` and ``start``).
:func:`load_table_set` reads it (``load_table(DIR)`` does too) into a :class:`TableSetPolicy`. It opens lazily:
the index and the first table now, every other table on its first use (``lazy=False`` reads and checks all).

Shapes: S tables (members), N states, d state dimensions, k the dimensions that choose a member, A actions, q
action dimensions.

Nearest: distance in cells (each dimension's difference over its cell size; angle dimensions the shorter way
round) over the dimensions a frame change does not move: for an SE(2)-invariant system the dimensions after (x,
y, theta), otherwise all of them. A member whose start lies in the start's own cell wins over nearer-or-equal
ones in other cells (it describes that cell's trajectories).

The member belongs to the trajectory, chosen by its start (t = 0), not by each state along it: a state at t > 0
has moved away from the start, and the member nearest to it is not the table the trajectory was drawn from. So

* a rollout (:func:`~cuniform_torch.sampling.rollout.rollout`, a controller) calls :meth:`TableSetPolicy.for_start`
  once with the start and rolls out with the member it returns;
* :meth:`TableSetPolicy.action_probs` and :meth:`TableSetPolicy.sample` answer each state from the member nearest
  to its trajectory's start: ``start=x0`` (``[d]`` or ``[N, d]``), or, at ``t = 0`` only, the state itself. A
  state at ``t > 0`` without ``start`` is a ValueError (which member is meant is not knowable from it).

A start outside the chosen table's start cell warns once per episode (``StartMismatchWarning``, with the miss
rate; :mod:`cuniform_torch.sampling.start_watch`), as a single table does; :attr:`TableSetPolicy.start_misses`
counts every such rollout of the episode. A controller's construction and ``reset()`` begin an episode; so does
:meth:`TableSetPolicy.new_episode`.
"""

from __future__ import annotations

import collections
import json
import math
import os
import threading
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any, overload

import numpy as np
import torch
from torch import Tensor

from cuniform_torch.common.fileio import MAX_JSON_BYTES, file_kind, read_capped_text
from cuniform_torch.policies.table import TablePolicy
from cuniform_torch.policies.table import load_table as load_table_file
from cuniform_torch.sampling.start_watch import StartMisses, watch_of
from cuniform_torch.tables.file import Table, TableError, read_table

__all__ = ["MemberRows", "SET_FORMAT", "SET_INDEX", "TableSetPolicy", "LazyMembers", "load_table_set", "load_table"]

SET_FORMAT = "cuniform-table-set/1"
SET_INDEX = "tables.json"
_CHUNK = 1 << 22  # distances computed at once (rows x members x dims): bounds the memory of a large batch


class LazyMembers(Sequence[TablePolicy]):
    """A set's tables, each read (by ``load(i)``) on its first use and kept; thread-safe (a background proposal
    bank may roll a member out while the control loop asks for another)."""

    def __init__(self, count: int, load: Callable[[int], TablePolicy], loaded: dict[int, TablePolicy] | None = None):
        self._count = count
        self._load = load
        self._members: dict[int, TablePolicy] = dict(loaded or {})
        self._lock = threading.Lock()
        self.reads = 0
        """tables read so far by ``load`` (not counting the ones given already loaded)"""
        self.on_load: Callable[[TablePolicy], None] | None = None
        """called with each member as it is read (the set gives it its episode)"""

    def __len__(self) -> int:
        return self._count

    @overload
    def __getitem__(self, i: int) -> TablePolicy: ...

    @overload
    def __getitem__(self, i: slice) -> list[TablePolicy]: ...

    def __getitem__(self, i: int | slice) -> TablePolicy | list[TablePolicy]:
        if isinstance(i, slice):
            return [self[j] for j in range(*i.indices(self._count))]
        i = int(i)
        if i < 0:
            i += self._count
        if not 0 <= i < self._count:
            raise IndexError(f"member {i} of a set of {self._count}")
        member = self._members.get(i)
        if member is None:
            with self._lock:
                member = self._members.get(i)
                if member is None:
                    member = self._load(i)
                    self.reads += 1
                    if self.on_load is not None:
                        self.on_load(member)
                    self._members[i] = member
        return member

    def __iter__(self) -> Iterator[TablePolicy]:
        return (self[i] for i in range(self._count))

    @property
    def loaded(self) -> list[int]:
        """Indices of the members read so far, ascending."""
        return sorted(self._members)

    def loaded_members(self) -> list[TablePolicy]:
        """The members read so far (reads none)."""
        return [self._members[i] for i in self.loaded]


def _rows(x: Tensor, rows: Tensor | None) -> Tensor:
    return x if rows is None else x.index_select(0, rows)


class MemberRows:
    """Several members of a table set answering one batch of states, each its own rows (``rows[i]``, ``[n_i]``
    int64: the rows of member ``members[i]``): a rollout of robots whose starts chose different members steps the
    dynamics once for all of them, with one lookup per member used. A Policy (``actions``, ``action_probs``) with
    ``draw(x, t, r)`` and ``watch_start``, for :func:`~cuniform_torch.sampling.rollout.rollout`'s plan."""

    def __init__(self, members: Sequence[TablePolicy], rows: Sequence[Tensor]):
        self.members, self.rows = list(members), list(rows)
        first = self.members[0]
        self.system, self.actions, self.horizon = first.system, first.actions, first.horizon
        self.device, self.dtype, self.start_relative = first.device, first.dtype, first.start_relative

    @classmethod
    def reusable(cls, first: TablePolicy) -> MemberRows:
        """One for the rollouts of the members of ``first``'s set, made once (a proposal settles its rollout plan
        on it) and :meth:`assign` ed per rollout."""
        return cls([first], [torch.zeros(0, dtype=torch.int64)])

    def assign(self, members: Sequence[TablePolicy], rows: Sequence[Tensor]) -> MemberRows:
        """The members and their rows of the next rollout (every member of the same set: the traits stay);
        returns ``self``."""
        self.members, self.rows = list(members), list(rows)
        return self

    def _each(self, x: Tensor, answer: Callable[[TablePolicy, Tensor | None], Tensor], width: int) -> Tensor:
        """Each member's answer for its rows (``rows`` None: one member answers every row, no gather)."""
        if len(self.members) == 1:
            return answer(self.members[0], None)
        out = x.new_empty((x.shape[0], width), dtype=self.dtype)
        for member, rows in zip(self.members, self.rows):
            out.index_copy_(0, rows, answer(member, rows))
        return out

    def action_probs(self, x: Tensor, t: int) -> Tensor:
        """``x [N, d]`` -> ``[N, A]``, each row from its member."""
        return self._each(x, lambda m, rows: m.action_probs(_rows(x, rows), t), self.actions.shape[0])

    def draw(self, x: Tensor, t: int, r: Tensor) -> Tensor:
        """``x [N, d]``, uniforms ``r [N]`` -> actions ``[N, q]``, each row drawn by its member."""
        return self._each(x, lambda m, rows: m.draw(_rows(x, rows), t, _rows(r, rows)), self.actions.shape[1])

    def watch_start(self, x0: Tensor, relative: bool) -> Callable[[], None] | None:
        """Each member's start check of its rows' starts (``x0 [N, d]``)."""
        reports = [m.watch_start(_rows(x0, rows), relative) for m, rows in zip(self.members, self.rows)]
        done = [r for r in reports if r is not None]
        if not done:
            return None

        def report() -> None:
            for r in done:
                r()
        return report


class TableSetPolicy:
    """Tables of one system from many starts (module docstring); a Policy / ActionSampler like a table.

    ``members`` are the tables (a list, or :class:`LazyMembers` that reads them on first use; every member must
    be of the first's system, actions and grid), ``starts [S, d]`` their build starts.
    """

    def __init__(self, members: Sequence[TablePolicy], starts: Tensor):
        if len(members) == 0 or starts.shape != (len(members), starts.shape[-1]):
            raise ValueError(f"TableSetPolicy needs one start [d] per table, got {list(starts.shape)} for "
                             f"{len(members)} tables")
        first = members[0]
        if starts.shape[1] != first.grid.dim:
            raise ValueError(f"TableSetPolicy: starts have {starts.shape[1]} dimensions, the tables' system "
                             f"{first.grid.dim}")
        self.members = members
        self.starts = starts.double()  # [S, d]
        self.system, self.grid, self.actions = first.system, first.grid, first.actions
        self.device, self.dtype, self.fallback = first.device, first.dtype, first.fallback
        self.horizon = first.horizon  # the system JSON names the horizon: every member has the first's
        self.start_relative = first.start_relative
        lo = 3 if self.start_relative else 0
        self._dims = list(range(lo, self.grid.dim))  # the dimensions that choose the table
        self._scale = torch.tensor(self.grid.cell_size, dtype=torch.float64)[self._dims]  # [k]
        self._angle = torch.tensor(self.grid.periodic, dtype=torch.bool)[self._dims]  # [k]
        self._start_cells = self.grid.cells(self.starts)[:, self._dims]  # [S, k]
        self._episode = StartMisses()
        """the members' start checks share one episode: the set warns once per episode, not once per member"""
        for member in self._loaded():
            self._join(member)
        if isinstance(members, LazyMembers):
            members.on_load = self._join
        self.current: TablePolicy = first
        """the member the latest :meth:`for_start` chose (to read; lookups choose their own)"""
        self.last_index, self.last_start_distance = 0, 0.0

    # ------------------------------------------------------------------------------------------ members

    def _loaded(self) -> list[TablePolicy]:
        members = self.members
        return members.loaded_members() if isinstance(members, LazyMembers) else list(members)

    def _join(self, member: TablePolicy) -> None:
        """Give a member's start check the set's episode."""
        watch = watch_of(member)
        if watch is not None:
            watch.episode = self._episode

    def member(self, i: int) -> TablePolicy:
        """Member ``i`` (read now if the set is lazy and it was not used yet)."""
        return self.members[i]

    def load_all(self) -> TableSetPolicy:
        """Read every member now (and check each against the first); returns ``self``."""
        for i in range(len(self.members)):
            self.member(i)
        return self

    @property
    def loaded(self) -> list[int]:
        """Indices of the members read so far."""
        members = self.members
        return members.loaded if isinstance(members, LazyMembers) else list(range(len(members)))

    # ------------------------------------------------------------------------------------------ nearest

    def nearest(self, x0: Tensor) -> tuple[Tensor, Tensor]:
        """The member nearest to each start: ``x0 [d]`` or ``[N, d]`` -> indices ``[]`` or ``[N]`` int64 and
        distances in cells, float64 (CPU tensors; reads no member)."""
        if not isinstance(x0, Tensor) or x0.ndim not in (1, 2) or x0.shape[-1] != self.grid.dim:
            got = list(x0.shape) if isinstance(x0, Tensor) else type(x0).__name__
            raise ValueError(f"a table set's start must be [{self.grid.dim}] or [N, {self.grid.dim}], got {got}")
        full = x0.detach().double().cpu().reshape(-1, self.grid.dim)  # [N, d]
        if not bool(torch.isfinite(full).all()):
            raise ValueError("a table set's start contains NaN or infinite values")
        n = full.shape[0]
        if not self._dims:  # nothing beyond the pose: every table serves every start
            index, dist = torch.zeros(n, dtype=torch.int64), torch.zeros(n, dtype=torch.float64)
        else:
            step = max(1, _CHUNK // (len(self.starts) * len(self._dims)))
            parts = [self._nearest_rows(full[i:i + step]) for i in range(0, n, step)]  # chunks of rows, not rows
            index, dist = torch.cat([p[0] for p in parts]), torch.cat([p[1] for p in parts])
        return (index[0], dist[0]) if x0.ndim == 1 else (index, dist)

    def _nearest_rows(self, full: Tensor) -> tuple[Tensor, Tensor]:
        """``full [n, d]`` float64 -> the nearest members ``[n]`` and their distances ``[n]`` (cells)."""
        x = full[:, self._dims]  # [n, k]
        diff = (x[:, None] - self.starts[None][..., self._dims]).abs()  # [n, S, k]
        wrapped = torch.remainder(diff, 2 * math.pi)
        diff = torch.where(self._angle, torch.minimum(wrapped, 2 * math.pi - wrapped), diff)  # angles: the shorter way
        dist = torch.linalg.vector_norm(diff / self._scale, dim=2)  # [n, S] cells
        own = self.grid.cells(full)[:, self._dims]  # [n, k] each start's cell
        same = (self._start_cells[None] == own[:, None]).all(dim=2)  # [n, S]
        # a table built from the start's own cell describes its trajectories: it wins ties with neighbours
        dist = torch.where(same.any(dim=1, keepdim=True) & ~same, torch.full_like(dist, math.inf), dist)
        best = torch.argmin(dist, dim=1)  # [n]
        return best, dist.gather(1, best[:, None])[:, 0]

    def member_index(self, x0: Tensor) -> int:
        """The index of the member nearest to the start ``x0 [d]`` (changes nothing; reads no member)."""
        if x0.ndim != 1:
            raise ValueError(f"member_index takes one start [{self.grid.dim}], got {list(x0.shape)}")
        return int(self.nearest(x0)[0])

    def for_start(self, x0: Tensor) -> TablePolicy:
        """The member nearest to the start ``x0 [d]``, for a rollout from it; sets :attr:`current`,
        :attr:`last_index` and :attr:`last_start_distance` (cells). ``x0 [N, d]`` (a start per trajectory) must
        choose one member (else a ValueError: roll out each member's starts apart, grouped by :meth:`nearest`)."""
        index, dist = self.nearest(x0)
        if x0.ndim == 2:
            if bool((index != index[0]).any()):
                chosen = sorted(set(index.tolist()))
                raise ValueError(f"the {x0.shape[0]} starts of this rollout are nearest to different members of the "
                                 f"table set ({len(chosen)} of them: {chosen[:8]}{' ...' if len(chosen) > 8 else ''}); "
                                 f"a rollout uses one member: roll out each member's starts apart "
                                 f"(policy.nearest(x0) groups them)")
            index, dist = index[0], dist.max()
        i = int(index)
        member = self.member(i)
        self.current, self.last_index, self.last_start_distance = member, i, float(dist)
        return member

    # ------------------------------------------------------------------------------------------ lookups

    def _members_of(self, x: Tensor, t: int, start: Tensor | None, who: str) -> Tensor:
        """The member of each state's trajectory: ``[N]`` int64 (CPU)."""
        if not isinstance(x, Tensor) or x.ndim != 2 or x.shape[1] != self.grid.dim:
            got = list(x.shape) if isinstance(x, Tensor) else type(x).__name__
            raise ValueError(f"TableSetPolicy.{who}: states must be [N, {self.grid.dim}], got {got}")
        if start is None:
            if t != 0:
                raise ValueError(
                    f"TableSetPolicy.{who}(x, t={t}): a set's member is chosen by the trajectory's start, and a state "
                    f"at t > 0 is not one; pass start=x0 (the trajectories' start, [d] or [N, d]), or ask the "
                    f"rollout's member: policy.for_start(x0).{who}(x, t)")
            start = x  # at t = 0 each state is its trajectory's start
        n = x.shape[0]
        if not isinstance(start, Tensor) or start.shape not in ((self.grid.dim,), (n, self.grid.dim)):
            got = list(start.shape) if isinstance(start, Tensor) else type(start).__name__
            raise ValueError(f"TableSetPolicy.{who}: start must be [{self.grid.dim}] or [{n}, {self.grid.dim}] "
                             f"(one per state), got {got}")
        index = self.nearest(start)[0]
        return index.expand(n) if start.ndim == 1 else index

    def _by_member(self, index: Tensor, answer: Callable[[TablePolicy, Tensor | None], Tensor]) -> Tensor:
        """Each member's rows answered by that member (one call per member used, ascending), in the rows' order."""
        used = torch.unique(index)
        if used.numel() == 1:
            return answer(self.member(int(used[0])), None)
        parts, rows = [], []
        for i in used.tolist():  # a loop over the members used, each answering its rows in one batch
            sel = torch.nonzero(index == i).squeeze(1)
            parts.append(answer(self.member(i), sel))
            rows.append(sel)
        order = torch.cat(rows).to(parts[0].device)
        out = parts[0].new_empty((index.shape[0], *parts[0].shape[1:]))
        out[order] = torch.cat(parts)
        return out

    def action_probs(self, x: Tensor, t: int, start: Tensor | None = None) -> Tensor:
        """``x [N, d]`` at step ``t`` -> ``[N, A]``: each row from the member nearest to its trajectory's start
        (``start [d]`` or ``[N, d]``; at ``t = 0`` it may be left out: the states are the starts)."""
        index = self._members_of(x, t, start, "action_probs")
        return self._by_member(index, lambda m, rows: m.action_probs(x if rows is None else x[rows.to(x.device)], t))

    def sample(self, x: Tensor, t: int, generator: torch.Generator | None = None,
               start: Tensor | None = None) -> Tensor:
        """Actions ``[N, q]`` for ``x [N, d]`` at step ``t``, each drawn by the member nearest to its
        trajectory's start (``start`` as in :meth:`action_probs`); the members used draw in ascending order."""
        index = self._members_of(x, t, start, "sample")
        return self._by_member(index, lambda m, rows: m.sample(x if rows is None else x[rows.to(x.device)], t,
                                                                  generator))

    def draw(self, x: Tensor, t: int, r: Tensor, start: Tensor | None = None) -> Tensor:
        """:meth:`sample` with the uniforms ``r [N]`` in ``[0, 1)`` given (each member draws as its ``draw``)."""
        index = self._members_of(x, t, start, "draw")
        return self._by_member(index, lambda m, rows: m.draw(x if rows is None else x[rows.to(x.device)], t,
                                                             r if rows is None else r[rows.to(r.device)]))

    def watch_start(self, x0: Tensor, relative: bool) -> Callable[[], None] | None:
        """The start check of the member nearest to ``x0`` (what a rollout through :meth:`for_start` runs)."""
        return self.member(self.member_index(x0 if x0.ndim == 1 else x0[0])).watch_start(x0, relative)

    # ------------------------------------------------------------------------------------------ episodes, counters

    def new_episode(self) -> None:
        """Begin an episode: the off-start warning is armed again and :attr:`start_misses` restarts (a
        controller's construction and ``reset()`` call this)."""
        self._episode.reset()

    @property
    def start_misses(self) -> StartMisses:
        """This episode's off-start rollouts over every member: ``rollouts``, ``lookups``, ``misses``, ``rate``,
        ``warned``."""
        return self._episode

    def reset_counters(self) -> None:
        for m in self._loaded():
            m.reset_counters()

    @property
    def queries(self) -> int:
        return sum(m.queries for m in self._loaded())

    @property
    def misses(self) -> Tensor:
        return sum((m.misses for m in self._loaded()), torch.zeros((), dtype=torch.int64, device=self.device))

    @property
    def nearest_hits(self) -> Tensor:
        return sum((m.nearest_hits for m in self._loaded()), torch.zeros((), dtype=torch.int64, device=self.device))

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


def _same_kind(table: Table, first: Table) -> bool:
    return (table.system == first.system and np.array_equal(table.actions, first.actions)
            and np.array_equal(table.cell_size, first.cell_size) and np.array_equal(table.periodic, first.periodic)
            and np.array_equal(table.cell_offset, first.cell_offset))


MAX_SET_TABLES = 100_000
"""the most tables a set's index may list (``precompute.build --starts`` builds at most 10,000 without
``--no-limit``)"""


def load_table_set(folder: str | os.PathLike, device: torch.device | str = "cpu", lazy: bool = True,
                   **kwargs: Any) -> TableSetPolicy:
    """The set in ``folder`` (its ``tables.json`` and tables; ``kwargs`` go to every :class:`TablePolicy`).

    Lazy (the default): the index and the first table are read and checked now, every other table on its first
    use (a 500-table set opens in about a second); ``lazy=False`` reads and checks them all now. A missing
    table (checked now), a table whose start is not the index's, or a table whose system, actions or grid differ
    from the first's (checked when it is read): a :class:`TableError` naming the file."""
    folder = Path(folder)
    index_path = folder / SET_INDEX
    try:
        index = json.loads(read_capped_text(index_path, MAX_JSON_BYTES, "the table-set index"))
    except (OSError, ValueError) as exc:
        raise TableError(f"{index_path}: not a readable table-set index ({exc})") from None
    except RecursionError:  # the json module's own limit: arrays or objects nested thousands deep
        raise TableError(f"{index_path}: not a readable table-set index (JSON nested too deep)") from None
    if not isinstance(index, dict) or index.get("format") != SET_FORMAT or not isinstance(index.get("tables"), list) \
            or not index["tables"]:
        raise TableError(f"{index_path}: not a {SET_FORMAT!r} index with a non-empty list of tables")
    if len(index["tables"]) > MAX_SET_TABLES:  # each entry is a stat and a start: bounded before any is made
        raise TableError(f"{index_path}: lists {len(index['tables']):,} tables, more than the {MAX_SET_TABLES:,} a "
                         "table set may hold")
    trust = kwargs.pop("trust_factory", None)
    paths: list[Path] = []
    starts: list[np.ndarray] = []
    for entry in index["tables"]:
        if not isinstance(entry, dict) or not isinstance(entry.get("file"), str) or "/" in entry["file"] \
                or "\\" in entry["file"]:
            raise TableError(f"{index_path}: each table needs a file name in the folder, got {entry!r}")
        path = folder / entry["file"]
        try:
            found = path.is_file()
        except (OSError, ValueError) as exc:  # a name too long, a NUL byte
            raise TableError(f"{index_path}: the table file name {entry['file'][:40]!r}... is not usable ({exc})") from None
        if not found:
            kind = f"{file_kind(os.stat(path).st_mode)}, not a regular file" if path.exists() else "missing"
            raise TableError(f"{path}: listed in {index_path} but {kind}")
        try:
            start = np.asarray(entry.get("start"), dtype=np.float64)
        except (TypeError, ValueError):
            start = np.zeros(0)
        if start.ndim != 1 or not np.isfinite(start).all() or (starts and start.shape != starts[0].shape):
            raise TableError(f"{index_path}: {entry['file']}'s start must be a list of finite numbers, one per state "
                             f"dimension, got {entry.get('start')!r}")
        paths.append(path)
        starts.append(start)
    if len(set(paths)) != len(paths):  # counted once each: paths.count per path took 47 s for 20,000 entries
        twice = sorted(name for name, n in collections.Counter(p.name for p in paths).items() if n > 1)
        raise TableError(f"{index_path}: {', '.join(twice[:5])} listed more than once; each table of a set is listed "
                         "once")
    unique_starts = np.unique(np.stack(starts), axis=0)
    if len(unique_starts) != len(starts):
        raise TableError(f"{index_path}: two tables are listed with the same start; each start of a set is built once "
                         "(nearest-member lookups would pick one of them arbitrarily)")

    def read(i: int, first: Table | None) -> Table:
        table = read_table(paths[i], graph=False, trust_factory=trust)
        own = table.start if table.start is not None else np.zeros(len(table.cell_size))
        if own.shape != starts[i].shape or not np.array_equal(own, starts[i]):
            raise TableError(f"{paths[i]}: built from {own.tolist()}, but {index_path} says {starts[i].tolist()}")
        if first is not None and not _same_kind(table, first):
            raise TableError(f"{paths[i]}: its system, actions or grid differ from {paths[0]}'s; a set holds tables "
                             f"of one system")
        return table

    first_table = read(0, None)
    first = TablePolicy(first_table, device=device, **kwargs)
    named = index.get("system")
    if isinstance(named, str) and named != first.system.name:
        raise TableError(f"{index_path}: names the system {named!r}, but {paths[0]} holds a "
                         f"{first.system.name!r} table")
    members = LazyMembers(len(paths), lambda i: TablePolicy(read(i, first_table), device=device, **kwargs), {0: first})
    policy = TableSetPolicy(members, torch.from_numpy(np.stack(starts)))
    return policy if lazy else policy.load_all()


def load_table(path: str | os.PathLike, device: torch.device | str = "cpu", **kwargs: Any) -> TablePolicy | TableSetPolicy:
    """``cuniform_torch.load_table``: a table file's :class:`TablePolicy`
    (:func:`cuniform_torch.policies.table.load_table`, ``kwargs`` as there), or a table-set folder's
    :class:`TableSetPolicy` (:func:`load_table_set`, which also takes ``lazy``)."""
    if Path(path).is_dir():
        return load_table_set(path, device=device, **kwargs)
    kwargs.pop("lazy", None)  # a single table is read whole either way
    return load_table_file(path, device=device, **kwargs)
