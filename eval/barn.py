"""The BARN maps (Benchmark Autonomous Robot Navigation) as data: load, validate, convert from Gazebo worlds.

Shapes used in this module: K maps, M cylinder rows (all maps), P reference-path points (all maps).

The shipped file ``eval/data/barn_train.npz`` (see ``eval/data/README.md``) holds 150 of the 300 BARN worlds
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
"""

from __future__ import annotations

import importlib.resources
import math
import os
import re
import zipfile
import zlib
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Mapping, Sequence

import numpy as np

from cuniform_torch.envs import Circle, Environment
from cuniform_torch.fileio import write_npz

__all__ = [
    "BarnMap", "BarnFormatError", "load_barn", "convert_worlds", "write_barn", "validate_barn",
    "default_path", "FILE_START", "FILE_GOAL", "CHALLENGE_START", "CHALLENGE_GOAL",
]

FILE_START = (-2.0, 3.0, 1.57)
"""the shipped file's start (x, y, heading), and what :func:`convert_worlds` writes by default"""
FILE_GOAL = (-2.0, 13.0)
"""the shipped file's goal (x, y)"""
CHALLENGE_START = (-2.25, 3.0, 1.57)
"""the BARN Challenge's ``INIT_POSITION`` (its ``run.py``)"""
CHALLENGE_GOAL = (-2.25, 13.0)
"""the BARN Challenge's goal: 10 m ahead of its start"""

_INT_KEYS = ("map_ids", "offsets", "path_offsets")
_FLOAT_KEYS = ("centers", "radius", "paths", "start", "goal")
KEYS = _INT_KEYS + _FLOAT_KEYS


class BarnFormatError(ValueError):
    """A BARN map file (``.npz``) or Gazebo world (``.world``) that is not in the expected format."""


def default_path() -> Path:
    """The shipped ``eval/data/barn_train.npz``."""
    return Path(str(importlib.resources.files("eval") / "data" / "barn_train.npz"))


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


# ------------------------------------------------------------------------------------------------ validation

def _fail(source: str, key: str | None, message: str) -> BarnFormatError:
    where = f"{source}: key {key!r}" if key is not None else source
    return BarnFormatError(f"{where}: {message}")


def _check_offsets(off: np.ndarray, n_rows: int, key: str, rows_key: str, K: int, source: str) -> None:
    if off.shape != (K + 1,):
        raise _fail(source, key, f"must have shape [{K + 1}] (len(map_ids) + 1), got {list(off.shape)}")
    if off[0] != 0:
        raise _fail(source, key, f"must start at 0, got {int(off[0])}")
    if np.any(np.diff(off) < 0):
        k = int(np.nonzero(np.diff(off) < 0)[0][0])
        raise _fail(source, key, f"must be non-decreasing; entry {k + 1} ({int(off[k + 1])}) < entry {k} ({int(off[k])})")
    if off[-1] != n_rows:
        raise _fail(source, key, f"must end at len({rows_key}) = {n_rows}, got {int(off[-1])}")


