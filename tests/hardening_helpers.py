"""Helpers that the hardening test files share (tests/test_files_*.py, tests/test_entry_*.py): run a call that
could hang on a FIFO with a timeout, make a FIFO, call an entry point's ``main`` and check its one ``error:`` line,
flip a byte, forge an ``.npy`` header, make a confident untrained MLP.

Not a test module (no ``test_`` prefix); tests/test_build_commands.py, tests/test_entry_points.py and
tests/test_nav_replay.py reach ``_call`` and ``_one_error`` through tests/test_cli_errors.py, which re-exports them.
"""

from __future__ import annotations

import io
import os
import stat
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
import torch

from cuniform_torch.grid.cells import Grid
from cuniform_torch.policies import MLPSupport
from cuniform_torch.policies.mlp import MLPConfig, MLPPolicy, default_feature_scale

HORIZON = 3
"""the horizon of conftest's ``small_table`` (levels 1, 5, 13, 25)"""

EVIL_MODULE = """
from pathlib import Path
Path({import_marker!r}).write_text("imported")

def Car(**params):
    Path({call_marker!r}).write_text("called")
    raise RuntimeError("the factory ran")
"""
"""the module conftest's ``evil`` fixture writes: it leaves a marker file when imported and when its factory runs"""


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


def _flip_byte(value: np.ndarray) -> np.ndarray:
    """A copy of ``value`` with one bit of one byte in the middle of its data flipped."""
    out = np.array(value, copy=True)
    raw = out.reshape(-1).view(np.uint8)
    raw[len(raw) // 2] ^= 0x10
    return out


def _notes(err: str, path: Path) -> list[str]:
    """The lines of ``err`` that note ``path`` has no content digest."""
    return [line for line in err.splitlines() if line.startswith(f"note: {path} has no content digest")]


def _forged_member(name, shape, dtype, data=b"\0" * 64):
    """The bytes of a zip member ``name.npy`` whose header claims ``shape`` but which holds only ``data``."""
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, {"descr": np.lib.format.dtype_to_descr(np.dtype(dtype)),
                                               "fortran_order": False, "shape": shape})
    return buf.getvalue() + data


def _mlp(table, support: bool = False, fallback: str = "nearest") -> MLPPolicy:
    """A small untrained MLP over ``table`` whose logits are confident (one action gets almost all the mass)."""
    system = table.make_system()
    grid = Grid.of(system)
    centres = grid.centers(torch.from_numpy(table.cells))
    config = MLPConfig(state_dim=grid.dim, num_actions=table.actions.shape[0], horizon=table.horizon,
                       periodic=list(grid.periodic), feature_scale=default_feature_scale(centres, grid),
                       hidden=8, layers=1)
    sup = MLPSupport(torch.from_numpy(table.cells), torch.from_numpy(table.level_offsets)) if support else None
    model = MLPPolicy(config, system, torch.from_numpy(table.actions), support=sup, fallback=fallback).eval()
    with torch.no_grad():
        model.net[-1].bias.zero_()
        model.net[-1].bias[0] = 20.0  # confident everywhere: what the issue saw outside the table
    return model
