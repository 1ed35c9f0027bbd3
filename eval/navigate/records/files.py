"""Reading a benchmark folder's files without torch: the checks of :mod:`cuniform_torch.common.fileio`'s readers.

``cuniform_torch.common.fileio`` itself needs no torch, but importing it runs ``cuniform_torch/__init__.py``, which
imports the whole runtime (torch included, about a second). The records layer reads with these copies instead,
so a report that only reads records (``python -m eval.navigate compare``) never loads torch. They must refuse what
those refuse with the same messages; ``tests/test_nav_records.py`` checks both on the same files. Writing stays
with ``cuniform_torch.common.fileio`` (atomic writes, stale temporaries): only a run writes a folder, and it has
torch loaded anyway.
"""

from __future__ import annotations

import io
import os
import stat
from pathlib import Path

__all__ = ["MAX_SMALL_JSON_BYTES", "MAX_JSONL_BYTES", "RecordFileKindError", "RecordFileTooLargeError", "file_kind",
           "open_regular", "read_capped_bytes", "read_capped_text"]

MAX_SMALL_JSON_BYTES = 1 << 20
"""the largest ``settings.json`` a reader reads: 1 MiB (``cuniform_torch.common.fileio.MAX_SMALL_JSON_BYTES``)"""
MAX_JSONL_BYTES = 1 << 30
"""the largest ``episodes.jsonl`` a reader reads: 1 GiB (``cuniform_torch.common.fileio.MAX_JSONL_BYTES``)"""


class RecordFileKindError(ValueError):
    """A path that names something other than a regular file: a FIFO, a device, a socket, a folder, or a symlink to
    one of them (``cuniform_torch.common.fileio.FileKindError``)."""


class RecordFileTooLargeError(ValueError):
    """A file larger than its reader's cap, refused from its size before it is read
    (``cuniform_torch.common.fileio.FileTooLargeError``)."""


def file_kind(mode: int) -> str:
    """``"a regular file"``, ``"a folder"``, ``"a FIFO (named pipe)"``, ... for an ``st_mode``."""
    for test, name in ((stat.S_ISREG, "a regular file"), (stat.S_ISDIR, "a folder"),
                       (stat.S_ISFIFO, "a FIFO (named pipe)"), (stat.S_ISCHR, "a character device"),
                       (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"), (stat.S_ISLNK, "a symlink")):
        if test(mode):
            return name
    return "not a regular file"


def _not_regular(path: Path, mode: int, what: str) -> RecordFileKindError:
    link = " (through a symlink)" if path.is_symlink() else ""
    return RecordFileKindError(f"{path}: {what} is {file_kind(mode)}{link}, not a regular file")


def open_regular(path: str | os.PathLike, what: str = "the file") -> io.BufferedReader:
    """``path`` opened for reading in binary when it is (or a symlink names) a regular file, else one
    :class:`RecordFileKindError` naming it before any read. Never blocks: a FIFO is refused from ``stat``, and the
    file is opened ``O_NONBLOCK`` and checked again with ``fstat`` (a FIFO swapped in meanwhile)."""
    path = Path(path)
    mode = os.stat(path).st_mode
    if not stat.S_ISREG(mode):
        raise _not_regular(path, mode, what)
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    try:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            raise _not_regular(path, mode, what)
        os.set_blocking(fd, True)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def read_capped_bytes(path: str | os.PathLike, max_bytes: int, what: str = "the file") -> bytes:
    """The bytes of the regular file ``path`` (:func:`open_regular`), at most ``max_bytes``: a larger file is one
    :class:`RecordFileTooLargeError` from its size before it is read (one that grows meanwhile, after at most
    ``max_bytes + 1`` bytes)."""
    with open_regular(path, what) as fh:
        size = os.fstat(fh.fileno()).st_size
        data = fh.read(max_bytes + 1) if size <= max_bytes else b""
        if size > max_bytes or len(data) > max_bytes:
            raise RecordFileTooLargeError(f"{path}: {what} holds {max(size, max_bytes + 1)} bytes, over the limit "
                                          f"of {max_bytes} bytes for such a file; is it the right file?")
    return data


def read_capped_text(path: str | os.PathLike, max_bytes: int, what: str = "the file") -> str:
    """:func:`read_capped_bytes` decoded as UTF-8 (a ``UnicodeDecodeError``, a ``ValueError``, when it is not)."""
    return read_capped_bytes(path, max_bytes, what).decode("utf-8")
