"""Local maps for safe level sets (C-Free-Uniform): the map file, its inflation, and the free-cell test.

Shapes: H x W map cells, n level cells, d state dimensions.

A local map is an occupancy grid in the robot's frame at the start (robot at the origin heading +x), in the
convention of :class:`cuniform_torch.envs.OccupancyGrid`: cell ``(i, j)`` covers ``x in [x0 + j r, x0 + (j+1) r)``
and ``y in [y0 + i r, y0 + (i+1) r)``; points outside the map are free.

Pruning rule (the one definition, used by both builders): a level cell is removed when the map cell under its
centre's (x, y) lies within ``radius`` of an occupied map cell, the distance measured between map-cell centres
(``scipy.ndimage.distance_transform_edt``); an occupied map cell itself is at distance 0.

Map file (``.npz``, format ``cuniform-local-map/1``): ``format`` (string), ``occupied`` uint8 ``[H, W]`` of 0/1,
``origin`` float64 ``[2]`` (x0, y0 in m), ``resolution`` float64 ``[]`` (m), and ``content_sha256`` (the digest of
the others, :mod:`cuniform_torch.common.digest`; absent in files written before it). It is read with the bounded
reader :func:`cuniform_torch.common.npz.read_npz`: each member's shape and dtype are checked from its ``.npy``
header (``occupied`` at most 4096 x 4096) before anything is allocated.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import scipy.ndimage
import torch

from cuniform_torch.common.digest import DIGEST_KEY, DigestError, check_digest, content_digest
from cuniform_torch.common.fileio import write_npz
from cuniform_torch.common.npz import NpzError, member_headers, read_npz
from cuniform_torch.grid.cells import Grid
from cuniform_torch.systems import System

__all__ = ["MAP_FORMAT", "MAX_MAP_SIDE", "MapError", "LocalMap", "read_map_file", "write_map_file", "check_map_system",
           "SafeCells", "map_table_keys", "map_overrides"]

MAP_FORMAT = "cuniform-local-map/1"
MAX_MAP_SIDE = 4096
"""at most this many map cells per side"""
_TIE = 1e-9  # cells exactly at the radius count as inside (robust to the last ulp of the distance)


class MapError(ValueError):
    """A local map that is missing, malformed or unusable (a start in an obstacle, a system without a pose)."""


@dataclass(frozen=True, eq=False)
class LocalMap:
    """An occupancy grid in the robot's frame at the start (module docstring)."""

    occupied: np.ndarray
    """uint8 ``[H, W]``, 1 = occupied (row i is y, column j is x)"""
    origin: tuple[float, float]
    """(x0, y0): the lower-left corner of cell (0, 0), m"""
    resolution: float
    """cell side, m"""

    def __post_init__(self) -> None:
        check_map_arrays(self.occupied, self.origin, self.resolution, "LocalMap")
        object.__setattr__(self, "occupied", np.ascontiguousarray(self.occupied, dtype=np.uint8))
        object.__setattr__(self, "origin", (float(self.origin[0]), float(self.origin[1])))
        object.__setattr__(self, "resolution", float(self.resolution))

    @property
    def shape(self) -> tuple[int, int]:
        return tuple(int(n) for n in self.occupied.shape)

    def sha256(self) -> str:
        """sha256 of the occupancy: the ``uint8 [H, W]`` C-order bytes (the frame is recorded beside it)."""
        return hashlib.sha256(self.occupied.tobytes()).hexdigest()

    def inflated(self, radius: float) -> np.ndarray:
        """bool ``[H, W]``: map cells whose centre lies within ``radius`` of an occupied cell's centre."""
        occ = self.occupied.astype(bool)
        if not occ.any():
            return occ
        dist = scipy.ndimage.distance_transform_edt(~occ)  # [H, W], in cells, 0 on occupied cells
        return dist <= radius / self.resolution + _TIE


