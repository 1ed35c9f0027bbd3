"""The C-Uniform table file (``.npz``, format ``cuniform-table/1``): a dataclass, a writer and a validating reader.

Shapes: C cells over all levels, d state dimensions, A actions, q action dimensions, T horizon (steps),
E flow arcs, K recorded transitions. See DESIGN.md for the key-by-key contract.
"""

from __future__ import annotations

import json
import math
import os
import zipfile
import zlib
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from .fileio import write_npz
from .grid import Grid, check_grid
from .systems import MAX_ACTIONS, MAX_HORIZON, System, system_from_json, system_to_json

__all__ = ["TABLE_FORMAT", "Table", "TableError", "write_table", "read_table", "system_fields"]

TABLE_FORMAT = "cuniform-table/1"

# key -> (dtype kind check, ndim)
_REQUIRED: dict[str, tuple[np.dtype | None, int]] = {
    "format": (None, 0),
    "system": (None, 0),
    "actions": (np.dtype(np.float32), 2),
    "cell_size": (np.dtype(np.float64), 1),
    "periodic": (np.dtype(np.bool_), 1),
    "cell_offset": (np.dtype(np.float64), 1),
    "level_offsets": (np.dtype(np.int64), 1),
    "cells": (np.dtype(np.int64), 2),
    "action_probs": (np.dtype(np.float32), 2),
    "cell_probs": (np.dtype(np.float64), 1),
    "flow_value": (np.dtype(np.int64), 1),
    "flow_target": (np.dtype(np.int64), 1),
}
_OPTIONAL_ARRAYS: dict[str, tuple[np.dtype, int]] = {
    "arc_offsets": (np.dtype(np.int64), 1),
    "arcs": (np.dtype(np.int64), 2),
    "arc_flow": (np.dtype(np.int64), 1),
    "transition_offsets": (np.dtype(np.int64), 1),
    "transitions": (np.dtype(np.int64), 2),
    "transition_frac": (np.dtype(np.float64), 1),
}
_OPTIONAL_STRINGS = ("method", "build_info")
_KNOWN_KEYS = {"format", *_REQUIRED, *_OPTIONAL_ARRAYS, *_OPTIONAL_STRINGS}

_ROW_SUM_TOL = 1e-4  # float32 rows
_LEVEL_SUM_TOL = 1e-6  # float64 cell probabilities per level


class TableError(ValueError):
    """A table file that is missing, corrupt, truncated, of an unknown format, or inconsistent."""


@dataclass
class Table:
    """A C-Uniform action-probability table, level by level (numpy arrays; see DESIGN.md).

    Optional graph data: ``arcs`` (global rows from -> to) with their max-flow ``arc_flow``, grouped per step by
    ``arc_offsets [T+1]``; ``transitions`` (global row from, action, global row to) with ``transition_frac``, the
    fraction of the (cell, action)'s kept sample points that land in the next cell, grouped by
    ``transition_offsets [T+1]``.
    """

    system: str
    actions: np.ndarray  # [A, q] float32
    cell_size: np.ndarray  # [d] float64
    periodic: np.ndarray  # [d] bool
    cell_offset: np.ndarray  # [d] float64
    level_offsets: np.ndarray  # [T+2] int64
    cells: np.ndarray  # [C, d] int64
    action_probs: np.ndarray  # [C, A] float32
    cell_probs: np.ndarray  # [C] float64
    flow_value: np.ndarray  # [T] int64
    flow_target: np.ndarray  # [T] int64
    method: str | None = None
    build_info: str | None = None
    arc_offsets: np.ndarray | None = None  # [T+1] int64
    arcs: np.ndarray | None = None  # [E, 2] int64
    arc_flow: np.ndarray | None = None  # [E] int64
    transition_offsets: np.ndarray | None = None  # [T+1] int64
    transitions: np.ndarray | None = None  # [K, 3] int64
    transition_frac: np.ndarray | None = None  # [K] float64
    extra: dict[str, np.ndarray] = field(default_factory=dict)
    """more keys to write, beyond the format's (readers ignore keys they do not know: :func:`read_table` never
    reads them)"""

    @property
    def horizon(self) -> int:
        return len(self.level_offsets) - 2

    @property
    def level_sizes(self) -> list[int]:
        return np.diff(self.level_offsets).tolist()

    def level(self, t: int) -> slice:
        """Rows of level ``t``."""
        return slice(int(self.level_offsets[t]), int(self.level_offsets[t + 1]))

    def make_system(self, trust_factory: str | Callable[..., Any] | None = None) -> System:
        """Rebuild the system this table was built for (from the registry or ``trust_factory``; see
        :func:`~cuniform_torch.systems.system_from_json`)."""
        return system_from_json(self.system, trust_factory=trust_factory)[0]

    def to_arrays(self) -> dict[str, np.ndarray]:
        arrays: dict[str, np.ndarray] = {"format": np.array(TABLE_FORMAT)}
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name == "extra" or value is None:
                continue
            arrays[f.name] = np.array(value) if isinstance(value, str) else value
        arrays.update(self.extra)
        return arrays


