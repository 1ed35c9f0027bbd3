"""Every error path of every ``python -m`` entry point: one line ``error: ...`` on stderr and exit code 2; Ctrl-C
one line and 130; never a traceback. Plus what keeps two runs, a killed run or a full disk from hurting the next.

Entry points run in-process through ``main(argv)``; a subprocess only where a signal is needed. Tables are tiny
(random walk, 2-3 levels).
"""

from __future__ import annotations

import errno
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

import eval.bench.maxflow as bench_maxflow
import eval.paper.coverage as eval_coverage
import eval.paper.uniformity as eval_uniformity
import eval.report as eval_report
import precompute.build as build
import precompute.flow.builder as builder
import precompute.one_table as one_table
import precompute.system_args as system_args
import training.distill as distill
from cuniform_torch.common import fileio
from cuniform_torch.systems import _REGISTRY
from cuniform_torch.tables.file import read_table

REPO = Path(__file__).resolve().parents[1]
TINY_DISTILL = ["--quiet", "--epochs", "1", "--hidden", "8", "--layers", "1", "--jitter", "1", "--batch-size", "64",
                "--eval-samples", "16", "--eval-every", "1000"]


@pytest.fixture(scope="module", autouse=True)
def restore_threads():
    """distill sets torch's thread count; give the other test modules theirs back."""
    threads = torch.get_num_threads()
    yield
    torch.set_num_threads(threads)


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
    report = ["--no-report"] if command != "set" else []
    return [command, "--system", "random_walk_1d", "--horizon", "2", "--out", str(out), "--quiet", *report, *extra]


