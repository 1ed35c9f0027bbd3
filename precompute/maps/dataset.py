"""The map-table data set ``cuniform-map-dataset/1``: one safe table per (local map, start pose), in shards.

Shapes: M entries per shard, H x W patch cells, R table rows of a shard, d state dimensions, A actions, T horizon.

A folder DIR holds ``dataset.json`` (written last, atomically) and ``shard-KKKKK.npz`` files; the format is fixed
in DESIGN.md (section "Map-table data set"). Per shard: ``patches`` uint8 [M, H, W] (1 = occupied, not
inflated), ``poses`` float64 [M, 3] (world start poses), ``entry_offsets`` int64 [M+1] (rows of entry m),
``level_offsets`` int64 [M, T+2] (per entry, relative to its first row), ``cells`` int32 [R, d],
``action_probs`` float16 [R, A], ``cell_probs`` float32 [R], and ``content_sha256`` (the digest of the others,
:mod:`cuniform_torch.common.digest`; absent in shards written before it).

:func:`read_map_dataset` validates everything and raises one :class:`MapDatasetError` naming the file and the
problem; :func:`entry_arrays` and :func:`write_shard` are the writer's half (:mod:`precompute.maps.farm`).

A shard is read with the bounded reader (:func:`cuniform_torch.common.npz.read_npz`): every member's shape and
dtype are checked from its ``.npy`` header against ``dataset.json`` before anything is allocated. Its tables are
then checked against what the farm's builders guarantee (:func:`_check_tables`): no patch occupied everywhere;
level 0 is the origin cell; every level's cells are distinct and ascending; every cell's centre is free in its
patch inflated by the data set's radius; the last level's rows are uniform; every cell of level t is in the blind
level set of t steps from the origin (``maxflow``), or within one cell of a successor of the level before's
lattice points (``coverage``). With ``verify_all`` every ``maxflow`` entry is also checked against the builder step
by step (about a third of the build's time; vectorized over a shard's entries, one pass per level; the commands of
:mod:`training.maps` run it by default, ``--skip-deep-checks`` trusts the files): each level's cells are successors of the level before's centres,
every free successor left out is a dead end, and each level's ``cell_probs`` is the level before's propagated
through its ``action_probs`` and the builder's transitions (recomputed). So rows permuted within a level, another
speed, radius or patch resolution, a transposed patch are refused.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from cuniform_torch.common.digest import DIGEST_KEY, DigestError, check_digest, content_digest
from cuniform_torch.common.fileio import MAX_JSON_BYTES, file_kind, open_regular, read_capped_text, write_npz
from cuniform_torch.common.npz import NpzError, member_headers, read_npz
from cuniform_torch.grid.cells import CellKeys, CellSet, Grid
from cuniform_torch.systems import System, system_from_json, system_to_json
from cuniform_torch.tables.file import Table
from precompute.levels.safe_map import LocalMap, MapError, check_map_system
from precompute.levels.sets import PointMode, cell_sample_offsets

__all__ = ["DATASET_FORMAT", "SHARD_KEYS", "MapDatasetError", "MapEntry", "MapShard", "MapDataset", "read_map_dataset",
           "entry_arrays", "write_shard", "file_sha256", "dataset_header"]

DATASET_FORMAT = "cuniform-map-dataset/1"
SHARD_KEYS = ("patches", "poses", "entry_offsets", "level_offsets", "cells", "action_probs", "cell_probs")
_DTYPES = {"patches": np.uint8, "poses": np.float64, "entry_offsets": np.int64, "level_offsets": np.int64,
           "cells": np.int32, "action_probs": np.float16, "cell_probs": np.float32}
_SHARD_NAME = re.compile(r"shard-\d{5}\.npz")
_ROW_TOL = 1e-2  # float16 action rows
_LEVEL_TOL = 1e-3  # float32 cell probabilities per level
_MAX_SIDE = 4096
_PROPAGATION_TOL = 1e-2  # L1 distance of a level's stored and propagated cell_probs (float16 rows, float32 probs)


class MapDatasetError(ValueError):
    """A map-table data set (or one of its shards) that is missing, corrupt, foreign or inconsistent."""


@dataclass(frozen=True, eq=False)
class MapEntry:
    """One (map, pose) entry: its local map and its safe table's rows."""

    source: str
    pose: np.ndarray  # [3] float64, world
    patch: np.ndarray  # [H, W] uint8
    level_offsets: np.ndarray  # [T+2] int64, relative to the entry's first row
    cells: np.ndarray  # [R_e, d] int32
    action_probs: np.ndarray  # [R_e, A] float32, renormalised rows
    cell_probs: np.ndarray  # [R_e] float32


@dataclass(frozen=True, eq=False)
class MapShard:
    """The validated arrays of one shard (keys :data:`SHARD_KEYS`)."""

    path: Path
    arrays: dict[str, np.ndarray]

    def __len__(self) -> int:
        return len(self.arrays["poses"])


