"""Table sets (a folder of tables and its ``tables.json`` index, ``load_table_set``): an index nested too
deeply, a special file, member names the system cannot use, runaway entry counts (``SET_INDEX_ABUSES`` of
tests/cases.py, which .ci/attack.py also runs), a set rebuilt or cached with other settings, and a cold cache shared
by two runs."""

from __future__ import annotations

import json
import os
import threading
from dataclasses import replace
from pathlib import Path

import pytest
from cases import DEEP, SET_MEMBER_NAMES, one_member_repeated, too_many_entries
from hardening_helpers import _fifo, _quick

from cuniform_torch.policies.table_set import load_table_set
from cuniform_torch.tables.file import TableError

pytestmark = pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="POSIX special files")


def _index(folder: Path, entries: list[dict]) -> None:
    (folder / "tables.json").write_text(json.dumps({"format": "cuniform-table-set/1", "system": "random_walk_1d",
                                                    "tables": entries}))


# ------------------------------------------------------------------------------------------------- the table-set index

def test_a_table_set_index_nested_too_deeply_is_one_error(tmp_path):
    (tmp_path / "tables.json").write_text(DEEP)
    with pytest.raises(TableError, match=r"tables.json: not a readable table-set index \(JSON nested too deep"):
        load_table_set(tmp_path)


# ------------------------------------------------------------------------------------------------- the table-set index

@pytest.mark.parametrize("target", ["fifo", "/dev/zero", "/dev/urandom"])
def test_a_table_set_index_that_is_a_special_file_is_one_clear_error(tmp_path, target):
    from cuniform_torch.policies.table_set import load_table_set
    from cuniform_torch.tables.file import TableError

    index = tmp_path / "tables.json"
    if target == "fifo":
        _fifo(index)
    else:
        index.symlink_to(target)
    with pytest.raises(TableError, match="not a regular file"):
        _quick(load_table_set, tmp_path)


@pytest.mark.parametrize("name, said", [pytest.param(n, s, id=i) for i, n, s in SET_MEMBER_NAMES])
def test_a_table_set_member_name_the_system_cannot_use_is_one_table_error(tmp_path, name, said):
    from cuniform_torch.policies.table_set import load_table_set
    from cuniform_torch.tables.file import TableError

    (tmp_path / "tables.json").write_text(json.dumps({"format": "cuniform-table-set/1", "system": "random_walk_1d",
                                                      "tables": [{"file": name, "start": [0.0]}]}))
    with pytest.raises(TableError, match=said):
        load_table_set(tmp_path)


# ------------------------------------------------------------------------------------------------- a rebuilt table set

@pytest.mark.parametrize("change, said", [(["--horizon", "5"], "horizon: 4 there, 5 now"),
                                          (["--num-actions", "3"], "num_actions: 5 there, 3 now"),
                                          (["--param", "dt=2"], "dt: 1"),
                                          (["--points", "random"], "points: 'centers' there, 'random' now")])
def test_a_table_set_rebuilt_with_other_settings_is_refused_not_kept_stale(tmp_path, capsys, change, said):
    from precompute.build import main

    base = ["--system", "random_walk_1d", "--horizon", "4", "--quiet", "--starts", "0=-1:1:3", "--out", str(tmp_path)]
    assert main(base) == 0
    index = (tmp_path / "tables.json").read_bytes()
    members = {p.name: p.read_bytes() for p in tmp_path.glob("start_*.npz")}
    capsys.readouterr()
    argv = [*base, *change]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "built with other settings" in err and said in err and "delete" in err
    assert (tmp_path / "tables.json").read_bytes() == index  # nothing rewritten
    assert {p.name: p.read_bytes() for p in tmp_path.glob("start_*.npz")} == members
    assert main(base) == 0  # the same settings still resume
    assert json.loads((tmp_path / "tables.json").read_text())["tables"][0]["file"] == "start_0000.npz"


@pytest.mark.parametrize("change, said", [(["--horizon", "5"], "horizon: 4 there, 5 now"),
                                          (["--param", "dt=2"], "dt: 1"),
                                          (["--starts", "0=-1:1.5:3"], "start_0001.npz: start [0.0] there, [0.25] now"),
                                          (["--points", "random"], "points: 'centers' there, 'random' now")])
