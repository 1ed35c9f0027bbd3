"""The training data of a map-conditioned policy: map-table data sets (``cuniform-map-dataset/1``) as tensors.

Shapes: M entries (maps), H x W patch cells, R rows (cells of every level of every entry), d state dimensions,
A actions, T horizon.

:func:`load_map_data` reads one or more data set folders and pools their entries; they must share the system,
the grid, the actions and the patch spec. A row is one cell of one level of one entry's safe table: its centre
(the state), its level t, its entry (the map) and its target ``p(u | cell, t)`` (float16 in the file,
renormalised here).
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
from torch import Tensor

from cuniform_torch.grid import Grid
from cuniform_torch.map_encoder import PatchSpec
from cuniform_torch.systems import System, system_from_json

__all__ = ["MapData", "MapDataError", "load_map_data", "dataset_digest", "DATASET_FORMAT"]

DATASET_FORMAT = "cuniform-map-dataset/1"


class MapDataError(ValueError):
    """Data sets that cannot be read or trained on together (reported as ``error: ...``)."""


@dataclass
class MapData:
    """Pooled entries of one or more data sets (module docstring)."""

    system: System
    system_json: str
    horizon: int
    actions: Tensor
    """``[A, q]`` float32"""
    spec: PatchSpec
    patches: Tensor
    """``uint8 [M, H, W]``"""
    centres: Tensor
    """``[R, d]`` float64 cell centres (start frame)"""
    probs: Tensor
    """``[R, A]`` float32 targets, rows summing to 1"""
    entry: Tensor
    """``[R]`` int64 entry of each row"""
    level: Tensor
    """``[R]`` int64 level of each row"""
    sources: list[dict[str, str]]
    """``{"path", "sha256", "entries"}`` per data set"""
    nbytes: int
    """bytes of the data set files read"""

    @property
    def num_entries(self) -> int:
        return int(self.patches.shape[0])

    @property
    def group(self) -> Tensor:
        """``[R]`` the (entry, level) group of each row: its weight is 1 / (rows of the group) / (groups)."""
        return self.entry * (self.horizon + 1) + self.level


def dataset_digest(folder: str | os.PathLike) -> str:
    """sha256 of a data set's ``dataset.json`` (which holds every shard's sha256)."""
    return hashlib.sha256((Path(folder) / "dataset.json").read_bytes()).hexdigest()


def load_map_data(folders: Sequence[str | os.PathLike]) -> MapData:
    """Read and pool the data sets in ``folders``; :class:`MapDataError` naming the folder and the problem."""
    if not folders:
        raise MapDataError("no data set given")
    parts = [_read_folder(Path(f)) for f in folders]
    head = parts[0]
    for part in parts[1:]:
        for key in ("system", "grid", "patch", "actions", "horizon"):
            if part["meta"][key] != head["meta"][key]:
                raise MapDataError(f"{part['path']}: its {key} differs from {head['path']}'s; data sets trained "
                                   f"together must share system, grid, actions and patch")
    meta = head["meta"]
    system, horizon = system_from_json(meta["system"])
    grid = Grid.of(system)
    if [list(meta["grid"][k]) for k in ("cell_size", "cell_offset")] != [list(grid.cell_size), list(grid.offset)] \
            or list(meta["grid"]["periodic"]) != list(grid.periodic):
        raise MapDataError(f"{head['path']}: its grid {meta['grid']} is not the grid of its system {system.name}")
    actions = torch.tensor(meta["actions"], dtype=torch.float32)
    if actions.shape != system.action_set().shape or not torch.allclose(actions, system.action_set(), atol=1e-6):
        raise MapDataError(f"{head['path']}: its actions are not the actions of its system {system.name}")
    patches, cells, probs, entry, level, base = [], [], [], [], [], 0
    for part in parts:
        for shard in part["shards"]:
            m = shard["patches"].shape[0]
            rows = np.diff(shard["entry_offsets"])  # [m]
            counts = np.diff(shard["level_offsets"], axis=1).ravel()  # [m * (T+1)] rows per (entry, level)
            lev = np.repeat(np.tile(np.arange(horizon + 1), m), counts)
            patches.append(shard["patches"])
            cells.append(shard["cells"])
            probs.append(shard["action_probs"].astype(np.float32))
            entry.append(np.repeat(np.arange(base, base + m), rows))
            level.append(lev)
            base += m
    p = torch.from_numpy(np.concatenate(probs))
    p = p / p.sum(dim=1, keepdim=True)
    return MapData(system, meta["system"], horizon, actions, PatchSpec.from_dict(meta["patch"]),
                   torch.from_numpy(np.concatenate(patches)),
                   grid.centers(torch.from_numpy(np.concatenate(cells).astype(np.int64))), p,
                   torch.from_numpy(np.concatenate(entry)), torch.from_numpy(np.concatenate(level)),
                   [{"path": str(pt["path"]), "sha256": pt["sha256"], "entries": str(pt["entries"])} for pt in parts],
                   sum(pt["nbytes"] for pt in parts))


def _read_folder(folder: Path) -> dict:
    """One data set: its metadata and its shards' arrays, every field checked against the format."""
    index = folder / "dataset.json"
    if not index.is_file():
        raise MapDataError(f"{folder}: no dataset.json there (not a map-table data set)")
    raw = index.read_bytes()
    try:
        meta = json.loads(raw)
    except json.JSONDecodeError as exc:
        raise MapDataError(f"{index}: not JSON ({exc})") from None

    def fail(msg: str, where: Path = index) -> None:
        raise MapDataError(f"{where}: {msg}")

    if not isinstance(meta, dict) or meta.get("format") != DATASET_FORMAT:
        fail(f"format is {meta.get('format') if isinstance(meta, dict) else None!r}, expected {DATASET_FORMAT!r}")
    for key in ("system", "horizon", "method", "grid", "actions", "radius", "patch", "split", "seed", "entries",
                "shards"):
        if key not in meta:
            fail(f"missing key {key!r}")
    try:
        system, horizon = system_from_json(meta["system"])
        spec = PatchSpec.from_dict(meta["patch"])
    except ValueError as exc:
        fail(str(exc))
    if meta["horizon"] != horizon:
        fail(f"horizon {meta['horizon']} differs from the system JSON's {horizon}")
    T, d, A, (H, W) = horizon, len(system.periodic), len(meta["actions"]), spec.shape
    shards, total, nbytes = [], 0, len(raw)
    for k, info in enumerate(meta["shards"]):
        path = folder / str(info.get("file", ""))
        if not path.is_file() or path.parent != folder:
            fail(f"shard {k}: no file {info.get('file')!r} in the folder")
        data = path.read_bytes()
        nbytes += len(data)
        if hashlib.sha256(data).hexdigest() != info.get("sha256"):
            fail("sha256 differs from dataset.json's (a changed or truncated shard)", path)
        with np.load(path, allow_pickle=False) as npz:
            arrays = {key: npz[key] for key in npz.files}
        shards.append(_check_shard(arrays, path, info.get("entries"), T, d, A, H, W, fail))
        total += arrays["patches"].shape[0]
    if total != len(meta["entries"]):
        fail(f"the shards hold {total} entries but 'entries' lists {len(meta['entries'])}")
    return {"path": folder, "meta": meta, "shards": shards, "sha256": hashlib.sha256(raw).hexdigest(),
            "entries": total, "nbytes": nbytes}


