"""The BARN maps (Benchmark Autonomous Robot Navigation) as data: load, validate, convert from Gazebo worlds.

Shapes used in this module: K maps, M cylinder rows (all maps), P reference-path points (all maps).

The shipped file ``precompute/worlds/data/barn_train.npz`` (see ``precompute/worlds/data/README.md``) holds 150 of the 300 BARN worlds
(ids 0, 2, ..., 298). Its keys:

* ``map_ids`` int ``[K]``, unique;
* ``centers`` float32 ``[M, 2]``: (x, y) of every unit cylinder (m); map k is ``centers[offsets[k]:offsets[k+1]]``;
* ``offsets`` int ``[K + 1]``: 0, non-decreasing, ending at M;
* ``radius`` float32 scalar: every cylinder's radius (0.075 m);
* ``paths`` float32 ``[P, 2]`` / ``path_offsets`` int ``[K + 1]``: the dataset's A* reference path of each
  map, in the dataset's grid coordinates (cells, not metres);
* ``start`` float32 ``[3]`` (x, y, heading; m, rad) and ``goal`` float32 ``[2]`` (x, y; m), shared by all maps.

The cylinders include the walls: every map has a full row at y = 0.075 and full columns at x = -0.075 and
x = -4.425 (cylinders 0.15 m apart, touching), so the field is closed on three sides and open towards the goal.

The shipped file lists every cylinder twice (its converter read both the world's model definitions and its
``<state>`` section); :func:`load_barn` drops exact duplicate rows, so :attr:`BarnMap.centers` holds each
cylinder once. :func:`convert_worlds` reads the model definitions only.

The shipped ``start`` / ``goal`` are (-2, 3, 1.57) / (-2, 13); the BARN Challenge's ``run.py`` uses
``INIT_POSITION = [-2.25, 3, 1.57]`` and the goal 10 m ahead, (-2.25, 13) (:data:`CHALLENGE_START`,
:data:`CHALLENGE_GOAL`).

The format's checks are :mod:`precompute.worlds.barn_format`, the Gazebo converter :mod:`precompute.worlds.barn_worlds`; their names are
importable from here too.
"""

from __future__ import annotations

import importlib.resources
import math
import os
import zipfile
import zlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cuniform_torch.common.fileio import check_regular, write_npz
from cuniform_torch.envs import Circle, Environment
from precompute.worlds.barn_format import KEYS, BarnFormatError, format_error, validate_barn
from precompute.worlds.barn_worlds import FILE_GOAL, FILE_START, convert_worlds

__all__ = [
    "BarnMap", "BarnFormatError", "load_barn", "convert_worlds", "write_barn", "validate_barn",
    "default_path", "FILE_START", "FILE_GOAL", "CHALLENGE_START", "CHALLENGE_GOAL",
]

CHALLENGE_START = (-2.25, 3.0, 1.57)
"""the BARN Challenge's ``INIT_POSITION`` (its ``run.py``)"""
CHALLENGE_GOAL = (-2.25, 13.0)
"""the BARN Challenge's goal: 10 m ahead of its start"""


def default_path() -> Path:
    """The shipped ``precompute/worlds/data/barn_train.npz``."""
    return Path(str(importlib.resources.files("precompute.worlds") / "data" / "barn_train.npz"))


@dataclass(frozen=True, eq=False)
class BarnMap:
    """One BARN world: unit cylinders (walls included), the start, the goal and the dataset's reference path."""

    map_id: int
    """the BARN world id (``world_<id>.world``)"""
    centers: np.ndarray
    """float32 ``[M, 2]``: (x, y) of each cylinder (m), each once"""
    radius: float
    """every cylinder's radius (m)"""
    start: tuple[float, float, float]
    """(x, y, heading) in m and rad"""
    goal: tuple[float, float]
    """(x, y) in m"""
    path: np.ndarray
    """float32 ``[P, 2]``: the dataset's A* reference path, in its grid coordinates (cells, not metres)"""

    def environment(self, robot_radius: float) -> Environment:
        """An :class:`Environment` of the cylinders as :class:`Circle` s of radius ``radius + robot_radius``,
        so that a point robot (the robot's centre) collides exactly when the disc robot would. No bounds: the
        walls are cylinders too."""
        if isinstance(robot_radius, bool) or not isinstance(robot_radius, (int, float)) \
                or not math.isfinite(robot_radius) or robot_radius < 0:
            raise ValueError(f"BarnMap.environment: robot_radius must be a finite number >= 0, got {robot_radius!r}")
        r = self.radius + float(robot_radius)
        return Environment([Circle((float(x), float(y)), r) for x, y in self.centers.tolist()])


