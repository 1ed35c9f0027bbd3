"""``python -m precompute.build``: bad flags and values (exit code 2 and one ``error:`` line, never a
traceback), outputs that are devices, runaway ``--starts`` grids (``STARTS_GRIDS`` of tests/cases.py, which
.ci/attack.py also runs), full disks, allocation failures, conflicting flags, Ctrl-C, resumes with changed settings
and locks. Entry points run in-process through ``main(argv)``; tables are tiny (random walk, 1-3 levels)."""

from __future__ import annotations

import errno
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from cases import STARTS_GRIDS
from hardening_helpers import _build, _call, _dead_pid, _one_error

import eval.paper.coverage as eval_coverage
import precompute.build as build
import precompute.flow.builder as builder
import precompute.one_table as one_table
import precompute.system_args as system_args
from cuniform_torch.common import fileio
from cuniform_torch.tables.file import read_table
from precompute.build import main as build_main

pytestmark = pytest.mark.usefixtures("restore_threads")


def _cli(tmp_path: Path, *args: str) -> tuple[list[str], Path]:
    out = tmp_path / "t.npz"
    return ["--out", str(out), "--quiet", "--no-report", *args], out


def _exit_code(main, argv) -> int:
    """``main(argv)``'s exit code: its return value, or argparse's exit for a flag value refused as it parses."""
    try:
        return main(argv)
    except SystemExit as exc:
        return exc.code


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


# ------------------------------------------------------------------------------------------------ bad flags and values

