"""The BARN map file format (:mod:`precompute.worlds.barn`'s module docstring lists its keys): the keys, the error that a
file or world not in the format raises, and :func:`validate_barn`, the one check of a set of arrays, used by the
loader, the writer and the Gazebo converter (:mod:`precompute.worlds.barn_worlds`) alike.

Shapes: K maps, M cylinder rows (all maps), P reference-path points (all maps).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

__all__ = ["KEYS", "BarnFormatError", "format_error", "validate_barn"]

_INT_KEYS = ("map_ids", "offsets", "path_offsets")
_FLOAT_KEYS = ("centers", "radius", "paths", "start", "goal")
KEYS = _INT_KEYS + _FLOAT_KEYS
"""every key of a BARN map file"""


class BarnFormatError(ValueError):
    """A BARN map file (``.npz``) or Gazebo world (``.world``) that is not in the expected format."""


def format_error(source: str, key: str | None, message: str) -> BarnFormatError:
    """The error ``"<source>: key '<key>': <message>"`` (without the key part when ``key`` is None)."""
    where = f"{source}: key {key!r}" if key is not None else source
    return BarnFormatError(f"{where}: {message}")


def _check_offsets(off: np.ndarray, n_rows: int, key: str, rows_key: str, K: int, source: str) -> None:
    if off.shape != (K + 1,):
        raise format_error(source, key, f"must have shape [{K + 1}] (len(map_ids) + 1), got {list(off.shape)}")
    if off[0] != 0:
        raise format_error(source, key, f"must start at 0, got {int(off[0])}")
    if np.any(np.diff(off) < 0):
        k = int(np.nonzero(np.diff(off) < 0)[0][0])
        raise format_error(source, key, f"must be non-decreasing; entry {k + 1} ({int(off[k + 1])}) < entry {k} ({int(off[k])})")
    if off[-1] != n_rows:
        raise format_error(source, key, f"must end at len({rows_key}) = {n_rows}, got {int(off[-1])}")


def validate_barn(arrays: Mapping[str, np.ndarray], source: str = "<arrays>") -> None:
    """Check arrays in the format of the module docstring; raise :class:`BarnFormatError` naming ``source``
    and the key for the first problem."""
    for key in KEYS:
        if key not in arrays:
            raise format_error(source, key, f"missing (a BARN map file needs {', '.join(KEYS)})")
    a = {key: np.asarray(arrays[key]) for key in KEYS}
    for key in _INT_KEYS:
        if a[key].dtype.kind not in "iu":
            raise format_error(source, key, f"must be an integer array, got dtype {a[key].dtype}")
    for key in _FLOAT_KEYS:
        if a[key].dtype.kind != "f":
            raise format_error(source, key, f"must be a floating-point array, got dtype {a[key].dtype}")
        if not np.all(np.isfinite(a[key])):
            raise format_error(source, key, "must be finite (found NaN or inf)")
    expected = {"centers": "[M, 2]", "paths": "[P, 2]"}
    for key, shape in expected.items():
        if a[key].ndim != 2 or a[key].shape[1] != 2:
            raise format_error(source, key, f"must have shape {shape}, got {list(a[key].shape)}")
    fixed = {"radius": (), "start": (3,), "goal": (2,)}
    for key, dims in fixed.items():
        if a[key].shape != dims:
            raise format_error(source, key, f"must have shape {list(dims)}, got {list(a[key].shape)}")
    ids = a["map_ids"]
    if ids.ndim != 1:
        raise format_error(source, "map_ids", f"must have shape [K], got {list(ids.shape)}")
    unique, counts = np.unique(ids, return_counts=True)
    if np.any(counts > 1):
        raise format_error(source, "map_ids", f"must be unique; repeated: {unique[counts > 1][:5].tolist()}")
    if float(a["radius"]) <= 0:
        raise format_error(source, "radius", f"must be > 0, got {float(a['radius'])}")
    K = ids.shape[0]
    _check_offsets(a["offsets"], a["centers"].shape[0], "offsets", "centers", K, source)
    _check_offsets(a["path_offsets"], a["paths"].shape[0], "path_offsets", "paths", K, source)