# ------------------------------------------------------------------------------------------------ loading

def _read_npz(path: Path) -> dict[str, np.ndarray]:
    source = str(path)
    try:
        check_regular(path, "the BARN file")  # a FIFO would block np.load; a device never ends
        data = np.load(path, allow_pickle=False)
        if not isinstance(data, np.lib.npyio.NpzFile):
            raise format_error(source, None, "not an .npz archive (a single .npy array)")
        with data:
            out = {}
            for key in data.files:
                try:
                    out[key] = data[key]
                except (ValueError, OSError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
                    raise format_error(source, key, f"cannot be read ({type(exc).__name__}: {exc})") from None
            return out
    except FileNotFoundError:
        raise
    except BarnFormatError:
        raise
    except (ValueError, OSError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
        raise format_error(source, None, f"not a readable .npz archive ({type(exc).__name__}: {exc})") from None


def _unique_rows(rows: np.ndarray) -> np.ndarray:
    """``rows [n, 2]`` without exact duplicate rows, first occurrences in their order."""
    if rows.shape[0] == 0:
        return rows
    _, first = np.unique(rows, axis=0, return_index=True)
    return rows[np.sort(first)]


def load_barn(path: str | os.PathLike | None = None) -> list[BarnMap]:
    """The maps of a BARN map file (default: the shipped ``precompute/worlds/data/barn_train.npz``), in file order.

    Raises :class:`BarnFormatError` (a ``ValueError``) naming the file and the key for any format problem,
    ``FileNotFoundError`` for a missing file. Exact duplicate cylinders of a map are dropped (see the module
    docstring).
    """
    p = default_path() if path is None else Path(path)
    arrays = _read_npz(p)
    validate_barn(arrays, str(p))
    off, poff = arrays["offsets"], arrays["path_offsets"]
    centers = arrays["centers"].astype(np.float32, copy=False)
    paths = arrays["paths"].astype(np.float32, copy=False)
    radius = float(arrays["radius"])
    start = tuple(float(v) for v in arrays["start"])
    goal = tuple(float(v) for v in arrays["goal"])
    maps = []
    for k, map_id in enumerate(arrays["map_ids"].tolist()):
        maps.append(BarnMap(
            map_id=int(map_id),
            centers=_unique_rows(centers[off[k]:off[k + 1]]).copy(),  # [M_k, 2]
            radius=radius,
            start=start,  # type: ignore[arg-type]
            goal=goal,  # type: ignore[arg-type]
            path=paths[poff[k]:poff[k + 1]].copy(),  # [P_k, 2]
        ))
    return maps


def pack_maps(maps: Sequence[BarnMap]) -> dict[str, np.ndarray]:
    """Maps -> arrays in the file format (all maps must share radius, start and goal)."""
    if not maps:
        raise ValueError("pack_maps: no maps")
    first = maps[0]
    for m in maps:
        if (m.radius, tuple(m.start), tuple(m.goal)) != (first.radius, tuple(first.start), tuple(first.goal)):
            raise ValueError(f"pack_maps: map {m.map_id} has another radius, start or goal than map {first.map_id}")
    counts = [len(m.centers) for m in maps]
    pcounts = [len(m.path) for m in maps]
    return {
        "map_ids": np.array([m.map_id for m in maps], dtype=np.int64),
        "centers": np.concatenate([np.asarray(m.centers, np.float32).reshape(-1, 2) for m in maps]),
        "offsets": np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
        "radius": np.asarray(first.radius, dtype=np.float32),  # [] (0-d, as np.load gives it back)
        "paths": np.concatenate([np.asarray(m.path, np.float32).reshape(-1, 2) for m in maps]),
        "path_offsets": np.concatenate([[0], np.cumsum(pcounts)]).astype(np.int64),
        "start": np.array(first.start, dtype=np.float32),
        "goal": np.array(first.goal, dtype=np.float32),
    }


def write_barn(path: str | os.PathLike, maps: Mapping[str, np.ndarray] | Sequence[BarnMap]) -> None:
    """Write maps (arrays in the file format, or :class:`BarnMap` s) atomically; validated first, so a bad
    input raises :class:`BarnFormatError` and leaves ``path`` untouched."""
    arrays = dict(maps) if isinstance(maps, Mapping) else pack_maps(list(maps))
    validate_barn(arrays, str(path))
    write_npz(path, {key: np.asarray(arrays[key]) for key in KEYS})
