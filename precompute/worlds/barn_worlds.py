"""BARN Gazebo worlds (``world_<id>.world``, with ``path_<id>.npy`` beside them) -> arrays in the BARN map file
format (:mod:`precompute.worlds.barn_format`); :func:`precompute.worlds.barn.write_barn` writes them.

Shapes: M cylinder rows (all maps), P reference-path points (all maps).
"""

from __future__ import annotations

import math
import os
import re
import xml.etree.ElementTree as ET
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np

from cuniform_torch.common.fileio import check_regular, read_capped_bytes
from precompute.worlds.barn_format import BarnFormatError, format_error, validate_barn

__all__ = ["convert_worlds", "FILE_START", "FILE_GOAL"]

FILE_START = (-2.0, 3.0, 1.57)
"""the shipped file's start (x, y, heading), and what :func:`convert_worlds` writes by default"""
FILE_GOAL = (-2.0, 13.0)
"""the shipped file's goal (x, y)"""

_WORLD_NAME = re.compile(r"world_(\d+)\.world")
_MAX_WORLD_BYTES = 64 << 20  # a BARN world is ~100 kB
_FORBIDDEN = re.compile(rb"<!\s*(DOCTYPE|ENTITY)", re.IGNORECASE)


def _parse_world(path: Path) -> tuple[np.ndarray, float]:
    """``world_<id>.world`` -> (centers float32 [M, 2], cylinder radius)."""
    source = str(path)
    try:
        data = read_capped_bytes(path, _MAX_WORLD_BYTES, "a Gazebo world file")
    except ValueError as exc:  # a FIFO, a device, a file far larger than any world
        raise format_error(source, None, str(exc).removeprefix(f"{source}: ")) from None
    if _FORBIDDEN.search(data):
        raise format_error(source, None, "contains a DOCTYPE or ENTITY declaration; refusing to parse it")
    try:
        root = ET.fromstring(data)
    except ET.ParseError as exc:
        raise format_error(source, None, f"not well-formed XML ({exc})") from None
    world = root.find("world") if root.tag == "sdf" else None
    if world is None:
        raise format_error(source, None, f"not a BARN world: expected <sdf><world>, got <{root.tag}>")
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
            raise format_error(source, None, f"model {name!r}: needs a <pose> of 6 finite numbers (x y z roll pitch yaw)")
        r = model.find("link/collision/geometry/cylinder/radius")
        try:
            radii.add(float(r.text) if r is not None and r.text else math.nan)
        except ValueError:
            radii.add(math.nan)
        centers.append(values[:2])
    if not centers:
        raise format_error(source, None, "not a BARN world: no <model name='unit_cylinder_N'> under <world>")
    if len(radii) != 1 or not all(math.isfinite(r) and r > 0 for r in radii):
        raise format_error(source, None, f"not a BARN world: the cylinders need one collision radius > 0, got {sorted(radii)}")
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
        check_regular(path, "a BARN path file")  # a FIFO would block np.load; a device never ends
        arr = np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        raise format_error(str(path), None, f"not a readable .npy path ({type(exc).__name__}: {exc})") from None
    if not isinstance(arr, np.ndarray) or arr.ndim != 2 or arr.shape[1] != 2 or arr.dtype.kind not in "iuf":
        raise format_error(str(path), None, f"a path must be a numeric [P, 2] array, got {getattr(arr, 'shape', arr)!r}")
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
    arrays: dict[str, np.ndarray] = {
        "map_ids": np.asarray(ids, dtype=np.int64),
        "centers": np.concatenate(centers).astype(np.float32),
        "offsets": np.concatenate([[0], np.cumsum([len(c) for c in centers])]).astype(np.int64),
        "radius": np.asarray(radii.pop(), dtype=np.float32),  # [] (0-d, as np.load gives it back)
        "paths": np.concatenate(paths).astype(np.float32),
        "path_offsets": np.concatenate([[0], np.cumsum([len(p) for p in paths])]).astype(np.int64),
        "start": np.asarray(start, dtype=np.float32),
        "goal": np.asarray(goal, dtype=np.float32),
    }
    validate_barn(arrays, str(folder_or_files))
    return arrays