@pytest.mark.parametrize("args, match", [
    (["--system", "nope"], r"unknown system 'nope'; known systems: .*dubins"),
    (["--system", "dubins", "--horizon", "0"], r"argument --horizon: must be an integer in \[1, 1000\].*got 0"),
    (["--system", "dubins", "--horizon", "-2"], r"argument --horizon: must be an integer in \[1, 1000\]"),
    (["--system", "dubins", "--horizon", "1", "--cell-size", "0", "0.05", "0.157"], r"dubins: cell_size must be positive"),
    (["--system", "dubins", "--horizon", "1", "--cell-size", "0.05", "0.05"], r"dubins: cell_size needs 3 value\(s\)"),
    (["--system", "dubins", "--horizon", "1", "--cell-size", "0.05", "0.05", "0.3"], r"angle cell size must divide 2\*pi"),
    (["--system", "random_walk_1d", "--speed", "2"], r"system 'random_walk_1d' has no parameter\(s\) speed"),
    (["--system", "random_walk_1d", "--max-omega", "1"], r"system 'random_walk_1d' has no parameter\(s\) max_omega"),
    (["--system", "dubins", "--max-speed", "1"], r"system 'dubins' has no parameter\(s\) max_speed"),
    (["--system", "dubins", "--horizon", "1", "--num-actions", "0"], r"argument --num-actions: must be an integer in"),
    (["--system", "dubins", "--horizon", "1", "--dt", "0"], r"dubins: dt must be a positive number"),
    (["--system", "dubins", "--horizon", "1", "--cell-offset", "0", "0", "0.5"], r"\|offset\| < 0\.5"),
    (["--system", "random_walk_1d", "--horizon", "1", "--points", "random", "--points-per-cell", "0"],
     r"argument --points-per-cell: must be an integer in"),
])
def test_cli_bad_input(tmp_path, capsys, args, match):
    argv, out = _cli(tmp_path, *args)
    assert _exit_code(build_main, argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: "), err
    assert re.search(match, err), err
    assert "Traceback" not in err
    assert not out.exists()


def test_cli_bad_flag_value_is_an_argparse_error(tmp_path, capsys):
    argv, out = _cli(tmp_path, "--system", "dubins", "--horizon", "abc")
    with pytest.raises(SystemExit) as info:
        build_main(argv)
    assert info.value.code == 2
    assert "argument --horizon: invalid int value: 'abc'" in capsys.readouterr().err
    assert not out.exists()


def test_cli_valid_control(tmp_path, capsys):
    """The same flags with good values do build (so the failures above are about the values)."""
    argv, out = _cli(tmp_path, "--system", "random_walk_1d", "--horizon", "1")
    assert build_main(argv) == 0
    assert read_table(out).horizon == 1


def test_cli_out_is_a_directory(tmp_path, capsys):
    out = tmp_path / "adir"
    out.mkdir()
    rc = build_main(["--out", str(out), "--quiet", "--no-report", "--system", "random_walk_1d", "--horizon", "1"])
    assert rc == 2
    assert re.search(r"error: .*adir", capsys.readouterr().err)


def test_cli_out_parent_is_a_file(tmp_path, capsys):
    (tmp_path / "afile").write_text("x")
    out = tmp_path / "afile" / "t.npz"
    rc = build_main(["--out", str(out), "--quiet", "--no-report", "--system", "random_walk_1d", "--horizon", "1"])
    assert rc == 2
    assert re.search(r"error: .*afile", capsys.readouterr().err)


def test_cli_bad_device(tmp_path, capsys):
    out = tmp_path / "t.npz"
    rc = _exit_code(build_main, ["--out", str(out), "--quiet", "--system", "random_walk_1d", "--horizon", "1",
                                 "--rollouts", "10", "--device", "nope"])
    assert rc == 2
    assert re.search(r"error: .*device.*nope", capsys.readouterr().err)


# -------------------------------------------------------------------------------------------- outputs that are devices

def test_build_to_a_device_is_one_line_and_leaves_it_a_device(tmp_path, capsys):
    from precompute.build import main

    out = tmp_path / "null.npz"  # a link to /dev/null, not the device: a regression never replaces /dev/null
    out.symlink_to("/dev/null")
    assert main(["--system", "random_walk_1d", "--horizon", "3", "--quiet", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"error: --out {out} is a character device (through a symlink)" in err
    assert out.is_symlink() and not (tmp_path / "null.report.json").exists()


# ---------------------------------------------------------------------------------------------- runaway --starts grids

@pytest.mark.parametrize("spec, count", STARTS_GRIDS)
def test_a_starts_grid_over_the_limit_is_refused_before_any_work(tmp_path, capsys, monkeypatch, spec, count):
    import time

    import precompute.build
    from precompute.build import main

    def never(*args, **kwargs):
        raise AssertionError("the set was built")

    monkeypatch.setattr(precompute.build, "build_table_set", never)  # a regression fails here, never builds

    begin = time.perf_counter()
    assert main(["--system", "random_walk_1d", "--horizon", "3", "--quiet", "--starts", spec,
                 "--out", str(tmp_path / "set")]) == 2
    err = capsys.readouterr().err
    assert f"--starts names {count} starts, more than the limit of 10,000" in err and "--no-limit" in err
    assert time.perf_counter() - begin < 5.0 and not (tmp_path / "set").exists()
    from cuniform_torch import make_system
    from precompute.table_set import parse_starts

    assert len(parse_starts("0=-1:1:20001", make_system("random_walk_1d"), limit=None)) == 20001  # --no-limit


def test_no_limit_without_starts_is_refused(tmp_path, capsys):
    from precompute.build import main

    assert main(["--system", "random_walk_1d", "--no-limit", "--out", str(tmp_path / "t.npz")]) == 2
    assert "give --starts too" in capsys.readouterr().err


# -------------------------------------------------------------------------------- errors, full disks, locks and Ctrl-C

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


def test_argparse_errors_are_one_line(tmp_path, capsys):
    assert _call(build.main, _build(tmp_path / "t.npz", "--horizon", "abc")) == 2
    _one_error(capsys, "--horizon", "invalid int value")
    assert _call(eval_coverage.main, ["--no-such-flag"]) == 2
    _one_error(capsys, "--no-such-flag")


# ------------------------------------------------------------------------------ the wrapper: a bug keeps its traceback

def test_a_bug_keeps_its_traceback():
    from precompute.cli import cli_main

    @cli_main()
    def main(argv=None) -> int:
        raise KeyError("a bug")

    with pytest.raises(KeyError):
        main([])