def validate_barn(arrays: Mapping[str, np.ndarray], source: str = "<arrays>") -> None:
    """Check arrays in the format of the module docstring; raise :class:`BarnFormatError` naming ``source``
    and the key for the first problem."""
    for key in KEYS:
        if key not in arrays:
            raise _fail(source, key, f"missing (a BARN map file needs {', '.join(KEYS)})")
    a = {key: np.asarray(arrays[key]) for key in KEYS}
    for key in _INT_KEYS:
        if a[key].dtype.kind not in "iu":
            raise _fail(source, key, f"must be an integer array, got dtype {a[key].dtype}")
    for key in _FLOAT_KEYS:
        if a[key].dtype.kind != "f":
            raise _fail(source, key, f"must be a floating-point array, got dtype {a[key].dtype}")
        if not np.all(np.isfinite(a[key])):
            raise _fail(source, key, "must be finite (found NaN or inf)")
    expected = {"centers": "[M, 2]", "paths": "[P, 2]"}
    for key, shape in expected.items():
        if a[key].ndim != 2 or a[key].shape[1] != 2:
            raise _fail(source, key, f"must have shape {shape}, got {list(a[key].shape)}")
    fixed = {"radius": (), "start": (3,), "goal": (2,)}
    for key, shape in fixed.items():
        if a[key].shape != shape:
            raise _fail(source, key, f"must have shape {list(shape)}, got {list(a[key].shape)}")
    ids = a["map_ids"]
    if ids.ndim != 1:
        raise _fail(source, "map_ids", f"must have shape [K], got {list(ids.shape)}")
    unique, counts = np.unique(ids, return_counts=True)
    if np.any(counts > 1):
        raise _fail(source, "map_ids", f"must be unique; repeated: {unique[counts > 1][:5].tolist()}")
    if float(a["radius"]) <= 0:
        raise _fail(source, "radius", f"must be > 0, got {float(a['radius'])}")
    K = ids.shape[0]
    _check_offsets(a["offsets"], a["centers"].shape[0], "offsets", "centers", K, source)
    _check_offsets(a["path_offsets"], a["paths"].shape[0], "path_offsets", "paths", K, source)


# ------------------------------------------------------------------------------------------------ loading