def test_a_cached_table_set_of_other_settings_is_refused_not_used(tmp_path, change, said):
    """ensure_table_set (the caches of eval.start_aware and eval.mountain_car) checks a complete set like a rebuild
    does: a set in the folder built with other settings or starts is one ValueError, never handed back as theirs."""
    from precompute.build import parse_job
    from precompute.table_set import ensure_table_set

    base = ["--system", "random_walk_1d", "--horizon", "4", "--quiet", "--starts", "0=-1:1:3", "--out", str(tmp_path)]
    template, spec = parse_job(base)
    assert ensure_table_set(template, spec["starts"], tmp_path) == tmp_path
    files = {p.name: p.stat().st_mtime_ns for p in tmp_path.iterdir()}
    assert ensure_table_set(template, spec["starts"], tmp_path) == tmp_path  # the same settings: used as it is
    other, other_spec = parse_job([*base, *change])
    with pytest.raises(ValueError, match="built with other settings") as info:
        ensure_table_set(other, other_spec["starts"], tmp_path)
    message = str(info.value)
    assert said in message and "delete" in message and "\n" not in message, message
    assert {p.name: p.stat().st_mtime_ns for p in tmp_path.iterdir()} == files  # nothing rebuilt or rewritten


# ------------------------------------------------------------------------------------------------------ runaway counts

def test_a_table_set_index_of_too_many_entries_is_refused_at_once(tmp_path):
    import time

    from cuniform_torch.policies.table_set import MAX_SET_TABLES, load_table_set
    from cuniform_torch.tables.file import TableError

    _index(tmp_path, too_many_entries(MAX_SET_TABLES))
    begin = time.perf_counter()
    with pytest.raises(TableError, match="lists 100,001 tables, more than the 100,000"):
        load_table_set(tmp_path)
    assert time.perf_counter() - begin < 5.0


def test_one_member_listed_20000_times_is_refused_in_a_moment(tmp_path):
    import time

    from cuniform_torch.policies.table_set import load_table_set
    from cuniform_torch.tables.file import TableError

    (tmp_path / "start_0000.npz").write_bytes(b"not read")
    _index(tmp_path, one_member_repeated(20_000))
    begin = time.perf_counter()
    with pytest.raises(TableError, match="start_0000.npz listed more than once"):
        load_table_set(tmp_path)
    assert time.perf_counter() - begin < 10.0  # was 47 s: a count per entry


# ------------------------------------------------------------------------------------------------- a shared cold cache

def test_a_second_run_on_a_cold_cache_waits_for_the_first_and_uses_its_table(tmp_path, monkeypatch, capsys):
    import subprocess
    import sys
    import time

    from cuniform_torch.common import fileio
    from eval.navigate import robot_files
    from precompute.worlds.robot import NAV_ROBOT

    monkeypatch.setattr(robot_files, "WAIT_POLL_S", 0.05)
    robot = replace(NAV_ROBOT, horizon=6)  # NAV_ROBOT's own tables ship with the package: nothing to build or wait for
    path = robot_files.table_file(robot, tmp_path)
    holder = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])  # the first run, alive
    try:
        path.with_name(path.name + ".lock").write_text(f"{holder.pid} {fileio._HOST}\n")
        got: dict = {}
        thread = threading.Thread(target=lambda: got.update(path=robot_files.ensure_table(robot, tmp_path)),
                                  daemon=True)
        thread.start()
        time.sleep(0.5)
        assert thread.is_alive() and not path.exists()  # waiting, not refused, not building
        path.write_bytes(b"the first run's table")  # the first run finishes
        path.with_name(path.name + ".lock").unlink()
        thread.join(20)
        assert not thread.is_alive() and got["path"] == path
        assert path.read_bytes() == b"the first run's table"  # used, not rebuilt
        assert "is being built by another run" in capsys.readouterr().out
    finally:
        holder.kill()
        holder.wait()
