"""run_jobs' worker processes die with their parent: a parent killed hard (kill -9) leaves no orphaned worker nor
multiprocessing resource tracker behind (precompute.parallel)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.skipif(not Path("/proc/self/stat").is_file(), reason="reads processes from /proc (Linux)")

JOB = '''
import os, time
from pathlib import Path

def nap(folder, seconds):
    Path(folder, f"{os.getpid()}.pid").write_text("")
    time.sleep(seconds)
'''

PARENT = ("import sys, job; from precompute.parallel import run_jobs; "
          "run_jobs(job.nap, [(sys.argv[1], 300)] * 2, workers=2)")


def _stat(pid: int) -> tuple[int, str, str] | None:
    """``(parent pid, state, start time)`` of a process, None when it is gone."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = text[text.rindex(")") + 2:].split()  # after the command name, which may hold spaces
    return int(fields[1]), fields[0], fields[19]


def _children(pid: int) -> dict[int, str]:
    """The live children of ``pid``: their start times (a pid reused later is another process)."""
    out = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            st = _stat(int(entry.name))
            if st is not None and st[0] == pid and st[1] not in "ZX":
                out[int(entry.name)] = st[2]
    return out


def _alive(pid: int, start: str) -> bool:
    st = _stat(pid)
    return st is not None and st[1] not in "ZX" and st[2] == start  # a zombie has exited


def _cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
    except OSError:
        return ""


def test_workers_and_resource_tracker_exit_when_the_parent_is_killed(tmp_path):
    (tmp_path / "job.py").write_text(JOB)
    pids = tmp_path / "pids"
    pids.mkdir()
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")])}
    parent = subprocess.Popen([sys.executable, "-c", PARENT, str(pids)], env=env)
    children: dict[int, str] = {}
    try:
        deadline = time.monotonic() + 120  # two spawned interpreters importing the library, on a busy machine
        while len(list(pids.iterdir())) < 2:
            assert parent.poll() is None, f"the parent exited early ({parent.returncode})"
            assert time.monotonic() < deadline, "the workers did not start"
            time.sleep(0.2)
        workers = {int(p.stem) for p in pids.iterdir()}
        children = _children(parent.pid)
        assert workers <= set(children)
        trackers = [c for c in children if "resource_tracker" in _cmdline(c)]
        assert trackers, f"no resource tracker among the parent's children: {[_cmdline(c) for c in children]}"

        parent.send_signal(signal.SIGKILL)  # no cleanup runs in the parent
        parent.wait()
        deadline = time.monotonic() + 15
        while any(_alive(c, s) for c, s in children.items()) and time.monotonic() < deadline:
            time.sleep(0.2)
        left = {c: _cmdline(c) for c, s in children.items() if _alive(c, s)}
        assert not left, f"still running after their parent was killed: {left}"
    finally:  # a failed run must not leave its sleepers behind
        if parent.poll() is None:
            parent.kill()
            parent.wait()
        for c, s in children.items():
            if _alive(c, s):
                os.kill(c, signal.SIGKILL)
