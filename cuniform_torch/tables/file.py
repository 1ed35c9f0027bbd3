"""The C-Uniform table file (``.npz``, format ``cuniform-table/1``): a dataclass, a writer and a bounded reader
(the content checks are in :mod:`cuniform_torch.tables.checks`).

Shapes: C cells over all levels, d state dimensions, A actions, q action dimensions, T horizon (steps),
E flow arcs, K recorded transitions. See DESIGN.md for the key-by-key contract.
"""

from __future__ import annotations

import hashlib
import io
import math
import mmap
import os
import zipfile
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch

from cuniform_torch.common.digest import DIGEST_KEY, DigestError, check_digest, content_digest
from cuniform_torch.common.fileio import file_kind, open_regular, write_npz
from cuniform_torch.common.npz import NpzError, npy_header
from cuniform_torch.systems import MAX_ACTIONS, MAX_HORIZON, System, system_from_json, system_to_json
from cuniform_torch.tables.checks import KNOWN_METHODS, TableError, validate_table

__all__ = ["TABLE_FORMAT", "Table", "TableError", "write_table", "read_table", "read_table_sha256",
           "validate_table", "system_fields",
           "KNOWN_METHODS", "DIGEST_KEY", "NOGRAPH_DIGEST_KEY", "table_digests"]

TABLE_FORMAT = "cuniform-table/1"

NOGRAPH_DIGEST_KEY = "content_sha256_nograph"
"""the digest of every format key but the six of the flow graph: what a ``graph=False`` read checks"""

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
_OPTIONAL_STRINGS = ("method", "build_info", "map_sha256")
_OPTIONAL_META: dict[str, tuple[np.dtype, int]] = {
    "start": (np.dtype(np.float64), 1),
    "map_origin": (np.dtype(np.float64), 1),
    "map_resolution": (np.dtype(np.float64), 0),
    "map_shape": (np.dtype(np.int64), 1),
    "map_radius": (np.dtype(np.float64), 0),
}
"""optional arrays a policy reads (unlike the graph's): ``start [d]``, the state the table was built from; the
local map of a safe table (with ``map_sha256``; see :data:`~cuniform_torch.tables.checks.MAP_KEYS`)"""
_DIGEST_KEYS = (DIGEST_KEY, NOGRAPH_DIGEST_KEY)
_KNOWN_KEYS = {"format", *_REQUIRED, *_OPTIONAL_ARRAYS, *_OPTIONAL_STRINGS, *_OPTIONAL_META, *_DIGEST_KEYS}



@dataclass
class Table:
    """A C-Uniform action-probability table, level by level (numpy arrays; see DESIGN.md).

    Optional graph data: ``arcs`` (global rows from -> to) with their max-flow ``arc_flow``, grouped per step by
    ``arc_offsets [T+1]``; ``transitions`` (global row from, action, global row to) with ``transition_frac``, the
    fraction of the (cell, action)'s kept sample points that land in the next cell, grouped by
    ``transition_offsets [T+1]``.

    Optional map keys (a safe table, whose levels exclude the cells in collision with a local map inflated by
    ``map_radius``): ``map_sha256``, ``map_origin``, ``map_resolution``, ``map_shape``, ``map_radius``, all or none.
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
    start: np.ndarray | None = None  # [d] float64: the build start; None: the zero state
    arc_offsets: np.ndarray | None = None  # [T+1] int64
    arcs: np.ndarray | None = None  # [E, 2] int64
    arc_flow: np.ndarray | None = None  # [E] int64
    transition_offsets: np.ndarray | None = None  # [T+1] int64
    transitions: np.ndarray | None = None  # [K, 3] int64
    transition_frac: np.ndarray | None = None  # [K] float64
    map_sha256: str | None = None  # a safe table's local map: sha256 of its uint8 [H, W] occupancy bytes
    map_origin: np.ndarray | None = None  # [2] float64, m: the map's cell (0, 0) corner in the start frame
    map_resolution: np.ndarray | None = None  # [] float64, m
    map_shape: np.ndarray | None = None  # [2] int64: H, W
    map_radius: np.ndarray | None = None  # [] float64, m: the robot radius the obstacles were inflated by
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


def table_digests(arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The two digest entries of a table's format ``arrays`` (name -> array; the ``extra`` keys left out):
    :data:`DIGEST_KEY` over all of them, :data:`NOGRAPH_DIGEST_KEY` over all but the flow graph's."""
    ours = {k: v for k, v in arrays.items() if k in _KNOWN_KEYS and k not in _DIGEST_KEYS}
    core = {k: v for k, v in ours.items() if k not in _OPTIONAL_ARRAYS}
    return {DIGEST_KEY: np.array(content_digest(ours)), NOGRAPH_DIGEST_KEY: np.array(content_digest(core))}