def check_map_arrays(occupied: Any, origin: Any, resolution: Any, source: str) -> None:
    """MapError naming ``source`` and the first problem of a map's arrays."""
    occ = np.asarray(occupied)
    if occ.dtype != np.uint8 or occ.ndim != 2:
        raise MapError(f"{source}: 'occupied' must be uint8 [H, W], got {occ.dtype} {list(occ.shape)}")
    if not (1 <= occ.shape[0] <= MAX_MAP_SIDE and 1 <= occ.shape[1] <= MAX_MAP_SIDE):
        raise MapError(f"{source}: 'occupied' must be between 1 x 1 and {MAX_MAP_SIDE} x {MAX_MAP_SIDE}, "
                       f"got {list(occ.shape)}")
    if occ.size and occ.max() > 1:
        raise MapError(f"{source}: 'occupied' must hold only 0 (free) and 1 (occupied), found {int(occ.max())}")
    org = np.asarray(origin, dtype=np.float64) if not isinstance(origin, np.ndarray) else origin
    if org.shape != (2,) or org.dtype.kind != "f" or not np.all(np.isfinite(org)):
        raise MapError(f"{source}: 'origin' must be 2 finite floats (x0, y0), got {org.dtype} {list(org.shape)}")
    res = np.asarray(resolution)
    if res.shape != () or res.dtype.kind != "f" or not (math.isfinite(float(res)) and float(res) > 0):
        raise MapError(f"{source}: 'resolution' must be one finite float > 0 (m), got {res.dtype} "
                       f"{list(res.shape)} {res.tolist()!r}")


_MAP_KEYS = ("format", "occupied", "origin", "resolution")


def read_map_file(path: str | Path) -> LocalMap:
    """Read and validate a map file (module docstring); every problem is one MapError naming the file."""
    path = Path(path)
    if not path.is_file():
        raise MapError(f"--map {path}: no such file")
    where = f"--map {path}"
    try:  # headers first: a member claiming more than a map holds is refused before it is allocated
        heads = member_headers(path)
        missing = [k for k in _MAP_KEYS if k not in heads]
        if missing:
            raise MapError(f"{where}: missing key(s) {', '.join(missing)}; a map file holds format, "
                           "occupied, origin, resolution")
        expect = {"format": ((), None), DIGEST_KEY: ((), None)}  # the others: check_map_arrays' messages
        occ_shape = heads["occupied"][0]
        if len(occ_shape) == 2 and not all(1 <= n <= MAX_MAP_SIDE for n in occ_shape):
            raise MapError(f"{where}: 'occupied' must be between 1 x 1 and {MAX_MAP_SIDE} x {MAX_MAP_SIDE}, got "
                           f"{list(occ_shape)}")
        keys = list(_MAP_KEYS) + ([DIGEST_KEY] if DIGEST_KEY in heads else [])
        z = read_npz(path, keys=keys, expect=expect, max_bytes=MAX_MAP_SIDE * MAX_MAP_SIDE + (1 << 16), what=where)
    except NpzError as exc:
        raise MapError(f"{where}: not a readable .npz map ({exc})") from None
    fmt = z["format"]
    if fmt.shape != () or fmt.dtype.kind != "U" or str(fmt[()]) != MAP_FORMAT:
        raise MapError(f"{where}: format must be {MAP_FORMAT!r}, got {fmt.tolist()!r}")
    stored = z.pop(DIGEST_KEY, None)
    if stored is not None and stored.dtype.kind != "U":
        raise MapError(f"{where}: {DIGEST_KEY} must be a string, got {stored.dtype}")
    try:  # a damaged file first; the note of an old file (no digest) only once it is otherwise valid
        if stored is not None:
            check_digest(z, str(stored[()]), str(path))
    except DigestError as exc:
        raise MapError(f"--map {exc}") from None
    check_map_arrays(z["occupied"], z["origin"], z["resolution"], where)
    for key in ("origin", "resolution"):  # the file's contract: float64 (a float32 0.1 is another resolution)
        if z[key].dtype != np.float64:
            raise MapError(f"{where}: '{key}' must be float64, got {z[key].dtype}")
    if stored is None:
        check_digest(z, None, str(path))
    return LocalMap(z["occupied"], tuple(z["origin"].tolist()), float(z["resolution"]))


def write_map_file(path: str | Path, local_map: LocalMap) -> None:
    """Write ``local_map`` as a map file (atomic, byte-deterministic), with its content digest."""
    arrays = {"format": np.array(MAP_FORMAT), "occupied": local_map.occupied,
              "origin": np.asarray(local_map.origin, dtype=np.float64),
              "resolution": np.array(local_map.resolution, dtype=np.float64)}
    write_npz(path, {**arrays, DIGEST_KEY: np.array(content_digest(arrays))})


