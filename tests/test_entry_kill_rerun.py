"""Signals and dead workers, for every command with worker processes (issue 38, scope 4): a Ctrl-C of
a run is handled by the parent alone (no worker prints a KeyboardInterrupt traceback, the workers end at once and
none is left), a worker that dies is one clear error, and the kill-and-rerun harness (``.ci/kill_rerun.py``)
compares what it should. The harness itself (minutes) is run by hand; its table is in docs/results/hardening.md."""

from __future__ import annotations

import importlib.util
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


SLOW_MODULE = """
import os, time
time.sleep(float(os.environ.get("SLOW_IMPORT", "0")))  # a worker importing its job's module (seconds, like torch)

def job(seconds):
    time.sleep(seconds)
    return seconds
"""


PARENT = """
import os, sys, time
from precompute.parallel import run_jobs
import slow_job
os.environ["SLOW_IMPORT"] = sys.argv[1]  # the spawned workers' import of slow_job takes this long
print("ready", flush=True)
try:
    run_jobs(slow_job.job, [(60,), (60,), (60,)], workers=2)
except KeyboardInterrupt:
    print("interrupted", file=sys.stderr)
    sys.exit(130)
"""


def _session_processes(sid: int) -> list[int]:
    """Live (not zombie) processes of the session ``sid`` (a run started with ``start_new_session``)."""
    found = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/stat", "rb") as fh:
                    fields = fh.read().rsplit(b")", 1)[1].split()
            except OSError:
                continue
            if int(fields[3]) == sid and fields[0] != b"Z":  # fields after the name: state, ppid, pgrp, session
                found.append(int(entry))
    return found