def system_fields(system: System, horizon: int) -> dict[str, Any]:
    """The table keys that describe the system (``system`` JSON, actions, grid), for table builders."""
    return {
        "system": system_to_json(system, horizon),
        "actions": system.action_set(dtype=torch.float32).numpy(),
        "cell_size": np.asarray(system.cell_size, dtype=np.float64),
        "periodic": np.asarray(system.periodic, dtype=bool),
        "cell_offset": np.asarray(system.cell_offset, dtype=np.float64),
    }


def write_table(path: str | os.PathLike, table: Table) -> None:
    """Validate ``table`` and write it atomically (a fixed-timestamp zip: equal tables give equal bytes)."""
    validate_table(table, source="table to write")
    write_npz(path, table.to_arrays())


def read_table(path: str | os.PathLike, *, check_system: bool = True, graph: bool = True,
               trust_factory: str | Callable[..., Any] | None = None) -> Table:
    """Read and validate a table file; every problem raises :class:`TableError` naming the file and the key.

    Only the keys of the format are read (others are never decompressed), each member's size must match its
    ``.npy`` header and the shapes the table's offsets imply, and the whole table may expand to at most
    :data:`MAX_EXPANSION` times the file's size, so a small hostile file cannot take much memory. The system is
    rebuilt from the registry or from ``trust_factory`` (see :func:`~cuniform_torch.systems.system_from_json`):
    nothing the file names is imported or called.

    ``graph=False`` leaves the optional flow graph (``arcs``, ``transitions`` and their values: the audit data a
    max-flow build stores) in the file, unread and unchecked; the table's graph fields are then None. A policy
    needs none of it, and for a large table it is most of the file: 3.5 GB of the ks table's arrays.
    """
    path = Path(path)
    if not path.is_file():
        raise TableError(f"{path}: no table file there")
    try:
        with zipfile.ZipFile(path) as zf:
            arrays = _read_members(zf, path, graph)
    except (zipfile.BadZipFile, zipfile.LargeZipFile, OSError, EOFError, zlib.error, NotImplementedError) as exc:
        raise TableError(f"{path}: not a readable .npz table ({type(exc).__name__}: {exc})") from None
    kwargs: dict[str, Any] = {k: v for k, v in arrays.items() if k != "format"}
    for key in ("system", *_OPTIONAL_STRINGS):
        if key in arrays:
            kwargs[key] = _string(arrays[key], key, path)
    table = Table(**kwargs)
    validate_table(table, source=str(path), check_system=check_system, trust_factory=trust_factory)
    return table


MAX_EXPANSION = 200
"""a table's arrays may take at most this many times its file's size (or 64 MiB) once decompressed"""

_MIN_BUDGET = 64 << 20
_MAX_DIM = 64  # state and action dimensions
_MAX_STRING = {"format": 64, "system": 1 << 20, "method": 64, "build_info": 1 << 22}  # characters


