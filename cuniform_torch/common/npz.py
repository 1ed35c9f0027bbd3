"""A bounded ``.npz`` reader: every member's ``.npy`` header is read and checked before its array is allocated.

``np.load`` trusts the header of each member: a few bytes claiming a shape of 10^9 elements make it allocate
that much before it finds the data missing. :func:`read_npz` reads the header of each member first
(``numpy.lib.format.read_magic`` and ``read_array_header_1_0/2_0`` on the zip member) and refuses, with one
:class:`NpzError` naming the file and the member, before any allocation:

* an object dtype (or any dtype holding Python objects: reading it would unpickle);
* a size (elements x item size) over the **size bound** of the member: ``max_ratio`` x its compressed size +
  ``slack`` bytes (``max_ratio`` defaults to 1032, the most deflate can ever expand, so a genuine file is never
  refused; a caller that knows its data can pass less), and over ``max_bytes`` when the caller gives a cap;
* a size that disagrees with the member's uncompressed size in the zip directory (a lying header);
* a shape or dtype other than the caller's ``expect``.

The data are then read in chunks (at most the header's size, which passed the bound), so a member whose stream
is shorter than its header claims is refused without the claimed allocation; the member's CRC is checked.
Shapes: n members.
"""

from __future__ import annotations

import math
import os
import stat
import zipfile
import zlib
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from cuniform_torch.common.fileio import file_kind

__all__ = ["NpzError", "DEFLATE_MAX_RATIO", "read_npz", "member_headers", "npy_header"]

DEFLATE_MAX_RATIO = 1032
"""deflate's largest possible expansion (a stream of one repeated byte): no genuine member exceeds it"""
_SLACK = 1 << 16  # bytes every member may hold whatever its compressed size (small arrays, stored members)
_CHUNK = 1 << 20  # bytes read at a time
_MAX_MEMBERS = 256


class NpzError(ValueError):
    """An ``.npz`` file that is unreadable, or whose members claim more than the file can hold."""


def _open_member(zf: zipfile.ZipFile, info: zipfile.ZipInfo, where: str):
    try:
        return zf.open(info)
    except (NotImplementedError, RuntimeError) as exc:  # an unknown compression, an encrypted member
        raise NpzError(f"{where}: cannot be opened ({exc})") from None
    except (OSError, EOFError, zipfile.BadZipFile, zlib.error) as exc:  # a damaged local header or directory
        raise NpzError(f"{where}: not readable ({type(exc).__name__}: {exc})") from None


