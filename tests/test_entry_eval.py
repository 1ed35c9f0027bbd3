"""The evaluation commands (``eval.navigate``, ``eval.bench``, ``eval.report``, ``eval.paper.*``,
``eval.bench.profile_split``): special inputs and outputs refused before any work, bad flags and paths as one
``error:`` line and exit code 2."""

from __future__ import annotations

import os
import stat

import pytest
from hardening_helpers import _build, _call, _fifo, _one_error, _quick

import eval.bench.maxflow as bench_maxflow
import eval.paper.coverage as eval_coverage
import eval.paper.uniformity as eval_uniformity
import eval.report as eval_report
import precompute.build as build
from cuniform_torch.common.fileio import (
    FileKindError,
)

pytestmark = [pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="POSIX special files"), pytest.mark.usefixtures("restore_threads")]




# ------------------------------------------------------------------------------------------ special inputs and outputs

@pytest.mark.parametrize("where", ["file", "set index", "set member"])
def test_the_benchmark_digests_its_inputs_from_regular_files_only(tmp_path, where):
    """eval.navigate's digest of an input (``_file_digest``: the settings record, ``eval.navigate.replay``'s check of
    a given --table) opens regular files only: a FIFO is one FileKindError naming it (it hung in ``open``)."""
    from eval.navigate.run import input_digest as _file_digest

    if where == "file":
        target = fifo = tmp_path / "table.npz"
    else:
        target = tmp_path / "set"
        target.mkdir()
        (target / "tables.json").write_text("{}")
        (target / "start_0000.npz").write_bytes(b"a member")
        fifo = target / ("tables.json" if where == "set index" else "start_0001.npz")
        fifo.unlink(missing_ok=True)
    os.mkfifo(fifo)
    with pytest.raises(FileKindError, match=f"{fifo}: an input file of the benchmark is a FIFO"):
        _quick(lambda _fifo: _file_digest(target), fifo, timeout=10.0)  # fifo: what _quick unblocks


def test_a_benchmark_out_that_is_a_device_is_refused_before_any_work(tmp_path, capsys, monkeypatch):
    """eval.navigate --out LINK->/dev/null: one line naming the device before the tasks are made (it made them,
    then said only "File exists"; under load the attack run saw it still at work after 30 s)."""
    import eval.navigate.run as nav_run

    out = tmp_path / "null"
    out.symlink_to("/dev/null")
    monkeypatch.setattr(nav_run, "make_tasks", lambda *a, **k: pytest.fail("work started before --out was checked"))
    assert nav_run.main(["--suite", "gaps", "--tasks", "1", "--methods", "mppi_1.0", "--budgets", "16",
                         "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"--out {out} is a character device (through a symlink)" in err, err
    assert out.is_symlink() and stat.S_ISCHR(os.stat("/dev/null").st_mode)


def test_eval_bench_reads_every_given_table_before_timing(tmp_path, capsys, monkeypatch, dubins_table):
    """eval.bench --table FIFO (the horizon-10 table): refused before any table is built or controller timed (it
    was read after the horizon-15 table's build and rows: 19 s and 635 MB), naming what is there."""
    import eval.bench.controllers as bench
    from cuniform_torch import write_table

    good = tmp_path / "t15.npz"
    write_table(good, dubins_table)
    fifo = _fifo(tmp_path / "t10.npz")
    monkeypatch.setattr(bench, "MPPI", lambda *a, **k: pytest.fail("a controller was timed before --table was read"))
    assert _quick(lambda _fifo: bench.main(["--table15", str(good), "--table", str(fifo), "--samples", "2"]), fifo,
                  timeout=60.0) == 2
    err = capsys.readouterr().err
    assert err.strip() == f"error: {fifo}: no table file there (a FIFO (named pipe))", err
    missing = tmp_path / "t15-missing.npz"  # a default to build: not before the given --table is read
    assert _quick(lambda _fifo: bench.main(["--table15", str(missing), "--table", str(fifo), "--samples", "2"]),
                  fifo, timeout=60.0) == 2
    assert not missing.exists()  # it built the horizon-15 table first (a 400 MB peak before the refusal)


def test_a_profile_that_is_a_fifo_is_refused(tmp_path, capsys):
    from eval.bench.profile_split import main

    fifo = _fifo(tmp_path / "run.prof")
    assert _quick(main, [str(fifo)]) == 2
    assert "a cProfile output is a FIFO" in capsys.readouterr().err


# ------------------------------------------------------------------------------------------------- bad flags and paths

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