def _read_members(zf: zipfile.ZipFile, path: Path, graph: bool) -> dict[str, np.ndarray]:
    """The format's arrays of an open ``.npz``, read in an order that bounds each one before it is decompressed."""
    infos = zf.infolist()
    seen: set[str] = set()
    for info in infos:
        if info.filename in seen:
            raise TableError(f"{path}: the zip holds {info.filename!r} twice (which copy is meant is ambiguous)")
        seen.add(info.filename)
    wanted = set(_REQUIRED) | set(_OPTIONAL_STRINGS) | (set(_OPTIONAL_ARRAYS) if graph else set())
    members = {info.filename[:-4]: info for info in infos
               if info.filename.endswith(".npy") and info.filename[:-4] in wanted}
    if "format" not in members:
        raise TableError(f"{path}: no 'format' key; this is not a cuniform table")
    budget = max(_MIN_BUDGET, MAX_EXPANSION * path.stat().st_size)
    total = sum(info.file_size for info in members.values())
    if total > budget:
        big = max(members, key=lambda k: members[k].file_size)
        raise TableError(f"{path}: its arrays would take {total} bytes decompressed ({big!r}: {members[big].file_size}), "
                         f"more than {MAX_EXPANSION}x the file's size; refusing to read it")
    headers = {key: _npy_header(zf, info, key, path) for key, info in members.items()}
    arrays: dict[str, np.ndarray] = {}

    def read(key: str, shape: tuple[int, ...] | None = None) -> None:
        if key not in members:
            return
        declared, dtype = headers[key]
        if shape is not None and declared != shape:
            raise TableError(f"{path}: key {key!r} must have shape {list(shape)} (from the table's offsets and "
                             f"sizes), its header says {list(declared)}")
        with zf.open(members[key]) as fh:
            try:
                arrays[key] = np.lib.format.read_array(fh, allow_pickle=False)
            except (ValueError, EOFError, zlib.error) as exc:
                raise TableError(f"{path}: array {key!r} is corrupt or truncated ({type(exc).__name__}: {exc})") from None

    read("format")
    fmt = _string(arrays["format"], "format", path)
    if fmt != TABLE_FORMAT:
        raise TableError(f"{path}: unknown table format {fmt!r}; this reader knows {TABLE_FORMAT!r}")
    missing = sorted(set(_REQUIRED) - set(members))
    if missing:
        raise TableError(f"{path}: missing required key(s) {', '.join(missing)}")
    for key, (dtype, ndim) in {**_REQUIRED, **_OPTIONAL_ARRAYS}.items():
        if key in headers and dtype is not None and (headers[key][1] != dtype or len(headers[key][0]) != ndim):
            raise TableError(f"{path}: key {key!r} must be {dtype} with {ndim} dimension(s), "
                             f"got {headers[key][1]} {list(headers[key][0])}")
    _check_small_shapes(headers, path)
    for key in ("system", *_OPTIONAL_STRINGS, "level_offsets", "actions", "cell_size", "periodic", "cell_offset",
                "flow_value", "flow_target", "arc_offsets", "transition_offsets"):
        read(key)
    C, d, A = int(arrays["level_offsets"][-1]) if len(arrays["level_offsets"]) else 0, len(arrays["cell_size"]), \
        len(arrays["actions"])
    read("cells", (C, d))
    read("action_probs", (C, A))
    read("cell_probs", (C,))
    for prefix, keys, width in (("arc", ("arcs", "arc_flow"), 2), ("transition", ("transitions", "transition_frac"), 3)):
        offsets = arrays.get(f"{prefix}_offsets")
        E = int(offsets[-1]) if offsets is not None and len(offsets) else 0
        read(keys[0], (E, width))
        read(keys[1], (E,))
    return arrays


def _npy_header(zf: zipfile.ZipFile, info: zipfile.ZipInfo, key: str, path: Path) -> tuple[tuple[int, ...], np.dtype]:
    """``(shape, dtype)`` from a member's ``.npy`` header; its data must be exactly what the header declares."""
    with zf.open(info) as fh:
        try:
            version = np.lib.format.read_magic(fh)
            if version == (1, 0):
                shape, _, dtype = np.lib.format.read_array_header_1_0(fh)
            elif version == (2, 0):
                shape, _, dtype = np.lib.format.read_array_header_2_0(fh)
            else:
                raise ValueError(f".npy version {version} is not supported")
        except (ValueError, EOFError, zlib.error) as exc:
            raise TableError(f"{path}: array {key!r} has no readable .npy header ({type(exc).__name__}: {exc})") from None
        header_size = fh.tell()
    if dtype.hasobject:
        raise TableError(f"{path}: array {key!r} holds Python objects (that would need pickle); refusing")
    expected = header_size + math.prod(shape) * dtype.itemsize
    if info.file_size != expected:
        raise TableError(f"{path}: array {key!r} holds {info.file_size} bytes, but its header declares {list(shape)} "
                         f"{dtype} ({expected} bytes)")
    return tuple(int(n) for n in shape), dtype


def _check_small_shapes(headers: dict[str, tuple[tuple[int, ...], np.dtype]], path: Path) -> None:
    """Absurd sizes in the small keys (horizon, actions, dimensions, strings), refused before anything is read."""
    limits = {"level_offsets": MAX_HORIZON + 2, "flow_value": MAX_HORIZON, "flow_target": MAX_HORIZON,
              "arc_offsets": MAX_HORIZON + 1, "transition_offsets": MAX_HORIZON + 1,
              "cell_size": _MAX_DIM, "periodic": _MAX_DIM, "cell_offset": _MAX_DIM}
    for key, limit in limits.items():
        if key in headers and headers[key][0][0] > limit:
            raise TableError(f"{path}: key {key!r} has {headers[key][0][0]} entries; at most {limit} are supported")
    A, q = headers["actions"][0]
    if A > MAX_ACTIONS or q > _MAX_DIM:
        raise TableError(f"{path}: key 'actions' is [{A}, {q}]; at most [{MAX_ACTIONS}, {_MAX_DIM}] is supported")
    for key, limit in _MAX_STRING.items():
        if key in headers:
            shape, dtype = headers[key]
            if shape != () or dtype.kind != "U":
                raise TableError(f"{path}: key {key!r} must be a string, got {dtype} {list(shape)}")
            if dtype.itemsize // 4 > limit:
                raise TableError(f"{path}: key {key!r} is {dtype.itemsize // 4} characters long; at most {limit}")


def _string(arr: np.ndarray, key: str, path: Any) -> str:
    if arr.ndim != 0 or arr.dtype.kind != "U":
        raise TableError(f"{path}: key {key!r} must be a string, got {arr.dtype} {list(arr.shape)}")
    return str(arr[()])


KNOWN_METHODS = ("maxflow", "coverage")
"""the builders whose tables this reader knows (the optional ``method`` key)"""