@dataclass(eq=False)
class MapDataset:
    """A read data set: its metadata (``dataset.json``), the system, and its shards (loaded or on demand)."""

    root: Path
    meta: dict[str, Any]
    system: System
    horizon: int
    method: str
    actions: np.ndarray  # [A, q] float64
    radius: float
    patch_shape: tuple[int, int]
    patch_resolution: float
    patch_origin: tuple[float, float]
    split: str
    seed: int
    entries: list[dict[str, Any]]
    shards: list[dict[str, Any]]
    verify_all: bool = False
    """check every ``maxflow`` entry's table against the farm's builder when a shard is read (module docstring)"""
    _loaded: dict[int, MapShard] = field(default_factory=dict)
    _blind: list[CellSet] | None = None

    def __len__(self) -> int:
        return len(self.entries)

    def shard(self, k: int) -> MapShard:
        """Shard ``k``, read and validated (sha256 first) on first use."""
        if k not in self._loaded:
            self._loaded[k] = _read_shard(self, k)
        return self._loaded[k]

    def __iter__(self) -> Iterator[MapEntry]:
        """Every entry in order (one shard in memory at a time unless they were loaded)."""
        for k in range(len(self.shards)):
            sh = self.shard(k) if k in self._loaded else _read_shard(self, k)
            a = sh.arrays
            for m in range(len(sh)):
                lo, hi = int(a["entry_offsets"][m]), int(a["entry_offsets"][m + 1])
                probs = a["action_probs"][lo:hi].astype(np.float32)
                yield MapEntry(self.entries[self._first[k] + m]["source"], a["poses"][m], a["patches"][m],
                               a["level_offsets"][m], a["cells"][lo:hi], probs / probs.sum(axis=1, keepdims=True),
                               a["cell_probs"][lo:hi])

    @property
    def _first(self) -> list[int]:
        return np.concatenate(([0], np.cumsum([s["entries"] for s in self.shards]))).astype(int).tolist()


def file_sha256(path: str | Path) -> str:
    """sha256 (hex) of a file's bytes."""
    h = hashlib.sha256()
    with open_regular(path) as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def dataset_header(system: System, horizon: int, method: str, radius: float, patch_shape: Sequence[int],
                   resolution: float, origin: Sequence[float], split: str, seed: int) -> dict[str, Any]:
    """The ``dataset.json`` keys other than ``entries`` and ``shards``."""
    grid = Grid.of(system)
    return {"format": DATASET_FORMAT, "system": system_to_json(system, horizon), "horizon": int(horizon),
            "method": method, "grid": {"cell_size": [float(v) for v in grid.cell_size],
                                       "cell_offset": [float(v) for v in grid.offset],
                                       "periodic": [bool(v) for v in grid.periodic]},
            "actions": system.action_set(dtype=torch.float32).double().tolist(), "radius": float(radius),
            "patch": {"shape": [int(v) for v in patch_shape], "resolution": float(resolution),
                      "origin": [float(v) for v in origin]},
            "split": split, "seed": int(seed)}


def entry_arrays(table: Table) -> dict[str, np.ndarray]:
    """One entry's rows from a safe table: ``level_offsets`` [T+2] int64, ``cells`` int32, ``action_probs``
    float16, ``cell_probs`` float32."""
    cells = table.cells
    if cells.size and (cells.min() < np.iinfo(np.int32).min or cells.max() > np.iinfo(np.int32).max):
        raise MapDatasetError("a table's cell indices do not fit in int32")
    return {"level_offsets": table.level_offsets.astype(np.int64), "cells": cells.astype(np.int32),
            "action_probs": table.action_probs.astype(np.float16), "cell_probs": table.cell_probs.astype(np.float32)}


def write_shard(path: str | Path, patches: np.ndarray, poses: np.ndarray, entries: Sequence[dict[str, np.ndarray]]) -> str:
    """Write a shard of ``len(entries)`` entries (from :func:`entry_arrays`) atomically; returns its sha256."""
    sizes = [len(e["cells"]) for e in entries]
    arrays = {"patches": np.ascontiguousarray(patches, dtype=np.uint8), "poses": np.asarray(poses, dtype=np.float64),
              "entry_offsets": np.concatenate(([0], np.cumsum(sizes))).astype(np.int64),
              "level_offsets": np.stack([e["level_offsets"] for e in entries]).astype(np.int64),
              **{k: np.concatenate([e[k] for e in entries]) for k in ("cells", "action_probs", "cell_probs")}}
    arrays[DIGEST_KEY] = np.array(content_digest(arrays))
    write_npz(path, arrays, compress=True)
    return file_sha256(path)


# -------------------------------------------------------------------------------------------------- reading

