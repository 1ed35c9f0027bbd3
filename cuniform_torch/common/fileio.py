"""Atomic, deterministic file writing shared by tables, checkpoints and reports; lock files for outputs.

Every file is written to a temporary file in the destination folder and renamed over the destination, so
an interrupt (Ctrl-C, a crash) leaves either the old file or the new one, never half of one. A temporary file
is named ``.<name>.<pid>-<host>.<random>.tmp``: one that a killed writer (SIGKILL, power loss) leaves behind is
removed by the next write to the same destination once its writer's process is gone (or after
:data:`STALE_TEMP_SECONDS`, when that cannot be checked).
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import re
import socket
import stat
import tempfile
import time
import zipfile
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["atomic_path", "write_npz", "write_json", "write_bytes", "remove_stale_temps", "exclusive_lock",
           "FileLockedError", "STALE_TEMP_SECONDS", "FileKindError", "FileTooLargeError", "file_kind",
           "open_regular", "check_regular", "read_capped_bytes", "read_capped_text", "check_not_special", "MAX_JSON_BYTES", "MAX_SMALL_JSON_BYTES",
           "MAX_JSONL_BYTES"]

# A fixed timestamp makes the zip (npz) bytes depend on the arrays only, so equal tables are equal files.
_ZIP_TIME = (1980, 1, 1, 0, 0, 0)


STALE_TEMP_SECONDS = 6 * 3600.0
"""age after which a temporary file whose writer cannot be checked (another host, the old naming) is stale;
a live writer keeps its file's mtime fresh, and one atomic write takes seconds to minutes"""

_HOST = re.sub(r"\W", "_", socket.gethostname())[:24] or "localhost"  # word characters: temp names stay unambiguous


MAX_JSON_BYTES = 64 << 20
"""the largest JSON file that lists many files a reader reads (a table-set index ``tables.json``, a data-set
manifest ``dataset.json``): 64 MiB"""
MAX_SMALL_JSON_BYTES = 1 << 20
"""the largest JSON file of settings a reader reads (a benchmark's ``settings.json``, a model card, a build's
manifest, a result file): 1 MiB"""
MAX_JSONL_BYTES = 1 << 30
"""the largest JSON-lines file a reader reads (a benchmark's ``episodes.jsonl``): 1 GiB"""


class FileKindError(ValueError):
    """A path that names something other than the regular file (or folder) a reader or writer expects: a FIFO, a
    device, a socket, a folder, or a symlink to one of them."""


class FileTooLargeError(ValueError):
    """A file larger than its reader's cap: refused from its size, before it is read."""


