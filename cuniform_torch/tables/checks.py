"""Checks of a table's content: shapes, offsets, probabilities, cells, flow graph and system.

:func:`validate_table` runs them all on a :class:`~cuniform_torch.tables.file.Table` (before it is written, after it is
read); the first problem raises :class:`TableError`, naming the file and the key. Shapes as in
:mod:`cuniform_torch.tables.file`.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from cuniform_torch.grid.cells import Grid, check_grid
from cuniform_torch.systems import system_from_json

__all__ = ["TableError", "KNOWN_METHODS", "MAP_KEYS", "PROPAGATION_RTOL", "PROPAGATION_ATOL", "validate_table"]


class TableError(ValueError):
    """A table file that is missing, corrupt, truncated, of an unknown format, or inconsistent."""


_ROW_SUM_TOL = 1e-4  # float32 rows
_LEVEL_SUM_TOL = 1e-6  # float64 cell probabilities per level
PROPAGATION_RTOL = 1e-5
"""relative tolerance of ``cell_probs`` against level t's mass propagated through ``transitions``: a builder
propagates float64 action probabilities that the file stores as float32 (a relative error below 1e-7 per cell)"""
PROPAGATION_ATOL = 1e-12
"""absolute part of that tolerance (cells of nearly no mass)"""

KNOWN_METHODS = ("maxflow", "coverage")
"""the builders whose tables this reader knows (the optional ``method`` key)"""

MAP_KEYS = ("map_sha256", "map_origin", "map_resolution", "map_shape", "map_radius")
"""the optional keys of a safe table's local map, stored all together or not at all"""
_MAX_MAP_SIDE = 4096