def validate_table(table: Table, source: str = "table", check_system: bool = True,
                   trust_factory: str | Callable[..., Any] | None = None) -> None:
    """Check shapes, offsets, probabilities and the system; raise :class:`TableError` on the first problem."""

    def fail(msg: str) -> None:
        raise TableError(f"{source}: {msg}")

    lo = np.asarray(table.level_offsets)
    if lo.ndim != 1 or len(lo) < 2:
        fail(f"level_offsets must have T+2 >= 2 entries, got shape {list(lo.shape)}")
    T = len(lo) - 2
    if table.cells.ndim != 2:
        fail(f"cells must be [C, d], got {list(table.cells.shape)}")
    C, d = table.cells.shape
    if lo[0] != 0 or lo[-1] != C or np.any(np.diff(lo) <= 0):
        fail(f"level_offsets must start at 0, end at the number of cells ({C}) and increase strictly; got {lo.tolist()[:12]}...")
    A = table.actions.shape[0]
    if A < 1 or table.actions.shape[1] < 1:
        fail(f"actions must be [A, q] with A, q >= 1, got {list(table.actions.shape)}")
    for key, shape in (("cell_size", (d,)), ("periodic", (d,)), ("cell_offset", (d,)), ("action_probs", (C, A)),
                       ("cell_probs", (C,)), ("flow_value", (T,)), ("flow_target", (T,))):
        if getattr(table, key).shape != shape:
            fail(f"{key} must have shape {list(shape)}, got {list(getattr(table, key).shape)}")
    for key in ("actions", "cell_size", "cell_offset", "action_probs", "cell_probs"):
        if not np.all(np.isfinite(getattr(table, key))):
            fail(f"{key} contains NaN or infinite values")
    try:  # the one check of the grid's invariants (angle cells of 2 pi / K within grid.ANGLE_CELL_RTOL)
        sizes, offsets = check_grid(table.cell_size, table.periodic, table.cell_offset, "grid")
    except ValueError as exc:
        fail(str(exc))
    grid = Grid(sizes, tuple(table.periodic), offsets)
    probs = table.action_probs
    if np.any(probs < 0) or np.any(probs > 1 + _ROW_SUM_TOL):
        fail("action_probs must lie in [0, 1]")
    row_err = np.abs(probs.sum(axis=1, dtype=np.float64) - 1.0)
    if np.any(row_err > _ROW_SUM_TOL):
        bad = int(np.argmax(row_err))
        fail(f"action_probs rows must sum to 1; row {bad} sums to {probs[bad].sum(dtype=np.float64):.6f}")
    if np.any(table.cell_probs < 0):
        fail("cell_probs must be non-negative")
    level_sums = np.add.reduceat(table.cell_probs, lo[:-1])
    if np.any(np.abs(level_sums - 1.0) > _LEVEL_SUM_TOL):
        fail(f"cell_probs must sum to 1 in every level; sums {np.round(level_sums, 6).tolist()[:12]}")
    sizes = np.diff(lo)
    if not np.array_equal(table.flow_target, sizes[:-1] * sizes[1:]):
        fail("flow_target must be n_t * n_{t+1} for every step")
    if np.any(table.flow_value < 0) or np.any(table.flow_value > table.flow_target):
        fail("flow_value must lie in [0, flow_target]")
    for dim in np.flatnonzero(table.periodic):
        k = grid.num_angle_cells[dim]
        col = table.cells[:, dim]
        if col.min() < 0 or col.max() >= k:
            fail(f"cells of angle dimension {dim} must lie in [0, {k})")
    if table.method is not None and table.method not in KNOWN_METHODS:
        fail(f"unknown method {table.method!r}; known: {', '.join(KNOWN_METHODS)}")
    _validate_cells(table, T, fail)
    _validate_graph(table, "arc", ("arcs", "arc_flow"), 2, T, C, A, fail)
    _validate_graph(table, "transition", ("transitions", "transition_frac"), 3, T, C, A, fail)
    if check_system:
        _validate_system(table, grid, T, fail, trust_factory)


_MAX_KEY_CELLS = 2**53  # the runtime packs a cell exactly into a float64 key
_MAX_PACKED = 2**62  # (level, cell) keys in int64, as cuniform_torch.grid.CellKeys packs them


def _validate_cells(table: Table, T: int, fail) -> None:
    """Level 0 is the start cell; every level's cells are distinct, in ascending (row-major) order, as the
    builders write them; the (level, cell) box with its one-cell halo packs into the runtime's keys."""
    cells, lo = table.cells, table.level_offsets
    box = 1
    for dim in range(cells.shape[1]):
        if table.periodic[dim]:
            box *= round(2 * np.pi / table.cell_size[dim])
        else:
            box *= int(cells[:, dim].max()) - int(cells[:, dim].min()) + 3  # python ints: no int64 overflow
    if box >= _MAX_KEY_CELLS or box * (T + 1) >= _MAX_PACKED:
        fail(f"the cells span a box of {box} cells (with the runtime's one-cell halo), too large to pack into keys "
             f"(at most 2^53); cell indices range over {cells.min(axis=0).tolist()} .. {cells.max(axis=0).tolist()}")
    if lo[1] != 1 or np.any(cells[0] != 0):
        fail(f"level 0 must be the single start cell {[0] * cells.shape[1]} (the zero state's cell), got "
             f"{lo[1]} cell(s) starting with {cells[0].tolist()}")
    if len(cells) > 1:
        diff = cells[1:] - cells[:-1]  # [C-1, d]: the first non-zero entry of each row gives the order
        nonzero = diff != 0
        first = np.argmax(nonzero, axis=1)
        sign = np.where(nonzero.any(axis=1), np.sign(diff[np.arange(len(diff)), first]), 0)
        same_level = np.ones(len(diff), dtype=bool)
        same_level[lo[1:-1] - 1] = False  # the pair (last of level t, first of level t+1)
        bad = np.flatnonzero(same_level & (sign <= 0))
        if len(bad):
            row = int(bad[0]) + 1
            level = int(np.searchsorted(lo, row, side="right")) - 1
            what = "repeats" if sign[bad[0]] == 0 else "comes before"
            fail(f"cells of level {level} must be distinct and in ascending order; row {row} {cells[row].tolist()} "
                 f"{what} row {row - 1} {cells[row - 1].tolist()}")