def file_kind(mode: int) -> str:
    """``"a regular file"``, ``"a folder"``, ``"a FIFO (named pipe)"``, ... for an ``st_mode``."""
    for test, name in ((stat.S_ISREG, "a regular file"), (stat.S_ISDIR, "a folder"), (stat.S_ISFIFO, "a FIFO (named pipe)"),
                       (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
                       (stat.S_ISSOCK, "a socket"), (stat.S_ISLNK, "a symlink")):
        if test(mode):
            return name
    return "not a regular file"


def _not_regular(path: Path, mode: int, what: str) -> FileKindError:
    link = " (through a symlink)" if path.is_symlink() else ""
    return FileKindError(f"{path}: {what} is {file_kind(mode)}{link}, not a regular file")


def open_regular(path: str | os.PathLike, what: str = "the file") -> io.BufferedReader:
    """``path`` opened for reading in binary, when it is (or a symlink names) a regular file; else one
    :class:`FileKindError` naming it, before any read. Never blocks: a FIFO is refused from ``stat``, and the file
    is opened ``O_NONBLOCK`` and checked again with ``fstat`` (a FIFO swapped in meanwhile opens without waiting
    for a writer). A missing file raises ``FileNotFoundError`` as ``open`` does."""
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


def check_regular(path: str | os.PathLike, what: str = "the file") -> None:
    """:class:`FileKindError` unless ``path`` is (or a symlink names) a regular file, from ``stat`` alone, for a
    reader that opens the path itself (``np.load``, ``zipfile``); ``FileNotFoundError`` when it is missing."""
    path = Path(path)
    mode = os.stat(path).st_mode
    if not stat.S_ISREG(mode):
        raise _not_regular(path, mode, what)


def read_capped_bytes(path: str | os.PathLike, max_bytes: int, what: str = "the file") -> bytes:
    """The bytes of the regular file ``path`` (:func:`open_regular`), at most ``max_bytes``: a larger file is one
    :class:`FileTooLargeError` from its size before it is read (and one that grows meanwhile, after at most
    ``max_bytes + 1`` bytes)."""
    with open_regular(path, what) as fh:
        size = os.fstat(fh.fileno()).st_size
        if size <= max_bytes:
            data = fh.read(max_bytes + 1)
        if size > max_bytes or len(data) > max_bytes:
            raise FileTooLargeError(f"{path}: {what} holds {max(size, max_bytes + 1)} bytes, over the limit of "
                                    f"{max_bytes} bytes for such a file; is it the right file?")
    return data


def read_capped_text(path: str | os.PathLike, max_bytes: int = MAX_JSON_BYTES, what: str = "the file") -> str:
    """:func:`read_capped_bytes` decoded as UTF-8 (a ``UnicodeDecodeError``, a ``ValueError``, when it is not)."""
    return read_capped_bytes(path, max_bytes, what).decode("utf-8")


def _check_not_system(path: Path, what: str) -> None:
    for where in {path.absolute(), path.resolve()}:
        if where.parts[1:2] in (("dev",), ("proc",), ("sys",)):  # /dev/stdout is a link into /proc: never replaced
            raise FileKindError(f"{path}: {what} is in /{where.parts[1]}, the system's device and process files; "
                                "refusing to write there, give another path")


def check_not_special(path: str | os.PathLike, what: str = "the output", folder: bool = False) -> None:
    """:class:`FileKindError` when ``path`` exists and is not a regular file (nor a folder, when ``folder``):
    an output never replaces or writes into a device, a FIFO or a socket (``--out /dev/null``). A symlink is judged
    by what it names; one that names nothing passes (a write replaces the link, never what it names). An existing
    path in (or naming a file in) ``/dev``, ``/proc`` or ``/sys`` is refused too: ``/dev/stdout`` names a regular
    file when the output is redirected to one, and an atomic write would replace the link itself."""
    path = Path(path)
    try:
        mode = os.stat(path).st_mode
    except (FileNotFoundError, NotADirectoryError):
        if os.path.lexists(path):  # a dangling link: a write replaces the link itself
            _check_not_system(path, what)
        return
    except OSError as exc:  # a symlink loop, a name too long
        raise FileKindError(f"{path}: {what} cannot be checked ({exc.strerror or exc}); give another path") from None
    if stat.S_ISREG(mode) or (folder and stat.S_ISDIR(mode)):
        _check_not_system(path, what)
        return
    expected = "a regular file or a folder" if folder else "a regular file"
    link = " (through a symlink)" if path.is_symlink() else ""
    raise FileKindError(f"{path}: {what} is {file_kind(mode)}{link}, not {expected}; refusing to write there, "
                        "give another path")


def _temp_pattern(name: str) -> re.Pattern[str]:
    """Temp names of destination ``name``: ``.<name>.<pid>-<host>.<8 random>.tmp`` (or the old ``.<name>.<8>.tmp``)."""
    return re.compile(rf"\.{re.escape(name)}\.(?:(\d+)-(\w*)\.)?\w{{8}}\.tmp")


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # alive, another user's
        return True
    return True


def remove_stale_temps(path: str | os.PathLike, max_age: float = STALE_TEMP_SECONDS) -> list[Path]:
    """Remove the temporary files that killed writers of ``path`` left behind; returns the removed paths.

    A file is stale when its writer (pid, this host) is gone, or when it is older than ``max_age`` seconds.
    """
    dest = Path(path)
    pattern, removed, now = _temp_pattern(dest.name), [], time.time()
    try:
        entries = list(os.scandir(dest.parent))
    except OSError:
        return []
    for entry in entries:
        match = pattern.fullmatch(entry.name)
        if match is None:
            continue
        pid, host = match.groups()
        try:
            old = now - entry.stat(follow_symlinks=False).st_mtime > max_age
        except FileNotFoundError:
            continue
        dead = pid is not None and host == _HOST and not _pid_alive(int(pid))
        if old or dead:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(entry.path)
                removed.append(Path(entry.path))
    return removed


def _with_filename(exc: OSError, dest: Path) -> OSError:
    """``exc`` naming the destination (a full disk raises ENOSPC from a write, which names no file)."""
    if exc.filename is not None or exc.errno is None:
        return exc
    return type(exc)(exc.errno, exc.strerror or os.strerror(exc.errno), str(dest))


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on success it replaces ``path`` atomically, else is removed.

    Stale temporary files of ``path`` (see :func:`remove_stale_temps`) are removed first. An ``OSError`` that
    names no file is re-raised naming ``path``. A ``path`` that is a device, a FIFO or a socket (or a symlink to
    one) is a :class:`FileKindError` before anything is written (the rename would replace ``/dev/null``).
    """
    dest = Path(path)
    check_not_special(dest, "the output", folder=True)  # a folder fails at the rename, naming it
    dest.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temps(dest)
    fd, tmp = tempfile.mkstemp(prefix=f".{dest.name}.{os.getpid()}-{_HOST}.", suffix=".tmp", dir=dest.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        with open(tmp_path, "rb+") as fh:
            os.fsync(fh.fileno())
        os.chmod(tmp_path, 0o644)  # mkstemp makes 0600; a table or report is an ordinary shared file
        os.replace(tmp_path, dest)
    except BaseException as exc:
        with contextlib.suppress(FileNotFoundError):
            tmp_path.unlink()
        if isinstance(exc, OSError):
            raise _with_filename(exc, dest) from exc
        raise


class FileLockedError(OSError):
    """The lock file of an output is held by a live process (another build or training run to the same file)."""


def _read_lock(lock: Path) -> str | None:
    try:
        return lock.read_text()
    except FileNotFoundError:
        return None


def _lock_owner(text: str) -> tuple[int, str] | None:
    """``(pid, host)`` of a lock file's text ``"<pid> <host>"``; None when it is empty or not of that form."""
    parts = text.split()
    if len(parts) != 2 or not parts[0].isdigit():
        return None
    return int(parts[0]), parts[1]


def _take_over(lock: Path, stale_text: str) -> bool:
    """Remove a stale lock, unless another process replaced it meanwhile (then restore theirs): True if removed."""
    aside = lock.with_name(f"{lock.name}.{os.getpid()}.stale")
    try:
        os.rename(lock, aside)
    except FileNotFoundError:
        return True  # someone else removed it: try to create ours
    if aside.read_text() != stale_text:  # a fresh lock of a racing process: put it back
        with contextlib.suppress(FileExistsError):
            os.link(aside, lock)
        os.unlink(aside)
        return False
    os.unlink(aside)
    return True


def _acquire(lock: Path, what: str) -> None:
    for _ in range(5):
        try:
            fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            text = _read_lock(lock)
            if text is None:
                continue  # released meanwhile
            owner = _lock_owner(text)
            if owner is None:
                try:
                    young = time.time() - lock.stat().st_mtime < 10.0
                except FileNotFoundError:
                    continue  # released meanwhile
                if young:  # just created, its pid not yet written
                    time.sleep(0.1)
                    continue
            else:
                pid, host = owner
                if host != _HOST or pid == os.getpid() or _pid_alive(pid):
                    where = f"process {pid}" + ("" if host == _HOST else f" on {host}")
                    raise FileLockedError(f"{what} is being written by {where} (lock file {lock}); wait for it to "
                                          "finish, or delete the lock file if no such process runs") from None
            _take_over(lock, text)
            continue
        try:
            with os.fdopen(fd, "w") as fh:
                fh.write(f"{os.getpid()} {_HOST}\n")
        except OSError as exc:  # a full disk: never leave an empty lock that refuses every rerun for 10 s
            with contextlib.suppress(FileNotFoundError):
                os.unlink(lock)
            raise _with_filename(exc, lock) from exc
        return
    raise FileLockedError(f"{what}: could not take the lock file {lock} (other processes keep taking it)")


@contextlib.contextmanager
def exclusive_lock(lock: str | os.PathLike, what: str = "the output") -> Iterator[Path]:
    """Hold the lock file ``lock`` while the block runs: created exclusively (``O_CREAT | O_EXCL``) holding
    ``"<pid> <host>"``, removed at the end. A lock of a process that is gone (on this host) is taken over;
    :class:`FileLockedError` (naming ``what`` and the holder) when a live process holds it."""
    lock = Path(lock)
    lock.parent.mkdir(parents=True, exist_ok=True)
    _acquire(lock, what)
    try:
        yield lock
    finally:
        if _lock_owner(_read_lock(lock) or "") == (os.getpid(), _HOST):  # never remove a lock taken over from us
            with contextlib.suppress(FileNotFoundError):
                lock.unlink()


def write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def write_json(path: str | os.PathLike, obj: Any) -> None:
    """Write ``obj`` as indented JSON, atomically."""
    write_bytes(path, (json.dumps(obj, indent=2, sort_keys=False) + "\n").encode())


def write_npz(path: str | os.PathLike, arrays: Mapping[str, np.ndarray], compress: bool = True) -> None:
    """Write arrays as an ``.npz`` that ``np.load(allow_pickle=False)`` reads; atomic and byte-deterministic."""
    compression = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED
    with atomic_path(path) as tmp:
        with zipfile.ZipFile(tmp, "w", compression=compression, compresslevel=1, allowZip64=True) as zf:
            for key, value in arrays.items():
                arr = np.asarray(value)
                if arr.dtype == object:
                    raise TypeError(f"write_npz: array {key!r} has dtype object, which needs pickle; refusing")
                buf = io.BytesIO()
                np.lib.format.write_array(buf, arr, allow_pickle=False)
                info = zipfile.ZipInfo(f"{key}.npy", date_time=_ZIP_TIME)
                info.compress_type = compression
                info.external_attr = 0o644 << 16
                zf.writestr(info, buf.getvalue())
