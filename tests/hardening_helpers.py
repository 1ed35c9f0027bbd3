"""Helpers that the hardening test files share (tests/test_files_*.py, tests/test_entry_*.py): run a call that
could hang on a FIFO with a timeout, make a FIFO, call an entry point's ``main`` and check its one ``error:`` line.

Not a test module (no ``test_`` prefix); tests/test_build_commands.py, tests/test_entry_points.py and
tests/test_nav_replay.py reach ``_call`` and ``_one_error`` through tests/test_cli_errors.py, which re-exports them.
"""

from __future__ import annotations

import os
import stat
import subprocess
import sys
import threading
from pathlib import Path

import pytest


def _quick(fn, *args, timeout: float = 20.0, **kwargs):
    """``fn(*args, **kwargs)`` in a thread: its result, or the exception it raised; a failed test (never a hung
    suite) when it does not return within ``timeout`` seconds (a FIFO opened blocking, an endless read)."""
    out: dict = {}

    def run() -> None:
        try:
            out["value"] = fn(*args, **kwargs)
        except BaseException as exc:  # noqa: BLE001 -- handed to the test
            out["error"] = exc

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    thread.join(timeout)
    if thread.is_alive():
        _unblock(args)
        pytest.fail(f"{getattr(fn, '__name__', fn)} did not return within {timeout} s (it blocks on a special file)")
    if "error" in out:
        raise out["error"]
    return out.get("value")


def _unblock(args) -> None:
    """Open each FIFO among ``args`` for writing without blocking, so a reader stuck opening it returns."""
    for arg in args:
        try:
            if isinstance(arg, (str, Path)) and stat.S_ISFIFO(os.stat(arg).st_mode):
                os.close(os.open(arg, os.O_RDWR | os.O_NONBLOCK))
        except OSError:
            pass


def _fifo(path: Path) -> Path:
    """A FIFO (named pipe) made at ``path``."""
    os.mkfifo(path)
    return path


def _call(main, argv: list[str]) -> int:
    """An entry point's exit status, whether it returns it or raises SystemExit (argparse; a string: 1)."""
    try:
        return main(argv)
    except SystemExit as exc:
        return exc.code if isinstance(exc.code, int) else 1


def _one_error(capsys, *needles: str) -> str:
    """stderr is exactly one line ``error: ...`` containing every needle; returns it."""
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1, err
    assert "Traceback" not in err
    for needle in needles:
        assert needle in err, err
    return err


def _build(out: Path, *extra: str, command: str = "maxflow") -> list[str]:
    """``precompute.build`` flags for a tiny random-walk table (2 levels) written to ``out``."""
    report = ["--no-report"] if command != "set" else []
    return [command, "--system", "random_walk_1d", "--horizon", "2", "--out", str(out), "--quiet", *report, *extra]


def _dead_pid() -> int:
    """The id of a process that has exited (a lock holder that died)."""
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid
