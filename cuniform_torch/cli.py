"""What every ``python -m`` entry point shares: one-line errors, exit codes, output checks, ``--system-module``.

Decorate an entry point's ``main(argv) -> int`` with :func:`cli_main`. Clear errors -- the library's
``ValueError`` subclasses (``TableError``, ``PolicyCheckpointError``, ``UnknownSystemError``, ...), a
:class:`CLIError`, an ``OSError`` (a missing file, a full disk, a folder one cannot write) and running out of
memory -- print one line ``error: ...`` on stderr and return :data:`EXIT_ERROR` (2); Ctrl-C prints one line and
returns :data:`EXIT_INTERRUPTED` (130). Any other exception is a bug and keeps its traceback.
"""

from __future__ import annotations

import argparse
import functools
import os
import re
import sys
import tempfile
from pathlib import Path
from typing import Callable, NoReturn, Sequence

from .systems import import_system_modules

__all__ = ["EXIT_ERROR", "EXIT_INTERRUPTED", "CLIError", "ArgumentParser", "cli_main", "error_message",
           "out_of_memory_message", "add_system_module_arg", "import_system_modules", "check_output_file", "check_output_folder"]

EXIT_ERROR = 2
EXIT_INTERRUPTED = 130


class CLIError(Exception):
    """A clear error a script finds (conflicting flags, an output it cannot write): ``error: <message>``, exit 2."""


class ArgumentParser(argparse.ArgumentParser):
    """argparse that reports a bad flag as one ``error: ...`` line and exits 2 (no usage block)."""

    def error(self, message: str) -> NoReturn:
        print(f"error: {message} (see {self.prog} --help)", file=sys.stderr)
        raise SystemExit(EXIT_ERROR)


def add_system_module_arg(parser: argparse.ArgumentParser) -> None:
    """The ``--system-module MODULE`` flag (repeatable) of every entry point that reads a table or checkpoint."""
    parser.add_argument("--system-module", action="append", default=[], metavar="MODULE",
                        help="import MODULE first (repeatable); it registers user systems with register_system, "
                             "which reading a table or checkpoint of a user system needs")


def out_of_memory_message(exc: BaseException) -> str | None:
    """A one-line description when ``exc`` is an allocation failure (Python, numpy or torch), else None."""
    text = str(exc)
    if isinstance(exc, MemoryError):
        return f"out of memory ({text})" if text else "out of memory"
    if isinstance(exc, RuntimeError) and ("can't allocate memory" in text or "out of memory" in text.lower()):
        asked = re.search(r"allocate (\d+) bytes", text)
        if asked:
            return f"out of memory: it tried to allocate {int(asked.group(1)) / 1e9:.3g} GB"
        return "out of memory: " + text.splitlines()[0]
    return None


def error_message(exc: BaseException) -> str | None:
    """The one-line message of a clear error, or None for an exception that is a bug."""
    message = out_of_memory_message(exc)
    if message is None and isinstance(exc, OSError) and exc.strerror and exc.filename is not None:
        message = f"{exc.filename}: {exc.strerror}"
        if exc.filename2 is not None:
            message += f" ({exc.filename2})"
    elif message is None and isinstance(exc, (ValueError, CLIError, OSError)):
        message = str(exc) or type(exc).__name__
    if message is None:
        return None
    return " ".join(line.strip() for line in message.splitlines() if line.strip())  # one line, always


def cli_main(interrupted: str = "interrupted") -> Callable[[Callable[..., int]], Callable[..., int]]:
    """Decorator of ``main(argv) -> int``: clear errors become ``error: ...`` and 2, Ctrl-C one line and 130.

    The Ctrl-C line is the message a ``KeyboardInterrupt`` was raised with (a script re-raises one to say what
    survives, e.g. "rerun with --resume"), else ``interrupted``.
    """

    def wrap(main: Callable[..., int]) -> Callable[..., int]:
        @functools.wraps(main)
        def run(argv: Sequence[str] | None = None) -> int:
            try:
                return main(argv)
            except KeyboardInterrupt as exc:
                print(str(exc) or interrupted, file=sys.stderr)
                return EXIT_INTERRUPTED
            except Exception as exc:
                message = error_message(exc)
                if message is None:
                    raise  # a bug: keep the traceback
                print(f"error: {message}", file=sys.stderr)
                return EXIT_ERROR

        return run

    return wrap


def _nearest_existing(path: Path) -> Path:
    for parent in path.parents:
        if parent.exists():
            return parent
    return Path(".")


def _check_folder_writable(path: Path, flag: str) -> None:
    """CLIError unless files can be created in the nearest existing folder at or above ``path``."""
    folder = path if path.is_dir() else _nearest_existing(path)
    if not folder.is_dir():
        raise CLIError(f"{flag} {path}: {folder} is a file, not a folder")
    try:
        with tempfile.TemporaryFile(dir=folder):  # the one reliable test (os.access ignores root, read-only mounts)
            pass
    except OSError as exc:
        raise CLIError(f"{flag} {path}: cannot create files in {folder} ({exc.strerror or exc})") from None


def check_output_file(path: str | os.PathLike, flag: str, example: str = "out.json") -> None:
    """Before long work starts: CLIError unless ``path`` can become a file (not a folder, its folder writable);
    ``example`` is the file name the message suggests inside a folder."""
    path = Path(path)
    if path.is_dir():
        raise CLIError(f"{flag} {path} is a folder; give a file path such as {path / example}")
    _check_folder_writable(path, flag)


def check_output_folder(path: str | os.PathLike, flag: str) -> None:
    """Before long work starts: CLIError unless ``path`` is, or can become, a writable folder."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise CLIError(f"{flag} {path} is a file; give a folder")
    _check_folder_writable(path, flag)