def _read_npz(path: Path) -> dict[str, np.ndarray]:
    source = str(path)
    try:
        data = np.load(path, allow_pickle=False)
        if not isinstance(data, np.lib.npyio.NpzFile):
            raise _fail(source, None, "not an .npz archive (a single .npy array)")
        with data:
            out = {}
            for key in data.files:
                try:
                    out[key] = data[key]
                except (ValueError, OSError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
                    raise _fail(source, key, f"cannot be read ({type(exc).__name__}: {exc})") from None
            return out
    except FileNotFoundError:
        raise
    except BarnFormatError:
        raise
    except (ValueError, OSError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
        raise _fail(source, None, f"not a readable .npz archive ({type(exc).__name__}: {exc})") from None


def _unique_rows(rows: np.ndarray) -> np.ndarray:
    """``rows [n, 2]`` without exact duplicate rows, first occurrences in their order."""
    if rows.shape[0] == 0:
        return rows
    _, first = np.unique(rows, axis=0, return_index=True)
    return rows[np.sort(first)]


def load_barn(path: str | os.PathLike | None = None) -> list[BarnMap]:
    """The maps of a BARN map file (default: the shipped ``eval/data/barn_train.npz``), in file order.

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
        "radius": np.float32(first.radius),
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


# ------------------------------------------------------------------------------------------------ Gazebo worlds

_WORLD_NAME = re.compile(r"world_(\d+)\.world")
_FORBIDDEN = re.compile(rb"<!\s*(DOCTYPE|ENTITY)", re.IGNORECASE)


def _parse_world(path: Path) -> tuple[np.ndarray, float]:
    """``world_<id>.world`` -> (centers float32 [M, 2], cylinder radius)."""
    source = str(path)
    data = path.read_bytes()
    if _FORBIDDEN.search(data):
        raise _fail(source, None, "contains a DOCTYPE or ENTITY declaration; refusing to parse it")
    try:
        root = ET.fromstring(data)
    except ET.ParseError as exc:
        raise _fail(source, None, f"not well-formed XML ({exc})") from None
    world = root.find("world") if root.tag == "sdf" else None
    if world is None:
        raise _fail(source, None, f"not a BARN world: expected <sdf><world>, got <{root.tag}>")
    centers, radii = [], set()
    for model in world.findall("model"):  # the definitions; world/state repeats them
        name = model.get("name", "")
        if not name.startswith("unit_cylinder_"):
            continue
        pose = model.find("pose")
        try:
            values = [float(v) for v in (pose.text or "").split()] if pose is not None else []
        except ValueError:
            values = []
        if len(values) != 6 or not all(math.isfinite(v) for v in values):
            raise _fail(source, None, f"model {name!r}: needs a <pose> of 6 finite numbers (x y z roll pitch yaw)")
        r = model.find("link/collision/geometry/cylinder/radius")
        try:
            radii.add(float(r.text) if r is not None and r.text else math.nan)
        except ValueError:
            radii.add(math.nan)
        centers.append(values[:2])
    if not centers:
        raise _fail(source, None, "not a BARN world: no <model name='unit_cylinder_N'> under <world>")
    if len(radii) != 1 or not all(math.isfinite(r) and r > 0 for r in radii):
        raise _fail(source, None, f"not a BARN world: the cylinders need one collision radius > 0, got {sorted(radii)}")
    return np.asarray(centers, dtype=np.float32), radii.pop()


def _world_files(folder_or_files: str | os.PathLike | Iterable[str | os.PathLike]) -> list[tuple[int, Path]]:
    if isinstance(folder_or_files, (str, os.PathLike)):
        p = Path(folder_or_files)
        files = sorted(p.glob("world_*.world")) if p.is_dir() else [p]
    else:
        files = [Path(f) for f in folder_or_files]
    out = []
    for f in files:
        m = _WORLD_NAME.fullmatch(f.name)
        if m is None:
            raise BarnFormatError(f"{f}: a BARN world file is named world_<id>.world")
        if not f.is_file():
            raise FileNotFoundError(f"{f}: no such file")
        out.append((int(m.group(1)), f))
    if not out:
        raise BarnFormatError(f"{folder_or_files}: no world_<id>.world files")
    return sorted(out)


def _read_path(path: Path) -> np.ndarray:
    try:
        arr = np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        raise _fail(str(path), None, f"not a readable .npy path ({type(exc).__name__}: {exc})") from None
    if not isinstance(arr, np.ndarray) or arr.ndim != 2 or arr.shape[1] != 2 or arr.dtype.kind not in "iuf":
        raise _fail(str(path), None, f"a path must be a numeric [P, 2] array, got {getattr(arr, 'shape', arr)!r}")
    return arr.astype(np.float32)


def convert_worlds(
    folder_or_files: str | os.PathLike | Iterable[str | os.PathLike],
    start: Sequence[float] = FILE_START,
    goal: Sequence[float] = FILE_GOAL,
) -> dict[str, np.ndarray]:
    """BARN Gazebo worlds -> arrays in the file format (see the module docstring), maps sorted by id.

    ``folder_or_files``: a folder (every ``world_<id>.world`` in it), one file, or a list of files. The
    reference path of world ``<id>`` is ``path_<id>.npy`` next to it when present (the dataset's layout),
    else empty. Cylinders are the ``<model name='unit_cylinder_N'>`` definitions under ``<world>`` (x, y of
    their ``<pose>``); the ``<state>`` section, which repeats them, is not read. Files with a DOCTYPE or ENTITY
    declaration are refused unparsed.
    """
    ids, centers, paths, radii = [], [], [], set()
    for map_id, f in _world_files(folder_or_files):
        c, r = _parse_world(f)
        path_file = f.with_name(f"path_{map_id}.npy")
        ids.append(map_id)
        centers.append(c)
        radii.add(r)
        paths.append(_read_path(path_file) if path_file.is_file() else np.zeros((0, 2), np.float32))
    if len(radii) != 1:
        raise BarnFormatError(f"{folder_or_files}: the worlds use different cylinder radii {sorted(radii)}")
    arrays = {
        "map_ids": np.asarray(ids, dtype=np.int64),
        "centers": np.concatenate(centers).astype(np.float32),
        "offsets": np.concatenate([[0], np.cumsum([len(c) for c in centers])]).astype(np.int64),
        "radius": np.float32(radii.pop()),
        "paths": np.concatenate(paths).astype(np.float32),
        "path_offsets": np.concatenate([[0], np.cumsum([len(p) for p in paths])]).astype(np.int64),
        "start": np.asarray(start, dtype=np.float32),
        "goal": np.asarray(goal, dtype=np.float32),
    }
    validate_barn(arrays, str(folder_or_files))
    return arrays