def check_map_system(system: System) -> None:
    """MapError unless ``system`` is SE(2)-invariant with states (x, y, theta, ...)."""
    periodic = tuple(system.periodic)
    if not (getattr(system, "se2_invariant", False) and len(periodic) >= 3 and periodic[:3] == (False, False, True)):
        raise MapError(f"--map: {system.name} does not take a map; a local map needs an SE(2)-invariant system whose "
                       "state starts with (x, y, theta)")


class SafeCells:
    """The free-cell test of one (map, radius) on a system's grid: ``keep(cells [n, d]) -> bool [n]``."""

    def __init__(self, system: System, local_map: LocalMap, radius: float) -> None:
        check_map_system(system)
        if isinstance(radius, bool) or not (math.isfinite(float(radius)) and float(radius) >= 0):
            raise MapError(f"--radius must be a finite number >= 0 (m), got {radius!r}")
        self.grid = Grid.of(system)
        self.map = local_map
        self.radius = float(radius)
        self.blocked = torch.from_numpy(local_map.inflated(self.radius))  # [H, W] bool

    def blocked_xy(self, xy: torch.Tensor) -> torch.Tensor:
        """``xy [n, 2]`` -> bool ``[n]``: whether each point lies in the inflated obstacles (outside: free)."""
        H, W = self.map.shape
        fx = (xy[:, 0] - self.map.origin[0]) / self.map.resolution
        fy = (xy[:, 1] - self.map.origin[1]) / self.map.resolution
        inside = (fx >= 0) & (fx < W) & (fy >= 0) & (fy < H)
        j = torch.where(inside, fx, torch.zeros_like(fx)).floor().long().clamp(0, W - 1)
        i = torch.where(inside, fy, torch.zeros_like(fy)).floor().long().clamp(0, H - 1)
        return self.blocked.reshape(-1)[i * W + j] & inside

    def keep(self, cells: torch.Tensor) -> torch.Tensor:
        """``cells [n, d]`` int64 -> bool ``[n]``: the cells whose centre is collision-free."""
        centres = self.grid.centers(cells, torch.float64)  # [n, d]
        return ~self.blocked_xy(centres[:, :2])

    def check_start(self, start_cell: torch.Tensor, start: torch.Tensor) -> None:
        """MapError when the start cell ``[1, d]`` of the start state ``[1, d]`` is not free."""
        if not bool(self.keep(start_cell)[0]):
            centre = self.grid.centers(start_cell, torch.float64)[0, :2].tolist()
            raise MapError(f"the start {start[0, :3].tolist()} is inside an obstacle of the map: its cell's centre "
                           f"({centre[0]:.4g}, {centre[1]:.4g}) lies within --radius {self.radius:g} m of an occupied "
                           "map cell")

    def table_keys(self) -> dict[str, Any]:
        """The table's optional map keys (see :func:`map_table_keys`)."""
        return map_table_keys(self.map, self.radius)


def map_table_keys(local_map: LocalMap, radius: float) -> dict[str, Any]:
    """``map_sha256`` (str), ``map_origin`` float64 [2], ``map_resolution`` float64 [], ``map_shape`` int64 [2],
    ``map_radius`` float64 []: the map a safe table was built with, for :class:`cuniform_torch.tables.file.Table`."""
    return {"map_sha256": local_map.sha256(), "map_origin": np.asarray(local_map.origin, dtype=np.float64),
            "map_resolution": np.array(local_map.resolution, dtype=np.float64),
            "map_shape": np.asarray(local_map.shape, dtype=np.int64),
            "map_radius": np.array(float(radius), dtype=np.float64)}


def map_overrides(args: Any, system: System) -> dict[str, Any]:
    """``{"local_map", "radius"}`` for the build configs from the flags ``--map`` and ``--radius`` (empty
    without ``--map``); MapError for a bad file, a system without a pose, or ``--radius`` alone."""
    if args.map_file is None:
        if args.map_radius is not None:
            raise MapError("--radius inflates the obstacles of --map: give --map too")
        return {}
    check_map_system(system)
    radius = 0.0 if args.map_radius is None else args.map_radius
    if not (math.isfinite(radius) and radius >= 0):
        raise MapError(f"--radius must be a finite number >= 0 (m), got {radius}")
    return {"local_map": read_map_file(args.map_file), "radius": float(radius)}