def write_table(path: str | os.PathLike, table: Table) -> None:
    """Validate ``table`` and write it atomically (a fixed-timestamp zip: equal tables give equal bytes), with
    the content digests of its format keys (:func:`table_digests`), which :func:`read_table` checks."""
    validate_table(table, source="table to write")
    clash = sorted(set(table.extra) & _KNOWN_KEYS)
    if clash:
        raise TableError(f"table to write: extra keys {', '.join(clash)} are keys of the format")
    arrays = table.to_arrays()
    arrays.update(table_digests(arrays))
    write_npz(path, arrays)


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

    Integrity: the arrays read are checked against the file's content digest (:data:`DIGEST_KEY`, or
    :data:`NOGRAPH_DIGEST_KEY` with ``graph=False``) before any check uses a value; a mismatch (a damaged or
    edited file) is a :class:`TableError` naming the file. A table written before digests loads, after a
    one-line note on stderr.
    """
    path = _table_path(path)
    try:
        arrays = _read_zip(path, path, graph, path.stat().st_size)
    except (zipfile.BadZipFile, zipfile.LargeZipFile, OSError, EOFError, zlib.error) as exc:
        raise TableError(f"{path}: not a readable .npz table ({type(exc).__name__}: {exc})") from None
    return _table_of(arrays, path, graph, check_system, trust_factory)


def read_table_sha256(path: str | os.PathLike, *, check_system: bool = True, graph: bool = True,
                      trust_factory: str | Callable[..., Any] | None = None) -> tuple[Table, str]:
    """:func:`read_table`, and the sha256 of the file's bytes (hex), from one read: the file is mapped once,
    hashed, and the table read from the same mapping, so the digest names exactly the bytes the table came
    from (a reader that hashes the path again reads the file twice and may hash a file replaced meanwhile)."""
    path = _table_path(path)
    try:
        with open_regular(path, "the table file") as fh:
            size = os.fstat(fh.fileno()).st_size
            if size == 0:  # mmap refuses an empty file; zipfile says what is wrong with it
                _read_zip(io.BytesIO(b""), path, graph, 0)
            with mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) as mm:
                sha = hashlib.sha256(mm).hexdigest()
                arrays = _read_zip(_Mapped(mm), path, graph, size)
    except (zipfile.BadZipFile, zipfile.LargeZipFile, OSError, EOFError, zlib.error) as exc:
        raise TableError(f"{path}: not a readable .npz table ({type(exc).__name__}: {exc})") from None
    return _table_of(arrays, path, graph, check_system, trust_factory), sha


class _Mapped:
    """A read-only file over an ``mmap`` for :class:`zipfile.ZipFile` (Python 3.11's mmap has no ``seekable``)."""

    def __init__(self, mm: mmap.mmap) -> None:
        self._mm = mm
        self.read, self.tell = mm.read, mm.tell

    def seek(self, pos: int, whence: Literal[0, 1, 2] = 0) -> int:
        try:
            self._mm.seek(pos, whence)
        except ValueError as exc:  # a file says OSError, which zipfile expects of a short (non-zip) file
            raise OSError(str(exc)) from None
        return self._mm.tell()

    def seekable(self) -> bool:
        return True


def _read_zip(source: Any, path: Path, graph: bool, size: int) -> dict[str, np.ndarray]:
    """:func:`_read_members` of the zip at ``source`` (a path or a seekable binary file)."""
    with zipfile.ZipFile(source) as zf:
        return _read_members(zf, path, graph, size)


def _table_path(path: str | os.PathLike) -> Path:
    """``path`` as a Path, or :class:`TableError` when no regular file is there (a FIFO or a device is never
    opened), saying what is there instead, when something is."""
    path = Path(path)
    if not path.is_file():
        try:
            there = f" ({file_kind(os.stat(path).st_mode)}{' through a symlink' if path.is_symlink() else ''})"
        except OSError:
            there = ""
        raise TableError(f"{path}: no table file there{there}")
    return path


def _table_of(arrays: dict[str, np.ndarray], path: Path, graph: bool, check_system: bool,
              trust_factory: str | Callable[..., Any] | None) -> Table:
    """The arrays read from ``path``, digest-checked, as a validated :class:`Table`."""
    _check_digests(arrays, path, graph)
    kwargs: dict[str, Any] = {k: v for k, v in arrays.items() if k != "format" and k not in _DIGEST_KEYS}
    for key in ("system", *_OPTIONAL_STRINGS):
        if key in arrays:
            kwargs[key] = _string(arrays[key], key, path)
    table = Table(**kwargs)
    validate_table(table, source=str(path), check_system=check_system, trust_factory=trust_factory)
    return table


def _check_digests(arrays: dict[str, np.ndarray], path: Path, graph: bool) -> None:
    """The arrays read against their digest (:func:`~cuniform_torch.common.digest.check_digest`): TableError
    on a mismatch; a note for a file without one."""
    key = DIGEST_KEY if graph else NOGRAPH_DIGEST_KEY
    stored = _string(arrays[key], key, path) if key in arrays else None
    covered = {k: v for k, v in arrays.items() if k not in _DIGEST_KEYS}
    try:
        check_digest(covered, stored, str(path))
    except DigestError as exc:
        raise TableError(str(exc)) from None


MAX_EXPANSION = 200
"""a table's arrays may take at most this many times its file's size (or 64 MiB) once decompressed"""

_MIN_BUDGET = 64 << 20
_MAX_DIM = 64  # state and action dimensions
_MAX_STRING = {"format": 64, "system": 1 << 20, "method": 64, "build_info": 1 << 22, "map_sha256": 64,
               DIGEST_KEY: 64, NOGRAPH_DIGEST_KEY: 64}  # characters


def _read_members(zf: zipfile.ZipFile, path: Path, graph: bool, file_size: int) -> dict[str, np.ndarray]:
    """The format's arrays of an open ``.npz`` of ``file_size`` bytes, read in an order that bounds each one before
    it is decompressed."""
    infos = zf.infolist()
    seen: set[str] = set()
    for info in infos:
        if info.filename in seen:
            raise TableError(f"{path}: the zip holds {info.filename!r} twice (which copy is meant is ambiguous)")
        seen.add(info.filename)
    wanted = _KNOWN_KEYS if graph else _KNOWN_KEYS - set(_OPTIONAL_ARRAYS)
    members = {info.filename[:-4]: info for info in infos
               if info.filename.endswith(".npy") and info.filename[:-4] in wanted}
    for key, info in members.items():  # zipfile itself would say only "That compression method is not supported"
        if info.compress_type not in (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED):
            raise TableError(f"{path}: array {key!r} uses zip compression method {info.compress_type}; a table is "
                             "stored or deflated")
    if "format" not in members:
        raise TableError(f"{path}: no 'format' key; this is not a cuniform table")
    budget = max(_MIN_BUDGET, MAX_EXPANSION * file_size)
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
    for key, (dtype, ndim) in {**_REQUIRED, **_OPTIONAL_ARRAYS, **_OPTIONAL_META}.items():
        if key in headers and dtype is not None and (headers[key][1] != dtype or len(headers[key][0]) != ndim):
            raise TableError(f"{path}: key {key!r} must be {dtype} with {ndim} dimension(s), "
                             f"got {headers[key][1]} {list(headers[key][0])}")
    _check_small_shapes(headers, path)
    for key in ("system", *_OPTIONAL_STRINGS, *_DIGEST_KEYS, "level_offsets", "actions", "cell_size", "periodic", "cell_offset",
                "flow_value", "flow_target", "arc_offsets", "transition_offsets"):
        read(key)
    C, d, A = int(arrays["level_offsets"][-1]) if len(arrays["level_offsets"]) else 0, len(arrays["cell_size"]), \
        len(arrays["actions"])
    read("start", (d,))
    for key, shape in (("map_origin", (2,)), ("map_resolution", ()), ("map_shape", (2,)), ("map_radius", ())):
        read(key, shape)
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
            shape, _, dtype, header_size = npy_header(fh, f"{path}: array {key!r}")
        except NpzError as exc:
            raise TableError(str(exc)) from None
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