@pytest.fixture(scope="module")
def walk_path(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("tables") / "walk.npz"
    assert build.main(_build(out)) == 0
    return out


def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


# ------------------------------------------------------------------------------------------ build

def test_build_system_that_is_not_a_factory(tmp_path, capsys):
    assert build.main(_build(tmp_path / "t.npz", "--system", "os:getpid")) == 2
    _one_error(capsys, "--system os:getpid", "not a System factory")


def test_build_unwritable_out_fails_before_building(tmp_path, capsys):
    if not Path("/proc/1").is_dir():
        pytest.skip("needs /proc (no file can be created in /proc/1, even as root)")
    assert build.main(_build(Path("/proc/1/t.npz"))) == 2
    _one_error(capsys, "--out /proc/1/t.npz", "cannot create files in /proc/1")


def test_build_huge_num_actions(tmp_path, capsys):
    out = tmp_path / "d.npz"
    # refused by the system's own check, before anything is allocated
    assert build.main(["maxflow", "--system", "dubins", "--horizon", "2", "--param", f"num_actions={10**12}",
                       "--out", str(out), "--quiet", "--no-report"]) == 2
    _one_error(capsys, "num_actions", str(10**12))
    assert not out.exists()


def test_build_allocation_failure_is_one_line(tmp_path, capsys, monkeypatch):
    def alloc_fails(name, **params):
        raise RuntimeError("[enforce fail at alloc_cpu.cpp:127] err == 0. DefaultCPUAllocator: can't allocate "
                           "memory: you tried to allocate 8000000000000 bytes. Error code 12 (Cannot allocate memory)")

    monkeypatch.setattr(system_args, "make_system", alloc_fails)
    assert build.main(_build(tmp_path / "t.npz")) == 2
    _one_error(capsys, "out of memory", "8e+03 GB", "--param num_actions=N")


def test_build_full_disk_on_the_final_write_keeps_the_levels(tmp_path, capsys, monkeypatch):
    out = tmp_path / "t.npz"

    def full_disk(path, table):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(one_table, "write_table", full_disk)
    assert build.main(_build(out)) == 2
    _one_error(capsys, "No space left on device", str(out), "--resume")
    monkeypatch.undo()
    assert build.main(_build(out, "--resume")) == 0  # the checkpointed levels are reused
    assert read_table(out).horizon == 2


def test_build_full_disk_on_a_checkpoint_names_the_file(tmp_path, capsys, monkeypatch):
    import zipfile

    def full_disk(self, *args, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(zipfile.ZipFile, "writestr", full_disk)
    assert build.main(_build(tmp_path / "t.npz")) == 2
    _one_error(capsys, "No space left on device", "step_0000.npz")
    assert not [p for p in (tmp_path / "t.npz.partial").iterdir() if p.suffix == ".tmp"]


@pytest.mark.parametrize("command, extra, flags", [
    ("coverage", ["--steps", "2", "--resume"], ["--resume is not a flag of coverage", "maxflow"]),
    ("coverage", ["--steps", "2", "--points", "lattice"], ["--points is not a flag of coverage"]),
    ("maxflow", ["--points-per-cell", "5"], ["--points-per-cell", "--points centers"]),
    ("maxflow", ["--points", "lattice", "--points-per-cell", "4"], ["--points-per-cell", "--points lattice"]),
    ("maxflow", ["--steps", "10"], ["--steps is not a flag of maxflow", "coverage"]),
    ("maxflow", ["--rollouts", "10"], ["--rollouts", "--no-report"]),
    ("maxflow", ["--num-actions", "3"], ["--num-actions is a system parameter", "--param num_actions="]),
    ("set", ["--starts", "0=-1:1:2", "--steps", "3"], ["--steps", "coverage method only", "--method coverage"]),
    ("set", ["--starts", "0=-1:1:2", "--method", "coverage", "--resume"], ["--resume", "maxflow method only"]),
    ("set", [], ["set needs --starts"]),
    ("safe", [], ["safe needs --map"]),
    ("maxflow", ["--starts", "0=-1:1:2"], ["--starts is not a flag of maxflow", "set"]),
    (None, ["--method", "coverage", "--steps", "2", "--resume"], ["--resume is not a flag of coverage"]),  # old
])
def test_build_conflicting_flags_are_refused(tmp_path, capsys, command, extra, flags):
    out = tmp_path / "t.npz"
    argv = _build(out, *extra, command=command or "maxflow")
    assert _call(build.main, argv if command else argv[1:]) == 2
    _one_error(capsys, *flags)
    assert not out.exists()


def _interrupted_build(out: Path, monkeypatch, *extra: str) -> None:
    """A build of 3 levels interrupted after its first level (its checkpoint stays)."""
    real, calls = builder._solve_step, {"n": 0}

    def interrupting(*a, **k):
        calls["n"] += 1
        if calls["n"] == 2:
            raise KeyboardInterrupt
        return real(*a, **k)

    monkeypatch.setattr(builder, "_solve_step", interrupting)
    assert build.main(["maxflow", "--system", "dubins", "--horizon", "3", "--out", str(out), "--quiet",
                       "--no-report", *extra]) == 130
    monkeypatch.setattr(builder, "_solve_step", real)


def test_build_ctrl_c_is_one_line(tmp_path, capsys, monkeypatch):
    _interrupted_build(tmp_path / "d.npz", monkeypatch)
    err = capsys.readouterr().err
    assert err.startswith("interrupted") and err.count("\n") == 1 and "--resume" in err, err


@pytest.mark.parametrize("changed, message", [
    (["--horizon", "4"], "--horizon was 3, now 4"),
    (["--param", "num_actions=7"], "--param num_actions was 5, now 7"),
    (["--points", "lattice"], "--points was 'centers', now 'lattice'"),
])
def test_build_resume_with_changed_settings_is_refused(tmp_path, capsys, monkeypatch, changed, message):
    out = tmp_path / "d.npz"
    _interrupted_build(out, monkeypatch)
    capsys.readouterr()
    argv = ["maxflow", "--system", "dubins", "--horizon", "3", "--out", str(out), "--quiet", "--no-report", "--resume"]
    assert build.main(argv + changed) == 2  # later flags win: the changed value
    _one_error(capsys, message, "--resume")
    assert not out.exists()
    assert build.main(argv) == 0  # the old settings still resume


def test_build_refuses_an_out_another_live_process_writes(tmp_path, capsys):
    out = tmp_path / "t.npz"
    holder = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        lock = tmp_path / "t.npz.lock"
        lock.write_text(f"{holder.pid} {fileio._HOST}\n")
        assert build.main(_build(out)) == 2
        _one_error(capsys, f"process {holder.pid}", str(lock))
        assert not out.exists() and lock.exists()
    finally:
        holder.kill()
        holder.wait()


def test_build_takes_over_the_lock_of_a_dead_process(tmp_path):
    out, lock = tmp_path / "t.npz", tmp_path / "t.npz.lock"
    lock.write_text(f"{_dead_pid()} {fileio._HOST}\n")
    assert build.main(_build(out)) == 0
    assert out.exists() and not lock.exists()


def test_lock_is_exclusive_within_a_run(tmp_path):
    from cuniform_torch.common.fileio import FileLockedError, exclusive_lock

    lock = tmp_path / "x.lock"
    with exclusive_lock(lock, what="x"):
        assert lock.read_text().split()[0] == str(os.getpid())
        with pytest.raises(FileLockedError, match=r"x is being written by process"):
            with exclusive_lock(lock, what="x"):
                pass
    assert not lock.exists()


def test_argparse_errors_are_one_line(tmp_path, capsys):
    assert _call(build.main, _build(tmp_path / "t.npz", "--horizon", "abc")) == 2
    _one_error(capsys, "--horizon", "invalid int value")
    assert _call(eval_coverage.main, ["--no-such-flag"]) == 2
    _one_error(capsys, "--no-such-flag")


# ------------------------------------------------------------------------------------------ stale temp files

def test_a_killed_writer_leaves_a_temp_file_that_the_next_write_removes(tmp_path):
    dest = tmp_path / "t.json"
    script = ("import os, signal, sys\nfrom cuniform_torch.common.fileio import atomic_path\n"
              "with atomic_path(sys.argv[1]) as tmp:\n    tmp.write_bytes(b'half')\n"
              "    os.kill(os.getpid(), signal.SIGKILL)\n")
    proc = subprocess.run([sys.executable, "-c", script, str(dest)], cwd=REPO)
    assert proc.returncode == -signal.SIGKILL
    orphans = [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]
    assert len(orphans) == 1 and not dest.exists()
    # a temp file of a live writer (this process) of the same destination, and one of another destination
    live = tmp_path / f".t.json.{os.getpid()}-{fileio._HOST}.abcdefgh.tmp"
    other = tmp_path / f".u.json.{_dead_pid()}-{fileio._HOST}.abcdefgh.tmp"
    live.write_text("x")
    other.write_text("x")
    fileio.write_json(dest, {"a": 1})
    assert json.loads(dest.read_text()) == {"a": 1}
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([dest.name, live.name, other.name])


def test_an_old_style_temp_file_is_removed_once_it_is_old(tmp_path):
    dest = tmp_path / "t.npz"
    young, old = tmp_path / ".t.npz.abcdefgh.tmp", tmp_path / ".t.npz.zyxwvuts.tmp"
    young.write_text("x")
    old.write_text("x")
    past = time.time() - 7 * 24 * 3600
    os.utime(old, (past, past))
    fileio.write_bytes(dest, b"data")
    assert young.exists() and not old.exists()


# ------------------------------------------------------------------------------------------ distill

def _distill(walk: Path, folder: Path, *extra: str) -> list[str]:
    return ["--tables", str(walk), "--out", str(folder / "p.pt"), "--logdir", str(folder / "runs"), *TINY_DISTILL,
            *extra]


def test_distill_out_that_is_a_folder_fails_before_training(walk_path, tmp_path, capsys):
    (tmp_path / "adir").mkdir()
    argv = _distill(walk_path, tmp_path)
    argv[argv.index("--out") + 1] = str(tmp_path / "adir")
    assert distill.main(argv) == 2
    _one_error(capsys, "--out", "adir", "is a folder")
    assert not (tmp_path / "runs").exists()  # no training started


def test_distill_logdir_that_is_a_file(walk_path, tmp_path, capsys):
    argv = _distill(walk_path, tmp_path)
    (tmp_path / "runs").write_text("not a folder")
    assert distill.main(argv) == 2
    _one_error(capsys, "--logdir", "is a file")
    assert not (tmp_path / "p.pt").exists()


def test_distill_full_disk(walk_path, tmp_path, capsys, monkeypatch):
    def full_disk(self, data):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(Path, "write_bytes", full_disk)
    assert distill.main(_distill(walk_path, tmp_path)) == 2
    _one_error(capsys, "No space left on device", "p.pt.train.pt")
    assert not any(p.name.endswith(".tmp") for p in tmp_path.iterdir())


def test_distill_refuses_an_out_another_live_process_writes(walk_path, tmp_path, capsys):
    holder = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        (tmp_path / "p.pt.lock").write_text(f"{holder.pid} {fileio._HOST}\n")
        assert distill.main(_distill(walk_path, tmp_path)) == 2
        _one_error(capsys, f"process {holder.pid}")
    finally:
        holder.kill()
        holder.wait()


def test_distill_ctrl_c_is_one_line(walk_path, tmp_path):
    argv = _distill(walk_path, tmp_path)
    argv[argv.index("--epochs") + 1] = "100000"
    state = tmp_path / "p.pt.train.pt"
    proc = subprocess.Popen([sys.executable, "-m", "training.distill", *argv, "--patience", "100000"], cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        deadline = time.time() + 120
        while not state.exists() and proc.poll() is None and time.time() < deadline:
            time.sleep(0.1)
        assert state.exists(), proc.communicate()
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 130, err
    assert err.startswith("interrupted") and err.count("\n") == 1 and "--resume" in err, err
    assert not (tmp_path / "p.pt.lock").exists()


USER_MODULE = '''
import dataclasses, torch
from cuniform_torch.systems import register_system


@dataclasses.dataclass(frozen=True)
class Hopper:
    hop: float = 1.0
    dt: float = 1.0
    cell_size: tuple = (0.5,)
    cell_offset: tuple = (0.0,)
    name, periodic, se2_invariant = "cli_hopper", (False,), False

    def action_set(self, dtype=torch.float32, device=None):
        return torch.tensor([[-1.0], [0.0], [1.0]], dtype=dtype, device=device)

    def step(self, x, u):
        return x + u * self.hop

    def params(self):
        return {"hop": self.hop}


register_system("cli_hopper", Hopper)
'''


def test_distill_reads_a_user_table_after_system_module(tmp_path, capsys, monkeypatch):
    module = f"cli_user_{abs(hash(str(tmp_path))) % 10**8}"
    (tmp_path / f"{module}.py").write_text(USER_MODULE)
    monkeypatch.syspath_prepend(str(tmp_path))
    table = tmp_path / "hop.npz"
    assert build.main(["maxflow", "--system-module", module, "--system", "cli_hopper", "--horizon", "2", "--out", str(table),
                       "--quiet", "--no-report"]) == 0
    try:
        sys.modules.pop(module, None)  # as a fresh process: neither the module nor its system are known
        _REGISTRY.pop("cli_hopper", None)
        assert distill.main(_distill(table, tmp_path / "a")) == 2
        _one_error(capsys, "cli_hopper", "--system-module")
        assert distill.main(_distill(table, tmp_path / "b", "--system-module", module)) == 0
    finally:
        sys.modules.pop(module, None)
        _REGISTRY.pop("cli_hopper", None)


# ------------------------------------------------------------------------------------------ eval

def test_report_out_that_is_a_file_exits_2(tmp_path, capsys):
    (tmp_path / "afile").write_text("x")
    assert _call(eval_report.main, ["--quick", "--out", str(tmp_path / "afile"), "--runs", str(tmp_path / "r")]) == 2
    _one_error(capsys, "--out", "afile")


@pytest.mark.parametrize("main", [eval_coverage.main, eval_uniformity.main])
def test_eval_unknown_system_module(main, walk_path, capsys):
    assert _call(main, ["--quick", "--table", str(walk_path), "--system-module", "no_such_module_xyz"]) == 2
    _one_error(capsys, "--system-module no_such_module_xyz")


def test_eval_json_that_is_a_folder_fails_before_the_experiment(walk_path, tmp_path, capsys):
    assert _call(eval_coverage.main, ["--quick", "--table", str(walk_path), "--json", str(tmp_path)]) == 2
    _one_error(capsys, "--json", "is a folder")
    assert capsys.readouterr().out == ""  # nothing ran


def test_bench_maxflow_on_a_table_without_a_graph(tmp_path, capsys):
    out = tmp_path / "cov.npz"
    assert build.main(_build(out, "--steps", "2", command="coverage")) == 0
    assert _call(bench_maxflow.main, ["--table", str(out)]) == 2
    _one_error(capsys, "no flow graph")


# ------------------------------------------------------------------------------------------ the wrapper

def test_a_bug_keeps_its_traceback():
    from precompute.cli import cli_main

    @cli_main()
    def main(argv=None) -> int:
        raise KeyError("a bug")

    with pytest.raises(KeyError):
        main([])