def _harness():
    spec = importlib.util.spec_from_file_location("kill_rerun", ROOT / ".ci" / "kill_rerun.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up while the class is made
    spec.loader.exec_module(module)
    return module


# ---------------------------------------------------------------------------------------------------- workers that die

def test_a_worker_that_dies_is_one_clear_error_not_a_broken_pool_traceback():
    from precompute.cli import error_message
    from precompute.parallel import WorkerDiedError, run_jobs

    with pytest.raises(WorkerDiedError) as err:
        run_jobs(os.abort, [(), ()], workers=2)  # each worker dies by a signal, as the OOM killer's SIGKILL does
    line = error_message(err.value)
    assert line is not None and "a worker process died" in line and "rerun to resume" in line


# ---------------------------------------------------------------------------------------- Ctrl-C and SIGTERM of a pool

@pytest.mark.slow  # a pool, interrupted (pytest --durations: 17.3 s at load 11, 2-4 s at 3)
@pytest.mark.skipif(not hasattr(signal, "pthread_sigmask"), reason="POSIX signals")
@pytest.mark.parametrize("target, slow_import, after", [("group", "20", 2.0), ("parent", "0", 4.0)])
def test_a_ctrl_c_of_a_pool_is_the_parents_alone(tmp_path, target, slow_import, after):
    """Ctrl-C sent to the terminal's process group while the workers import their job's module (they printed one
    KeyboardInterrupt traceback each), or SIGINT sent to the parent alone while the workers run 60 s jobs (the
    parent waited for them): one line, exit 130, within seconds, and no worker left."""
    (tmp_path / "slow_job.py").write_text(SLOW_MODULE)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), str(tmp_path)]))
    proc = subprocess.Popen([sys.executable, "-c", PARENT, slow_import], cwd=tmp_path, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "ready"
        time.sleep(after)
        (os.killpg if target == "group" else os.kill)(proc.pid, signal.SIGINT)
        t0 = time.time()
        try:
            _, err = proc.communicate(timeout=15)
        except subprocess.TimeoutExpired:
            pytest.fail("the run did not end within 15 s of Ctrl-C (it waits for its workers' jobs)")
        took = time.time() - t0
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    left = []
    for _ in range(30):  # a worker of a dead parent notices within 0.25 s
        left = _session_processes(proc.pid)
        if not left:
            break
        time.sleep(0.1)
    for pid in left:
        os.kill(pid, signal.SIGKILL)
    assert proc.returncode == 130 and err.strip() == "interrupted", err
    assert "Traceback" not in err and took < 10, (took, err)
    assert not left, f"processes left: {left}"


@pytest.mark.slow  # a pool, terminated (pytest --durations: 5.1 s at load 3)
@pytest.mark.skipif(not hasattr(signal, "raise_signal"), reason="POSIX signals")
def test_a_sigterm_of_a_pools_parent_ends_the_workers_first_and_still_dies_of_it(tmp_path):
    """``kill PID`` of a run with workers (the parent alone): it died at once and left its workers mid-job (a
    ``ConnectionResetError`` traceback from one mid-handshake, the resource tracker's "leaked semaphore" warning);
    now the workers are ended and the pool shut down first, and the process still dies of SIGTERM."""
    (tmp_path / "slow_job.py").write_text(SLOW_MODULE)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), str(tmp_path)]))
    proc = subprocess.Popen([sys.executable, "-c", PARENT, "0"], cwd=tmp_path, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "ready"
        time.sleep(4.0)  # the workers run their 60 s jobs
        os.kill(proc.pid, signal.SIGTERM)
        _, err = proc.communicate(timeout=15)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    time.sleep(1.0)
    left = _session_processes(proc.pid)
    for pid in left:
        os.kill(pid, signal.SIGKILL)
    assert proc.returncode == -signal.SIGTERM, (proc.returncode, err)
    assert "Traceback" not in err and "leaked" not in err, err
    assert not left, f"processes left: {left}"


# ------------------------------------------------------------------------------------------------ the harness's checks

def test_the_harness_sees_a_lost_a_duplicated_and_a_changed_record(tmp_path):
    kr = _harness()

    def folder(name: str, records: list[dict]) -> Path:
        out = tmp_path / name
        out.mkdir()
        (out / "settings.json").write_text(json.dumps({"suite": "clutter", "seed": 0}))
        (out / "episodes.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))
        return out

    a = {"key": "clutter/0/mppi_1.0/32/0", "outcome": "goal", "steps": 10, "wall_s": 1.0, "cycle_hist": {"7": 10}}
    b = {"key": "clutter/1/mppi_1.0/32/0", "outcome": "collision", "steps": 4, "wall_s": 0.5}
    ref = kr.fp_navigate(folder("ref", [a, b]))
    assert kr.differences(ref, kr.fp_navigate(folder("same", [b, {**a, "wall_s": 9.0, "cycle_hist": {}}]))) == []
    assert kr.differences(ref, kr.fp_navigate(folder("lost", [a]))) == [f"lost record {b['key']}"]
    dup = kr.differences(ref, kr.fp_navigate(folder("dup", [a, b, a])))
    assert dup == [f"extra duplicated records: {a['key']}"]
    assert kr.differences(ref, kr.fp_navigate(folder("changed", [a, {**b, "steps": 5}]))) == [
        f"record {b['key']} differs"]


def test_the_harness_finds_locks_and_temporary_files(tmp_path):
    kr = _harness()
    out = tmp_path / "out"
    (out / "runs").mkdir(parents=True)
    (out / "p.pt").write_bytes(b"x")
    assert kr.leftover_files(out) == []
    (out / "p.pt.lock").write_text("1 host\n")
    (out / ".p.pt.123-host.abcdefgh.tmp").write_bytes(b"")
    (out / "runs" / ".lock").write_text("")
    assert kr.leftover_files(out) == ["out/.p.pt.123-host.abcdefgh.tmp", "out/p.pt.lock", "out/runs/.lock"]


def test_the_quick_plan_tries_every_signal_and_target_and_every_moment():
    kr = _harness()
    quick, full = kr.plan(quick=True), kr.plan(quick=False)
    assert len(full) == 18 and len(set(full)) == 18
    assert {(s, t) for s, t, _ in quick} == {(s, t) for s, t, _ in full} and len(quick) == 6
    assert {m for _, _, m in quick} == set(kr.MOMENTS)