_DTYPES = {"patches": np.uint8, "poses": np.float64, "entry_offsets": np.int64, "level_offsets": np.int64,
           "cells": np.int32, "action_probs": np.float16, "cell_probs": np.float32}


def _check_shard(a: dict, path: Path, entries: object, T: int, d: int, A: int, H: int, W: int, fail) -> dict:
    missing = sorted(set(_DTYPES) - set(a))
    if missing:
        fail(f"missing array(s) {', '.join(missing)}", path)
    for key, dtype in _DTYPES.items():
        if a[key].dtype != dtype:
            fail(f"{key} is {a[key].dtype}, expected {np.dtype(dtype)}", path)
    M = a["patches"].shape[0]
    R = a["cells"].shape[0]
    shapes = {"patches": (M, H, W), "poses": (M, 3), "entry_offsets": (M + 1,), "level_offsets": (M, T + 2),
              "cells": (R, d), "action_probs": (R, A), "cell_probs": (R,)}
    for key, shape in shapes.items():
        if a[key].shape != shape:
            fail(f"{key} has shape {list(a[key].shape)}, expected {list(shape)}", path)
    if entries != M:
        fail(f"holds {M} entries, dataset.json says {entries}", path)
    eo, lo = a["entry_offsets"], a["level_offsets"]
    if eo[0] != 0 or eo[-1] != R or (np.diff(eo) < 0).any():
        fail("entry_offsets must rise from 0 to the number of rows", path)
    if M and ((lo[:, 0] != 0).any() or (np.diff(lo, axis=1) < 0).any() or (lo[:, -1] != np.diff(eo)).any()):
        fail("level_offsets must rise from 0 to each entry's row count", path)
    if a["patches"].max(initial=0) > 1:
        fail("patches must hold 0 / 1", path)
    p = a["action_probs"].astype(np.float32)
    if not np.isfinite(p).all() or (p < 0).any() or (R and (p.sum(axis=1) <= 0).any()):
        fail("action_probs must be finite, non-negative, with a positive sum per row", path)
    if not np.isfinite(a["cell_probs"]).all() or (a["cell_probs"] < 0).any():
        fail("cell_probs must be finite and non-negative", path)
    return a
