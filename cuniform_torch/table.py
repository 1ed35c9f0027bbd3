"""The C-Uniform table file (``.npz``, format ``cuniform-table/1``): a dataclass, a writer and a validating reader.

Shapes: C cells over all levels, d state dimensions, A actions, q action dimensions, T horizon (steps),
E flow arcs, K recorded transitions. See DESIGN.md for the key-by-key contract.
"""

from __future__ import annotations

import json
import os
import zipfile
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .fileio import write_npz
from .systems import System, system_from_json, system_to_json

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
    """keys this reader does not know, kept as they are"""

    @property
    def horizon(self) -> int:
        return len(self.level_offsets) - 2

    @property
    def level_sizes(self) -> list[int]:
        return np.diff(self.level_offsets).tolist()

    def level(self, t: int) -> slice:
        """Rows of level ``t``."""
        return slice(int(self.level_offsets[t]), int(self.level_offsets[t + 1]))

    def make_system(self) -> System:
        """Rebuild the system this table was built for."""
        return system_from_json(self.system)[0]

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


def read_table(path: str | os.PathLike, *, check_system: bool = True, graph: bool = True) -> Table:
    """Read and validate a table file; every problem raises :class:`TableError` naming the file and the key.

    ``graph=False`` leaves the optional flow graph (``arcs``, ``transitions`` and their values: the audit data a
    max-flow build stores) in the file, unread and unchecked; the table's graph fields are then None. A policy
    needs none of it, and for a large table it is most of the file: 3.5 GB of the ks table's arrays.
    """
    path = Path(path)
    if not path.is_file():
        raise TableError(f"{path}: no table file there")
    try:
        npz = np.load(path, allow_pickle=False)
    except (zipfile.BadZipFile, ValueError, OSError, EOFError) as exc:
        raise TableError(f"{path}: not a readable .npz table ({type(exc).__name__}: {exc})") from None
    if not isinstance(npz, np.lib.npyio.NpzFile):
        raise TableError(f"{path}: a single .npy array, not an .npz table")
    with npz:
        names = set(npz.files) if graph else set(npz.files) - set(_OPTIONAL_ARRAYS)
        arrays: dict[str, np.ndarray] = {}
        for key in names:
            try:
                arrays[key] = npz[key]
            except Exception as exc:  # zlib.error, ValueError (pickled objects), EOFError (truncated), ...
                raise TableError(f"{path}: array {key!r} is corrupt or truncated ({type(exc).__name__}: {exc})") from None
            if not isinstance(arrays[key], np.ndarray):  # a zip member without the .npy suffix: raw bytes
                if key in _KNOWN_KEYS:
                    raise TableError(f"{path}: entry {key!r} is not a .npy array")
                del arrays[key]
    if "format" not in arrays:
        raise TableError(f"{path}: no 'format' key; this is not a cuniform table")
    fmt = _string(arrays["format"], "format", path)
    if fmt != TABLE_FORMAT:
        raise TableError(f"{path}: unknown table format {fmt!r}; this reader knows {TABLE_FORMAT!r}")
    missing = sorted(set(_REQUIRED) - names)
    if missing:
        raise TableError(f"{path}: missing required key(s) {', '.join(missing)}")
    for key, (dtype, ndim) in {**_REQUIRED, **_OPTIONAL_ARRAYS}.items():
        if key not in arrays or dtype is None:
            continue
        arr = arrays[key]
        if arr.dtype != dtype or arr.ndim != ndim:
            raise TableError(f"{path}: key {key!r} must be {dtype} with {ndim} dimension(s), got {arr.dtype} {list(arr.shape)}")
    known = set(_REQUIRED) | set(_OPTIONAL_ARRAYS) | set(_OPTIONAL_STRINGS)
    kwargs: dict[str, Any] = {k: arrays[k] for k in known if k in arrays and k != "format"}
    kwargs["system"] = _string(arrays["system"], "system", path)
    for key in _OPTIONAL_STRINGS:
        if key in arrays:
            kwargs[key] = _string(arrays[key], key, path)
    table = Table(**kwargs, extra={k: v for k, v in arrays.items() if k not in known})
    validate_table(table, source=str(path), check_system=check_system)
    return table


def _string(arr: np.ndarray, key: str, path: Any) -> str:
    if arr.ndim != 0 or arr.dtype.kind != "U":
        raise TableError(f"{path}: key {key!r} must be a string, got {arr.dtype} {list(arr.shape)}")
    return str(arr[()])


def validate_table(table: Table, source: str = "table", check_system: bool = True) -> None:
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
    if np.any(table.cell_size <= 0):
        fail(f"cell_size must be positive, got {table.cell_size.tolist()}")
    if np.any(np.abs(table.cell_offset) >= 0.5):
        fail(f"cell_offset must satisfy |offset| < 0.5 cells, got {table.cell_offset.tolist()}")
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
        k = round(2 * np.pi / table.cell_size[dim])
        col = table.cells[:, dim]
        if col.min() < 0 or col.max() >= k:
            fail(f"cells of angle dimension {dim} must lie in [0, {k})")
    _validate_graph(table, "arc", ("arcs", "arc_flow"), 2, T, C, A, fail)
    _validate_graph(table, "transition", ("transitions", "transition_frac"), 3, T, C, A, fail)
    if check_system:
        _validate_system(table, T, fail)


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


def _validate_system(table: Table, T: int, fail) -> None:
    try:
        system, horizon = system_from_json(table.system)
    except ValueError as exc:  # includes UnknownSystemError
        fail(f"the system cannot be rebuilt: {exc}")
    if horizon != T:
        fail(f"system JSON says horizon {horizon} but the table has {T} steps")
    expect = system.action_set(dtype=torch.float32).numpy()
    if expect.shape != table.actions.shape or not np.allclose(expect, table.actions, atol=1e-6):
        fail(f"actions do not match the system {system.name!r} ({expect.shape[0]} actions expected)")
    checks = (("cell_size", system.cell_size), ("periodic", system.periodic), ("cell_offset", system.cell_offset))
    for key, value in checks:
        if not np.allclose(np.asarray(value, dtype=np.float64), np.asarray(getattr(table, key), dtype=np.float64)):
            fail(f"{key} {getattr(table, key).tolist()} does not match the system's {list(value)}")
    if json.loads(table.system).get("dt") not in (None, system.dt):
        fail("system JSON dt does not match its params")
