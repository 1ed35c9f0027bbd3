"""The training data of a map-conditioned policy: map-table data sets (``cuniform-map-dataset/1``) as tensors.

Shapes: M entries (maps), H x W patch cells, R rows (cells of every level of every entry), d state dimensions,
A actions, T horizon.

:func:`load_map_data` reads one or more data set folders and pools their entries; they must share the system,
the grid, the actions and the patch spec. Each is read and validated by the map farm's reader
(:func:`precompute.maps.dataset.read_map_dataset`). A row is one cell of one level of one entry's safe table: its centre
(the state), its level t, its entry (the map) and its target ``p(u | cell, t)`` (float16 in the file,
renormalised here).
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from cuniform_torch.common.fileio import MAX_JSON_BYTES, read_capped_bytes, read_capped_text
from cuniform_torch.grid.cells import Grid
from cuniform_torch.maps.encoder import PatchSpec
from cuniform_torch.systems import System, system_from_json
from precompute.maps.dataset import DATASET_FORMAT, read_map_dataset

__all__ = ["MapData", "MapDataError", "load_map_data", "dataset_digest", "DATASET_FORMAT"]


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
    return hashlib.sha256(read_capped_bytes(Path(folder) / "dataset.json", MAX_JSON_BYTES, "the data-set manifest")).hexdigest()


def load_map_data(folders: Sequence[str | os.PathLike], deep_checks: bool = True) -> MapData:
    """Read and pool the data sets in ``folders``; :class:`MapDataError` naming the folder and the problem.
    ``deep_checks``: every table's propagation recomputed too (``verify_all`` of
    :func:`~precompute.maps.dataset.read_map_dataset`: permuted action rows refused); False trusts the rows."""
    if not folders:
        raise MapDataError("no data set given")
    _check_poolable([(Path(f), _raw_header(Path(f))) for f in folders])  # before any shard is read
    parts = [_read_folder(Path(f), deep_checks) for f in folders]
    head = parts[0]
    _check_poolable([(part["path"], part["meta"]) for part in parts])
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


_POOLED_KEYS = ("system", "grid", "patch", "actions", "horizon")


def _raw_header(folder: Path) -> dict | None:
    """``dataset.json`` as plain JSON, unchecked (None when it is not a readable object of a sane size: the reader
    then says what is wrong with it)."""
    path = folder / "dataset.json"
    try:
        head = json.loads(read_capped_text(path, MAX_JSON_BYTES, "the data-set manifest"))
    except (OSError, ValueError, RecursionError):
        return None
    return head if isinstance(head, dict) else None


def _check_poolable(heads: Sequence[tuple[Path, dict | None]]) -> None:
    """Data sets trained together share system, grid, actions, patch and horizon (a :class:`MapDataError` naming
    the first that differs); unreadable headers are skipped here (their reader refuses them)."""
    known = [(path, head) for path, head in heads if head is not None]
    for path, head in known[1:]:
        for key in _POOLED_KEYS:
            if head.get(key) != known[0][1].get(key):
                raise MapDataError(f"{path}: its {key} differs from {known[0][0]}'s; data sets trained together must "
                                   "share system, grid, actions and patch")


def _read_folder(folder: Path, deep_checks: bool) -> dict:
    """One data set, read and validated (every shard, sha256 first) by :func:`precompute.maps.dataset.read_map_dataset`."""
    ds = read_map_dataset(folder, load=True, verify_all=deep_checks)
    index = folder / "dataset.json"
    raw = read_capped_bytes(index, MAX_JSON_BYTES, "the data-set manifest")
    shards = [ds.shard(k).arrays for k in range(len(ds.shards))]
    nbytes = len(raw) + sum((folder / sh["file"]).stat().st_size for sh in ds.shards)
    return {"path": folder, "meta": ds.meta, "shards": shards, "sha256": hashlib.sha256(raw).hexdigest(),
            "entries": len(ds), "nbytes": nbytes}