def read_map_dataset(root: str | Path, load: bool = False, verify_all: bool = False) -> MapDataset:
    """Read and validate ``root/dataset.json`` and check every shard's sha256 (``load``: also read and validate
    every shard now; else each is read and validated on first use). ``verify_all``: also check every ``maxflow``
    entry against the builder step by step, its reach, pruning and propagation (module docstring; about a third of
    the farm's build time). One :class:`MapDatasetError` per problem."""
    root = Path(root)
    path = root / "dataset.json"
    if path.exists() and not path.is_file():
        raise MapDatasetError(f"{path}: {file_kind(os.stat(path).st_mode)}, not a regular file")
    if not path.is_file():
        raise MapDatasetError(f"{path}: no dataset.json there (an unfinished or missing data set)")
    try:
        meta = json.loads(read_capped_text(path, MAX_JSON_BYTES, "the data-set manifest"))
    except (OSError, UnicodeDecodeError, ValueError, RecursionError) as exc:  # RecursionError: nested too deep
        raise MapDatasetError(f"{path}: not readable JSON ({type(exc).__name__}: {exc})") from None
    ds = _dataset_from_meta(meta, root, path)
    ds.verify_all = bool(verify_all)
    for k in range(len(ds.shards)):
        _check_sha(ds, k)
        if load:
            ds.shard(k)
    return ds