def validate_table(table: Any, source: str = "table", check_system: bool = True,
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
    level_sizes = np.diff(lo)
    if not np.array_equal(table.flow_target, level_sizes[:-1] * level_sizes[1:]):
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
    start_cell = np.zeros(d, dtype=np.int64)
    start = getattr(table, "start", None)
    if start is not None:
        start = np.asarray(start)
        if start.shape != (d,) or start.dtype != np.float64 or not np.all(np.isfinite(start)):
            fail(f"start must be {d} finite float64 numbers (the build start), got {start.dtype} {list(start.shape)}")
        start_cell = grid.cells(torch.from_numpy(start)[None])[0].numpy()
    _validate_map(table, fail)
    _validate_cells(table, T, fail, start_cell)
    _validate_graph(table, "arc", ("arcs", "arc_flow"), 2, T, C, A, fail)
    _validate_graph(table, "transition", ("transitions", "transition_frac"), 3, T, C, A, fail)
    _validate_arc_flow(table, T, fail)
    _validate_propagation(table, fail)
    if check_system:
        _validate_system(table, grid, T, fail, trust_factory)


_MAX_KEY_CELLS = 2**53  # the runtime packs a cell exactly into a float64 key
_MAX_PACKED = 2**62  # (level, cell) keys in int64, as cuniform_torch.grid.cells.CellKeys packs them


def _validate_cells(table: Any, T: int, fail, start_cell: np.ndarray) -> None:
    """Level 0 is the start cell (of ``start``, else the zero state); every level's cells are distinct, in ascending (row-major) order, as the
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
    if lo[1] != 1 or np.any(cells[0] != start_cell):
        fail(f"level 0 must be the single start cell {start_cell.tolist()} (the build start's cell), got "
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


def _validate_map(table: Any, fail) -> None:
    """The map keys: all or none; a 64-digit hex sha256, a finite origin [2], a resolution > 0, a shape [2] of
    1..4096 cells, a radius >= 0 (m)."""
    values = {key: getattr(table, key, None) for key in MAP_KEYS}
    given = [key for key, value in values.items() if value is not None]
    if not given:
        return
    if len(given) != len(MAP_KEYS):
        fail(f"the map keys {', '.join(MAP_KEYS)} must be stored together; missing "
             f"{', '.join(k for k in MAP_KEYS if values[k] is None)}")
    sha = values["map_sha256"]
    if not isinstance(sha, str) or len(sha) != 64 or any(c not in "0123456789abcdef" for c in sha):
        fail(f"map_sha256 must be 64 lowercase hex digits, got {sha!r}")
    arrays = {key: np.asarray(values[key]) for key in MAP_KEYS[1:]}
    for key, dtype, shape in (("map_origin", np.float64, (2,)), ("map_resolution", np.float64, ()),
                              ("map_shape", np.int64, (2,)), ("map_radius", np.float64, ())):
        arr = arrays[key]
        if arr.dtype != dtype or arr.shape != shape or not np.all(np.isfinite(arr)):
            fail(f"{key} must be finite {np.dtype(dtype)} of shape {list(shape)}, got {arr.dtype} {list(arr.shape)}")
    if not arrays["map_resolution"] > 0:
        fail(f"map_resolution must be > 0 (m), got {float(arrays['map_resolution'])}")
    if not arrays["map_radius"] >= 0:
        fail(f"map_radius must be >= 0 (m), got {float(arrays['map_radius'])}")
    if np.any(arrays["map_shape"] < 1) or np.any(arrays["map_shape"] > _MAX_MAP_SIDE):
        fail(f"map_shape must be 1..{_MAX_MAP_SIDE} cells per side, got {arrays['map_shape'].tolist()}")


def _validate_graph(table: Any, prefix: str, keys: tuple[str, str], width: int, T: int, C: int, A: int, fail) -> None:
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


def _validate_arc_flow(table: Any, T: int, fail) -> None:
    """The flow into each level t+1 (the ``arc_flow`` of step t's arcs, summed) equals ``flow_value[t]``."""
    if table.arcs is None:
        return
    flow, offsets = table.arc_flow, table.arc_offsets
    if len(flow) and float(flow.sum(dtype=np.float64)) >= 2.0**62:  # the int64 sums below could wrap
        fail("arc_flow sums to more than 2^62")
    total = np.concatenate(([0], np.cumsum(flow, dtype=np.int64)))  # [E+1]
    into = total[offsets[1:]] - total[offsets[:-1]]  # [T]: the flow into level t+1
    bad = np.flatnonzero(into != table.flow_value)
    if len(bad):
        t = int(bad[0])
        fail(f"arc_flow does not match flow_value: the arcs of step {t} carry {int(into[t])} into level {t + 1}, "
             f"flow_value[{t}] is {int(table.flow_value[t])}")


def _validate_propagation(table: Any, fail) -> None:
    """Level t's ``cell_probs``, propagated through the transitions (``P'[j] = sum P[i] p(a | i) frac(i, a, j)``,
    normalized per level as a safe build does), give level t+1's within :data:`PROPAGATION_RTOL` (relative) +
    :data:`PROPAGATION_ATOL`. Not checked for a coverage table with a map: its builder propagates states, and a
    map prunes a (state, action) state by state, so the cell-level propagation is only approximate there."""
    if table.transitions is None or (table.method == "coverage" and table.map_sha256 is not None):
        return
    lo, stored = table.level_offsets, table.cell_probs
    src, act, dst = table.transitions[:, 0], table.transitions[:, 1], table.transitions[:, 2]
    mass = stored[src] * table.action_probs[src, act].astype(np.float64) * table.transition_frac  # [K]
    # [C]: level 0 receives none; float64 (weighted bincount), the stubs type it as an int array
    prop: np.ndarray = np.bincount(dst, weights=mass, minlength=len(stored))
    sums = np.add.reduceat(prop, lo[:-1])[1:]  # [T]: levels 1..T
    if np.any(~(sums > 0)):
        t = int(np.flatnonzero(~(sums > 0))[0]) + 1
        fail(f"cell_probs do not match transitions: no probability mass reaches level {t} through them")
    prop[lo[1]:] /= np.repeat(sums, np.diff(lo)[1:])
    err = np.abs(prop - stored)[lo[1]:]  # [C-1]
    bad = np.flatnonzero(err > PROPAGATION_RTOL * stored[lo[1]:] + PROPAGATION_ATOL)
    if len(bad):
        row = int(bad[np.argmax(err[bad])]) + int(lo[1])
        level = int(np.searchsorted(lo, row, side="right")) - 1
        fail(f"cell_probs do not match transitions: cell row {row} of level {level} holds {stored[row]:.9g}, but "
             f"level {level - 1}'s cell_probs propagated through the transitions give {prop[row]:.9g} "
             f"(tolerance {PROPAGATION_RTOL:g} relative)")


def _validate_system(table: Any, grid: Grid, T: int, fail, trust_factory: str | Callable[..., Any] | None = None) -> None:
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