def npy_header(fh, where: str) -> tuple[tuple[int, ...], bool, np.dtype, int]:
    """``(shape, fortran_order, dtype, header_bytes)`` of the ``.npy`` stream ``fh`` (at its start); an
    :class:`NpzError` naming ``where`` when it is not a header numpy reads."""
    try:
        version = np.lib.format.read_magic(fh)
        if version == (1, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_1_0(fh)
        elif version == (2, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_2_0(fh)
        else:
            raise ValueError(f"unsupported .npy version {version}")
    except (ValueError, TypeError, SyntaxError, EOFError, OverflowError, zlib.error) as exc:
        raise NpzError(f"{where}: not a .npy header ({type(exc).__name__}: {exc})") from None
    return tuple(int(n) for n in shape), bool(fortran), np.dtype(dtype), int(fh.tell())


def _size(shape: tuple[int, ...], dtype: np.dtype) -> int:
    return math.prod(shape) * dtype.itemsize  # python ints: no overflow however large the claim


def member_headers(path: str | os.PathLike) -> dict[str, tuple[tuple[int, ...], np.dtype]]:
    """``{key: (shape, dtype)}`` of every member of the ``.npz`` at ``path``, from the headers only."""
    where = str(path)
    out = {}
    with _zip(path) as zf:
        for info in zf.infolist():
            try:
                with _open_member(zf, info, f"{where}: member {info.filename}") as fh:
                    shape, _, dtype, _ = npy_header(fh, f"{where}: member {info.filename}")
            except (OSError, EOFError, zipfile.BadZipFile) as exc:  # a damaged stream under the header
                raise NpzError(f"{where}: member {info.filename}: not readable ({type(exc).__name__}: {exc})") \
                    from None
            out[info.filename.removesuffix(".npy")] = (shape, dtype)
    return out


def _zip(path: str | os.PathLike) -> zipfile.ZipFile:
    try:
        mode = os.stat(path).st_mode
    except OSError as exc:
        raise NpzError(f"{path}: not a readable .npz ({type(exc).__name__}: {exc})") from None
    if not stat.S_ISREG(mode):  # a FIFO would block the open; a device never ends
        raise NpzError(f"{path}: {file_kind(mode)}, not a regular file; give the .npz file itself")
    try:
        return zipfile.ZipFile(path)
    except (OSError, zipfile.BadZipFile, zlib.error, ValueError, EOFError) as exc:
        raise NpzError(f"{path}: not a readable .npz ({type(exc).__name__}: {exc})") from None


def read_npz(path: str | os.PathLike, *, keys: Sequence[str] | None = None,
             expect: Mapping[str, tuple[tuple[int | None, ...] | None, np.dtype | type | None]] | None = None,
             max_ratio: float = DEFLATE_MAX_RATIO, slack: int = _SLACK, max_bytes: int | None = None,
             what: str | None = None) -> dict[str, np.ndarray]:
    """The arrays of the ``.npz`` at ``path`` (module docstring), never allocating more than the size bound.

    ``keys``: the members to read, all of which must be present (default: every member; others are skipped
    unread). ``expect``: ``{key: (shape, dtype)}``, where a shape may use None for any length and either part
    may be None (not checked); checked from the header, before the data are read. ``max_bytes``: a cap on the
    total size of the arrays read. ``what``: how errors name the file (default: its path). One
    :class:`NpzError` per problem.
    """
    what = what or str(path)
    if not Path(path).is_file():
        if Path(path).exists():
            raise NpzError(f"{what}: {file_kind(os.stat(path).st_mode)}, not a regular file; give the .npz file itself")
        raise NpzError(f"{what}: no such file")
    out: dict[str, np.ndarray] = {}
    total = 0
    with _zip(path) as zf:
        infos = zf.infolist()
        if len(infos) > _MAX_MEMBERS:
            raise NpzError(f"{what}: {len(infos)} members, more than an .npz of this project holds ({_MAX_MEMBERS})")
        names = [i.filename for i in infos]
        if len(set(names)) != len(names) or not all(n.endswith(".npy") for n in names):
            raise NpzError(f"{what}: members must be distinct KEY.npy files, got {names[:8]}")
        members = {n.removesuffix(".npy"): i for n, i in zip(names, infos)}
        wanted = list(members) if keys is None else list(keys)
        missing = [k for k in wanted if k not in members]
        if missing:
            raise NpzError(f"{what}: missing key(s) {', '.join(missing)}")
        for key in wanted:
            info, where = members[key], f"{what}: member {key!r}"
            budget = None if max_bytes is None else max_bytes - total
            try:
                out[key] = _read_member(zf, info, where, (expect or {}).get(key), max_ratio, slack, budget)
            except (OSError, EOFError, zipfile.BadZipFile, zlib.error) as exc:  # a damaged stream, a bad CRC
                raise NpzError(f"{where}: not readable ({type(exc).__name__}: {exc})") from None
            total += out[key].nbytes
    return out


def _read_member(zf: zipfile.ZipFile, info: zipfile.ZipInfo, where: str, expect, max_ratio: float,
                 slack: int, budget: int | None) -> np.ndarray:
    with _open_member(zf, info, where) as fh:
        shape, fortran, dtype, hlen = npy_header(fh, where)
        if dtype.hasobject:
            raise NpzError(f"{where}: dtype {dtype} holds Python objects (reading it would run pickle); refused")
        nbytes = _size(shape, dtype)
        bound = int(max_ratio * info.compress_size) + slack
        if nbytes > bound:
            raise NpzError(f"{where}: its header claims {list(shape)} {dtype} ({nbytes} bytes), more than its "
                           f"{info.compress_size} compressed bytes can hold (at most {max_ratio:g} x + {slack}); "
                           "a damaged or forged file")
        if budget is not None and nbytes > budget:
            raise NpzError(f"{where}: its header claims {list(shape)} {dtype} ({nbytes} bytes), more than this file "
                           f"may hold ({budget} bytes left of its cap)")
        if hlen + nbytes != info.file_size:
            raise NpzError(f"{where}: its header claims {list(shape)} {dtype} ({nbytes} bytes) but the member holds "
                           f"{info.file_size - hlen} data bytes; a damaged or forged file")
        if expect is not None:
            eshape, edtype = expect
            if edtype is not None and dtype != np.dtype(edtype):
                raise NpzError(f"{where}: must be {np.dtype(edtype)}, got {dtype}")
            if eshape is not None and (len(shape) != len(eshape)
                                       or any(e is not None and e != s for s, e in zip(shape, eshape))):
                want = ["*" if e is None else e for e in eshape]
                raise NpzError(f"{where}: must have shape {want}, got {list(shape)}")
        buf = bytearray(nbytes)  # within the bound checked above
        view, got = memoryview(buf), 0
        while got < nbytes:
            n = fh.readinto(view[got:got + _CHUNK])
            if not n:
                raise NpzError(f"{where}: ends after {got} of its {nbytes} data bytes (truncated)")
            got += n
        if fh.read(1):  # also runs the CRC check at the end of the stream
            raise NpzError(f"{where}: holds more data than its header says")
    arr = np.frombuffer(buf, dtype=dtype) if nbytes else np.zeros(0, dtype=dtype)
    return arr.reshape(shape[::-1]).T if fortran else arr.reshape(shape)