def _dataset_from_meta(meta: Any, root: Path, path: Path) -> MapDataset:
    def fail(msg: str) -> None:
        raise MapDatasetError(f"{path}: {msg}")

    if not isinstance(meta, dict):
        fail("must hold a JSON object")
    if meta.get("format") != DATASET_FORMAT:
        fail(f"format must be {DATASET_FORMAT!r}, got {meta.get('format')!r}")
    need = ("system", "horizon", "method", "grid", "actions", "radius", "patch", "split", "seed", "entries", "shards")
    missing = [k for k in need if k not in meta]
    if missing:
        fail(f"missing key(s) {', '.join(missing)}")
    if not isinstance(meta["system"], str):
        fail("system must be the system JSON string")
    try:
        system, horizon = system_from_json(meta["system"])
    except ValueError as exc:
        fail(f"the system cannot be rebuilt: {exc}")
    if not _is_int(meta["horizon"]) or meta["horizon"] != horizon or horizon < 1:
        fail(f"horizon {meta['horizon']!r} does not match the system JSON's {horizon}")
    if meta["method"] not in ("maxflow", "coverage"):
        fail(f"method must be maxflow or coverage, got {meta['method']!r}")
    ref = dataset_header(system, horizon, meta["method"], 0.0, (1, 1), 1.0, (0, 0), "train", 0)
    grid = meta["grid"]
    if not isinstance(grid, dict) or not all(_close(grid.get(k), ref["grid"][k]) for k in ref["grid"]) \
            or not all(isinstance(v, bool) for v in grid["periodic"]):  # 0 for false: not what the farm writes
        fail(f"grid {grid!r} does not match the system's {ref['grid']}")
    if not _close(meta["actions"], ref["actions"]):
        fail(f"actions do not match the system {system.name!r} ({len(ref['actions'])} actions expected)")
    radius, patch = meta["radius"], meta["patch"]
    if not _is_num(radius) or radius < 0:
        fail(f"radius must be a number >= 0 (m), got {radius!r}")
    if not isinstance(patch, dict) or set(patch) != {"shape", "resolution", "origin"}:
        fail(f"patch must hold shape, resolution, origin, got {patch!r}")
    shape, res, origin = patch["shape"], patch["resolution"], patch["origin"]
    if not (isinstance(shape, list) and len(shape) == 2 and all(_is_int(v) and 1 <= v <= _MAX_SIDE for v in shape)):
        fail(f"patch shape must be [H, W] of 1..{_MAX_SIDE}, got {shape!r}")
    if not (_is_num(res) and res > 0):
        fail(f"patch resolution must be > 0 (m), got {res!r}")
    if not (isinstance(origin, list) and len(origin) == 2 and all(_is_num(v) for v in origin)):
        fail(f"patch origin must be [x0, y0], got {origin!r}")
    centred = [-shape[1] * res / 2, -shape[0] * res / 2]  # the farm's: the robot's start at the patch's centre
    if not np.allclose(origin, centred, rtol=1e-9, atol=1e-12):
        fail(f"patch origin {origin!r} must be the centred origin [-W * resolution / 2, -H * resolution / 2] = "
             f"{centred!r} of shape {shape!r} and resolution {res!r}")
    if meta["split"] not in ("train", "test"):
        fail(f"split must be train or test, got {meta['split']!r}")
    if not _is_int(meta["seed"]):
        fail(f"seed must be an integer, got {meta['seed']!r}")
    shards, entries = meta["shards"], meta["entries"]
    if not isinstance(shards, list) or not isinstance(entries, list):
        fail("shards and entries must be lists")
    for k, sh in enumerate(shards):
        if not (isinstance(sh, dict) and isinstance(sh.get("file"), str) and _SHARD_NAME.fullmatch(sh["file"])
                and isinstance(sh.get("sha256"), str) and re.fullmatch(r"[0-9a-f]{64}", sh["sha256"])
                and _is_int(sh.get("entries")) and sh["entries"] >= 1):
            fail(f"shard {k} must be {{file: shard-KKKKK.npz, sha256: 64 hex digits, entries: n >= 1}}, got {sh!r}")
    if len({sh["file"] for sh in shards}) != len(shards):
        fail("two shards name the same file")
    held = sum(sh["entries"] for sh in shards)
    if len(entries) != held:  # before the list below: a forged count (10^30) is refused, not allocated
        fail(f"{len(entries)} entries, but the shards hold {held}")
    expect = [(k, i) for k, sh in enumerate(shards) for i in range(sh["entries"])]
    for n, (e, (k, i)) in enumerate(zip(entries, expect)):
        if not (isinstance(e, dict) and isinstance(e.get("source"), str) and isinstance(e.get("pose"), list)
                and len(e["pose"]) == 3 and all(_is_num(v) for v in e["pose"])):
            fail(f"entry {n} must be {{source, pose: [x, y, theta], shard, index}}, got {e!r}")
        if e.get("shard") != k or e.get("index") != i:
            fail(f"entry {n} must be shard {k} index {i} (entries in shard order), got shard {e.get('shard')!r} "
                 f"index {e.get('index')!r}")
    return MapDataset(root, meta, system, horizon, meta["method"], np.asarray(meta["actions"], dtype=np.float64),
                      float(radius), (int(shape[0]), int(shape[1])), float(res), (float(origin[0]), float(origin[1])),
                      meta["split"], int(meta["seed"]), entries, shards)


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_num(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _close(a: Any, b: Any) -> bool:
    try:
        x, y = np.asarray(a), np.asarray(b)
        if x.shape != y.shape or x.dtype.kind not in "biuf" or y.dtype.kind not in "biuf":
            return False
        return bool(np.array_equal(x, y) if y.dtype == bool else np.allclose(x, y, rtol=0, atol=1e-6))
    except (TypeError, ValueError):
        return False


def _check_sha(ds: MapDataset, k: int) -> Path:
    path = ds.root / ds.shards[k]["file"]
    if not path.is_file():
        what = f"{file_kind(os.stat(path).st_mode)}, not a regular file" if path.exists() else "missing"
        raise MapDatasetError(f"{path}: shard {k} is {what}")
    if file_sha256(path) != ds.shards[k]["sha256"]:
        raise MapDatasetError(f"{path}: sha256 does not match dataset.json (a changed, truncated or foreign shard)")
    return path


def _read_shard(ds: MapDataset, k: int) -> MapShard:
    path = _check_sha(ds, k)

    def fail(msg: str) -> None:
        raise MapDatasetError(f"{path}: {msg}")

    M, (H, W), T = ds.shards[k]["entries"], ds.patch_shape, ds.horizon
    d, A = len(ds.meta["grid"]["cell_size"]), len(ds.actions)
    try:  # shapes and dtypes from the .npy headers first: nothing is allocated for a member that does not fit
        heads = member_headers(path)
        keys = set(heads) - {DIGEST_KEY}
        if sorted(keys) != sorted(SHARD_KEYS):
            fail(f"must hold exactly the keys {', '.join(SHARD_KEYS)} (and {DIGEST_KEY}), has {', '.join(sorted(heads))}")
        for key, dtype in _DTYPES.items():
            if heads[key][1] != dtype:
                fail(f"{key} must be {np.dtype(dtype)}, got {heads[key][1]}")
        shapes = {"patches": (M, H, W), "poses": (M, 3), "entry_offsets": (M + 1,), "level_offsets": (M, T + 2)}
        _check_shapes(heads, shapes, fail)
        eo = read_npz(path, keys=["entry_offsets"], expect={"entry_offsets": ((M + 1,), np.int64)})["entry_offsets"]
        R = int(eo[-1])
        shapes.update({"cells": (R, d), "action_probs": (R, A), "cell_probs": (R,)})
        _check_shapes(heads, shapes, fail)
        want = list(SHARD_KEYS) + ([DIGEST_KEY] if DIGEST_KEY in heads else [])
        arrays = read_npz(path, keys=want, expect={**{key: (shape, _DTYPES[key]) for key, shape in shapes.items()},
                                                    DIGEST_KEY: ((), None)})
    except NpzError as exc:
        fail(f"not a readable .npz shard ({exc})")
    stored = arrays.pop(DIGEST_KEY, None)
    if stored is not None and stored.dtype.kind != "U":
        fail(f"{DIGEST_KEY} must be a string, got {stored.dtype}")
    try:  # a damaged shard first; the note of an old shard (no digest) only once it is otherwise valid
        if stored is not None:
            check_digest(arrays, str(stored[()]), str(path))
    except DigestError as exc:
        raise MapDatasetError(str(exc)) from None
    _check_shard(arrays, ds, k, fail)
    if stored is None:
        check_digest(arrays, None, str(path))
    return MapShard(path, arrays)


def _check_shapes(heads: dict[str, tuple[tuple[int, ...], np.dtype]], shapes: dict[str, tuple[int, ...]],
                  fail) -> None:
    for key, shape in shapes.items():
        if heads[key][0] != shape:
            fail(f"{key} must have shape {list(shape)} (from dataset.json's system, patch and entries), got "
                 f"{list(heads[key][0])}")


def _check_shard(a: dict[str, np.ndarray], ds: MapDataset, k: int, fail) -> None:
    """Poses, offsets, cells, patches and probabilities of shard ``k`` (dtypes and shapes are checked) against
    ``ds``'s metadata, then its tables against the builders' guarantees (:func:`_check_tables`)."""
    M = ds.shards[k]["entries"]
    if a["patches"].size and a["patches"].max() > 1:
        fail("patches must hold only 0 and 1")
    full = np.flatnonzero(a["patches"].reshape(M, -1).min(axis=1) == 1) if a["patches"].size else []
    if len(full):
        fail(f"the patch of entry {int(full[0])} is occupied everywhere (no free cell for its start)")
    first = ds._first[k]
    poses = np.asarray([e["pose"] for e in ds.entries[first:first + M]], dtype=np.float64)
    if not np.array_equal(a["poses"], poses):
        fail("poses do not match dataset.json's entries")
    eo, lo = a["entry_offsets"], a["level_offsets"]
    if eo[0] != 0 or np.any(np.diff(eo) <= 0):
        fail("entry_offsets must start at 0 and increase strictly")
    if np.any(lo[:, 0] != 0) or np.any(np.diff(lo, axis=1) <= 0) or not np.array_equal(lo[:, -1], np.diff(eo)) \
            or np.any(lo[:, 1] != 1):
        fail("level_offsets must rise strictly from 0 (level 0: one start cell) to each entry's row count")
    R = int(eo[-1])
    for dim in np.flatnonzero(ds.meta["grid"]["periodic"]):
        K = round(2 * math.pi / ds.meta["grid"]["cell_size"][dim])
        if R and (a["cells"][:, dim].min() < 0 or a["cells"][:, dim].max() >= K):
            fail(f"cells of angle dimension {dim} must lie in [0, {K})")
    probs, cp = a["action_probs"].astype(np.float64), a["cell_probs"].astype(np.float64)
    if not (np.all(np.isfinite(probs)) and np.all(probs >= 0) and np.all(np.isfinite(cp)) and np.all(cp >= 0)):
        fail("action_probs and cell_probs must be finite and non-negative")
    if np.any(np.abs(probs.sum(axis=1) - 1) > _ROW_TOL):
        fail(f"action_probs rows must sum to 1 (within {_ROW_TOL}, float16)")
    starts = (eo[:-1, None] + lo[:, :-1]).reshape(-1)  # every level's first row, entries in order
    if np.any(np.abs(np.add.reduceat(cp, starts) - 1) > _LEVEL_TOL):
        fail(f"cell_probs must sum to 1 in every level of every entry (within {_LEVEL_TOL})")
    _check_cells(a["cells"], eo, starts, ds, fail)
    _check_tables(a, ds, k, fail)


def _check_cells(cells: np.ndarray, eo: np.ndarray, starts: np.ndarray, ds: MapDataset, fail) -> None:
    """Level 0 of every entry is the origin cell (the farm builds from the zero state of the robot's frame); the
    cells of every level are distinct and in ascending row-major order (as the builders write them, and as the
    rows are matched to cells by sorted keys)."""
    origin = Grid.of(ds.system).cells(torch.zeros(1, len(ds.meta["grid"]["cell_size"]), dtype=torch.float64))[0]
    bad = np.flatnonzero(np.any(cells[eo[:-1]] != origin.numpy(), axis=1))
    if len(bad):
        fail(f"level 0 of entry {int(bad[0])} must be the origin cell {origin.tolist()} (the robot's start), got "
             f"{cells[eo[int(bad[0])]].tolist()}")
    if len(cells) < 2:
        return
    diff = cells[1:].astype(np.int64) - cells[:-1]  # [R-1, d]: the first non-zero entry of each row gives the order
    nonzero = diff != 0
    sign = np.where(nonzero.any(axis=1), np.sign(diff[np.arange(len(diff)), np.argmax(nonzero, axis=1)]), 0)
    same_level = np.ones(len(diff), dtype=bool)
    same_level[starts[1:] - 1] = False  # the pair (last row of a level, first row of the next)
    bad = np.flatnonzero(same_level & (sign <= 0))
    if len(bad):
        row = int(bad[0]) + 1
        what = "repeats" if sign[bad[0]] == 0 else "comes before"
        fail(f"the cells of a level must be distinct and ascending (as the builders write them; rows permuted or "
             f"duplicated?): row {row} {cells[row].tolist()} {what} row {row - 1} {cells[row - 1].tolist()}")


def _check_tables(a: dict[str, np.ndarray], ds: MapDataset, k: int, fail) -> None:
    """The tables of every entry of a shard against its patch and the system's dynamics (module docstring).

    Vectorized over the shard's entries: one pass per level (its cells of every entry stepped at once, told apart
    by compound keys ``entry * box + cell key``), so the cost is the stepping itself, not Python."""
    eo, lo, T, A = a["entry_offsets"], a["level_offsets"], ds.horizon, len(ds.actions)
    M = len(eo) - 1
    entry = np.repeat(np.arange(M), np.diff(eo))  # [R]
    level = np.repeat(np.tile(np.arange(T + 1), M), np.diff(lo, axis=1).ravel())  # [R]
    probs = a["action_probs"].astype(np.float64)
    probs /= probs.sum(axis=1, keepdims=True)
    cp = a["cell_probs"].astype(np.float64)
    last = np.flatnonzero(level == T)
    bad = last[np.any(np.abs(probs[last] - 1.0 / A) > _ROW_TOL / A, axis=1)]
    if len(bad):
        fail(f"entry {int(entry[bad[0]])}: the rows of the last level (the horizon) must be uniform (1/{A}), as the "
             "builders write them")
    cells = torch.from_numpy(a["cells"].astype(np.int64))  # [R, d]
    ent = torch.from_numpy(entry)
    blocked = _inflated(a["patches"], ds, fail)  # [M, H, W]
    hit = np.flatnonzero(_blocked(ds, blocked, cells, ent).numpy())
    if len(hit):
        r = int(hit[0])
        fail(f"entry {int(entry[r])}: the cell {cells[r].tolist()} (level {int(level[r])}) lies within radius "
             f"{ds.radius:g} m of an obstacle of its patch: the patch, radius or resolution do not match the table (a "
             "transposed patch, another radius or resolution)")
    order = np.argsort(level, kind="stable")  # rows by level, entries in order within each
    bounds = np.concatenate(([0], np.cumsum(np.bincount(level, minlength=T + 1))))
    rows = [torch.from_numpy(order[bounds[t]:bounds[t + 1]]) for t in range(T + 1)]
    left = None  # the free successors of level t-1 left out of level t: (cells [n, d], entries [n])
    for t in range(T):
        now, nxt = rows[t], rows[t + 1]

        def where(e: int, lvl: int, msg: str) -> None:
            fail(f"entry {e}, level {lvl}: {msg}")

        if ds.method == "coverage":
            _check_coverage_reach(ds, cells[now], ent[now], cells[nxt], ent[nxt], t + 1, where)
            continue
        deep = ds.verify_all
        if not deep:  # the cheap check: every cell is in the blind level set (what any map's table may hold)
            miss = _blind_levels(ds)[t + 1].lookup(cells[nxt]) < 0
            if bool(miss.any()):
                e, mine, m = _first_entry(ent[nxt], miss)
                where(e, t + 1, f"{int(mine.sum())} of its {m} cells (e.g. {cells[nxt][mine][0].tolist()}) are not "
                                f"reached from the origin in {t + 1} step(s) of the system: the speed, the actions or "
                                "the cells do not match")
            continue
        target = _Level(cells[nxt], ent[nxt], M)
        succ, prop = [], np.zeros(len(nxt))
        w = cp[now.numpy(), None] * probs[now.numpy()]  # [n, A]: the mass each (cell, action) sends on
        for i, j, reached in _stepped(ds, cells[now], lattice=True):  # [c, P, A, d], point 0 the centre
            succ.append(reached[:, 0])
            # the builder's transitions: every lattice point, kept where it lands in level t+1
            at = target.lookup(ent[now][i:j], reached)  # [c, P, A]
            ok = at >= 0
            kept = ok.sum(dim=1, keepdim=True).numpy()  # [c, 1, A] kept points per (cell, action)
            share = np.where(kept > 0, w[i:j, None, :] / np.maximum(kept, 1), 0.0)  # [c, 1, A]
            prop += np.bincount(at[ok].numpy(), np.broadcast_to(share, ok.shape)[ok.numpy()], len(nxt))
        left = _check_builder_reach(ds, torch.cat(succ), ent[now], cells[nxt], ent[nxt], M, blocked, left, target,
                                    t + 1, t + 1 == T, where)
        _check_propagation(prop, cp[nxt.numpy()], entry[nxt.numpy()], M, t + 1, where)


def _blind_levels(ds: MapDataset) -> list[CellSet]:
    """The blind level sets from the origin cell (every cell a ``maxflow`` table may hold at each level, before any
    map pruned it), computed once per data set."""
    if ds._blind is None:
        grid = Grid.of(ds.system)
        cells = grid.cells(torch.zeros(1, grid.dim, dtype=torch.float64))
        levels = [CellSet.build(cells)]
        for _ in range(ds.horizon):
            cells = torch.unique(torch.cat([pts.reshape(-1, grid.dim) for _, _, pts in _stepped(ds, cells, False)]),
                                 dim=0)
            levels.append(CellSet.build(cells))
        ds._blind = levels
    return ds._blind


class _Level:
    """Cells of one level of several entries, looked up by (entry, cell) through compound keys."""

    def __init__(self, cells: torch.Tensor, entry: torch.Tensor, M: int, distinct: bool = False) -> None:
        self.keys = CellKeys.covering(cells)
        self.size = int(torch.prod(self.keys.span))
        if self.size * max(M, 1) >= 2**62:  # physical successors: not expected
            raise MapDatasetError(f"the cells of a level spread over {self.keys.span.tolist()} cells: too far to key")
        if distinct:  # a set of the distinct (entry, cell) pairs: rows are positions in ``sorted``
            self.sorted = torch.unique(self.key(entry, cells))
            self.rows = torch.arange(len(self.sorted))
        else:
            self.sorted, self.rows = torch.sort(self.key(entry, cells))

    def key(self, entry: torch.Tensor, cells: torch.Tensor) -> torch.Tensor:
        """``entry [n]``, ``cells [n, ..., d]`` -> compound keys ``[n, ...]`` (-1 outside the key box)."""
        packed = self.keys.pack(cells)
        e = entry.view((-1,) + (1,) * (packed.ndim - 1))
        return torch.where(packed >= 0, e * self.size + packed, torch.full_like(packed, -1))

    def lookup(self, entry: torch.Tensor, cells: torch.Tensor) -> torch.Tensor:
        """Row of each (entry, cell) in the cells given ``[n, ...]`` (-1 where it is not there)."""
        q = self.key(entry, cells)
        pos = torch.searchsorted(self.sorted, q.contiguous()).clamp_(max=len(self.sorted) - 1)
        return torch.where(self.sorted[pos] == q, self.rows[pos], -1)

    def unpack(self, keys: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Compound keys ``[n]`` -> (cells ``[n, d]``, entries ``[n]``)."""
        e = torch.div(keys, self.size, rounding_mode="floor")
        return self.keys.unpack(keys - e * self.size), e


_CHUNK_PAIRS = 1 << 21  # (point, action) pairs stepped at once, as the builder (bounds memory on big levels)


def _stepped(ds: MapDataset, cells: torch.Tensor, lattice: bool) -> Iterator[tuple[int, int, torch.Tensor]]:
    """The cells reached from the centres (``lattice``: the builder's 3^d sample points, the centre first) of
    ``cells [n, d]`` under every action, as the builder assigns them (ties by direction): chunks ``(i, j,
    reached [j - i, P, A, d])``."""
    grid = Grid.of(ds.system)
    actions = ds.system.action_set(dtype=torch.float64)  # [A, q]
    A, q, d = actions.shape[0], actions.shape[1], grid.dim
    offsets = cell_sample_offsets(grid, PointMode.CENTERS, 1, 1, None)[0] if lattice \
        else torch.zeros(1, d, dtype=torch.float64)  # [P, d]
    P = len(offsets)
    centres = grid.centers(cells, torch.float64)  # [n, d]
    chunk = max(1, _CHUNK_PAIRS // (P * A))
    for i in range(0, len(cells), chunk):
        src = cells[i:i + chunk]
        c = len(src)
        pts = grid.wrap(centres[i:i + chunk].unsqueeze(1) + offsets)  # [c, P, d]
        x = pts.unsqueeze(2).expand(c, P, A, d).reshape(-1, d)
        u = actions.expand(c * P, A, q).reshape(-1, q)
        yield i, i + c, grid.cells_from(src, ds.system.step(x, u).reshape(c, P * A, d)).reshape(c, P, A, d)


def _inflated(patches: np.ndarray, ds: MapDataset, fail) -> torch.Tensor:
    """``[M, H, W]`` bool: each entry's patch inflated by the data set's radius (the farm's free-cell test)."""
    try:
        check_map_system(ds.system)
        return torch.from_numpy(np.stack([LocalMap(p, ds.patch_origin, ds.patch_resolution).inflated(ds.radius)
                                          for p in patches]))  # one distance transform per entry
    except MapError as exc:
        fail(f"the patches cannot be used with the system: {exc}")


def _blocked(ds: MapDataset, blocked: torch.Tensor, cells: torch.Tensor, entry: torch.Tensor) -> torch.Tensor:
    """``cells [n, d]`` of the entries ``entry [n]`` -> bool ``[n]``: the centre lies in its entry's inflated
    obstacles (:meth:`precompute.levels.safe_map.SafeCells.blocked_xy`, one patch per entry)."""
    _, H, W = blocked.shape
    xy = Grid.of(ds.system).centers(cells, torch.float64)[:, :2]
    fx = (xy[:, 0] - ds.patch_origin[0]) / ds.patch_resolution
    fy = (xy[:, 1] - ds.patch_origin[1]) / ds.patch_resolution
    inside = (fx >= 0) & (fx < W) & (fy >= 0) & (fy < H)
    j = torch.where(inside, fx, torch.zeros_like(fx)).floor().long().clamp(0, W - 1)
    i = torch.where(inside, fy, torch.zeros_like(fy)).floor().long().clamp(0, H - 1)
    return blocked.reshape(-1)[(entry * H + i) * W + j] & inside


def _first_entry(entry: torch.Tensor, bad: torch.Tensor) -> tuple[int, torch.Tensor, int]:
    """The first entry with a ``bad`` row: (entry, its bad rows as a mask, its row count)."""
    e = int(entry[bad][0])
    mine = entry == e
    return e, bad & mine, int(mine.sum())


def _check_builder_reach(ds: MapDataset, succ: torch.Tensor, ent_now: torch.Tensor, nxt: torch.Tensor,
                         ent_nxt: torch.Tensor, M: int, blocked: torch.Tensor,
                         left: tuple[torch.Tensor, torch.Tensor] | None, target: _Level, lvl: int, horizon: bool,
                         where) -> tuple[torch.Tensor, torch.Tensor]:
    """A ``maxflow`` step into level ``lvl``: each of its cells (``nxt [m, d]``) is a successor of a centre of the
    level before (``succ [n, A, d]``, the builder's level set before its pruning); the free successors ``left`` left
    out of the level before are dead ends (none of their transitions lands in this level, ``target``); at the
    horizon no free successor is left out. Returns the free successors left out of this level (checked next)."""
    reached = _Level(succ.reshape(-1, succ.shape[-1]), ent_now.repeat_interleave(succ.shape[1]), M, distinct=True)
    uniq = reached.sorted  # [u] compound keys of the distinct successors
    want = reached.key(ent_nxt, nxt)
    pos = torch.searchsorted(uniq, want).clamp_(max=len(uniq) - 1)
    miss = uniq[pos] != want
    if bool(miss.any()):
        e, mine, m = _first_entry(ent_nxt, miss)
        where(e, lvl, f"{int(mine.sum())} of its {m} cells (e.g. {nxt[mine][0].tolist()}) are not a cell reached from "
                      "the level before in one step of the system: the speed, the actions or the cells do not match")
    if left is not None and len(left[0]):
        live = torch.zeros(len(left[0]), dtype=torch.bool)
        for i, j, pts in _stepped(ds, left[0], lattice=True):
            live[i:j] = (target.lookup(left[1][i:j], pts) >= 0).flatten(1).any(dim=1)
        if bool(live.any()):
            e, mine, _ = _first_entry(left[1], live)
            _left_out(where, e, lvl - 1, int(mine.sum()), left[0][mine][0], "not dead ends")
    kept = torch.zeros(len(uniq), dtype=torch.bool)
    kept[pos] = True
    out, out_ent = reached.unpack(uniq[~kept])
    free = ~_blocked(ds, blocked, out, out_ent)
    out, out_ent = out[free], out_ent[free]
    if horizon and len(out):
        e, mine, _ = _first_entry(out_ent, torch.ones(len(out), dtype=torch.bool))
        _left_out(where, e, lvl, int(mine.sum()), out[mine][0], "at the horizon")
    return out, out_ent


def _left_out(where, e: int, lvl: int, n: int, cell: torch.Tensor, why: str) -> None:
    where(e, lvl, f"{n} free successor(s) of the level before are left out (e.g. {cell.tolist()}) though they are "
                  f"{why}: the patch, radius or resolution do not match the table (a transposed patch, another radius "
                  "or resolution)")


def _check_coverage_reach(ds: MapDataset, now: torch.Tensor, ent_now: torch.Tensor, nxt: torch.Tensor,
                          ent_nxt: torch.Tensor, lvl: int, where) -> None:
    """A ``coverage`` step into level ``lvl`` (states anywhere in a cell): each of its cells ``nxt [m, d]`` lies within
    one cell of a successor of a lattice point of a cell of the level before (``now [n, d]``)."""
    grid = Grid.of(ds.system)
    found = torch.cat([pts.flatten(1, 2) for _, _, pts in _stepped(ds, now, lattice=True)])  # [n, P A, d]
    reached = _Level(found.reshape(-1, grid.dim), ent_now.repeat_interleave(found.shape[1]), int(ent_now.max()) + 1,
                     distinct=True)
    around = torch.cartesian_prod(*[torch.tensor([-1, 0, 1])] * grid.dim).reshape(-1, grid.dim)  # [3^d, d]
    near = nxt.unsqueeze(1) + around  # [m, 3^d, d]
    for dim, K in enumerate(grid.num_angle_cells):
        if K:
            near[..., dim] %= K
    miss = ~(reached.lookup(ent_nxt, near) >= 0).any(dim=1)
    if bool(miss.any()):
        e, mine, m = _first_entry(ent_nxt, miss)
        where(e, lvl, f"{int(mine.sum())} of its {m} cells (e.g. {nxt[mine][0].tolist()}) are not within one cell of "
                      "a state reached from the level before in one step of the system: the speed, the actions or the "
                      "cells do not match")


def _check_propagation(prop: np.ndarray, cp_next: np.ndarray, entry: np.ndarray, M: int, lvl: int, where) -> None:
    """A ``maxflow`` level's ``cell_probs`` (``cp_next [m]``, entries ``entry [m]``) is the level before's propagated
    through its rows and the builder's transitions (``prop [m]``, unnormalized: the mass into obstacles is gone)."""
    total = np.bincount(entry, prop, M)
    empty = np.flatnonzero(~(total[np.unique(entry)] > 0))
    if len(empty):
        where(int(np.unique(entry)[empty[0]]), lvl, "no probability mass reaches it through the action_probs of the "
                                                     "level before")
    err = np.bincount(entry, np.abs(prop / total[entry] - cp_next), M)
    bad = np.flatnonzero(err > _PROPAGATION_TOL)
    if len(bad):
        where(int(bad[0]), lvl, f"its cell_probs are not the level before's propagated through its action_probs (L1 "
                                f"distance {err[bad[0]]:.3g} > {_PROPAGATION_TOL}): action rows permuted or changed")