def _validate_graph(table: Table, prefix: str, keys: tuple[str, str], width: int, T: int, C: int, A: int, fail) -> None:
    offsets, edges, values = getattr(table, f"{prefix}_offsets"), getattr(table, keys[0]), getattr(table, keys[1])
    present = [x is not None for x in (offsets, edges, values)]
    if not any(present):
        return
    if not all(present):
        fail(f"{prefix}_offsets, {keys[0]} and {keys[1]} must be stored together")
    E = len(edges)
    if offsets.shape != (T + 1,) or offsets[0] != 0 or offsets[-1] != E or np.any(np.diff(offsets) < 0):
        fail(f"{prefix}_offsets must be [T+1] non-decreasing from 0 to {E}")
    if edges.shape != (E, width) or values.shape != (E,):
        fail(f"{keys[0]} must be [E, {width}] and {keys[1]} [E]")
    if not np.all(np.isfinite(values)) or np.any(values < 0):
        fail(f"{keys[1]} must be finite and non-negative")
    src, dst = edges[:, 0], edges[:, -1]
    if E and (src.min() < 0 or dst.min() < 0 or src.max() >= C or dst.max() >= C):
        fail(f"{keys[0]} refer to rows outside the table")
    if width == 3 and E and (edges[:, 1].min() < 0 or edges[:, 1].max() >= A):
        fail(f"{keys[0]} refer to actions outside [0, {A})")
    step = np.repeat(np.arange(T), np.diff(offsets))
    lo = table.level_offsets
    if E and (np.any(src < lo[step]) or np.any(src >= lo[step + 1]) or np.any(dst < lo[step + 1]) or np.any(dst >= lo[step + 2])):
        fail(f"{keys[0]} of step t must go from level t to level t+1")


def _validate_system(table: Table, grid: Grid, T: int, fail, trust_factory: str | Callable[..., Any] | None = None) -> None:
    try:
        system, horizon = system_from_json(table.system, trust_factory=trust_factory)
    except ValueError as exc:  # includes UnknownSystemError
        fail(f"the system cannot be rebuilt: {exc}")
    if horizon != T:
        fail(f"system JSON says horizon {horizon} but the table has {T} steps")
    expect = system.action_set(dtype=torch.float32).numpy()
    if expect.shape != table.actions.shape or not np.allclose(expect, table.actions, atol=1e-6):
        fail(f"actions do not match the system {system.name!r} ({expect.shape[0]} actions expected)")
    ours = Grid.of(system)  # both grids normalized by check_grid: angle sizes exactly 2 pi / K
    checks = (("cell_size", ours.cell_size, grid.cell_size), ("periodic", ours.periodic, grid.periodic),
              ("cell_offset", ours.offset, grid.offset))
    for key, value, theirs in checks:
        if not np.allclose(np.asarray(value, dtype=np.float64), np.asarray(theirs, dtype=np.float64)):
            fail(f"{key} {getattr(table, key).tolist()} does not match the system's {list(value)}")
    if json.loads(table.system).get("dt") not in (None, system.dt):
        fail("system JSON dt does not match its params")
