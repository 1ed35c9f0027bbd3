"""What a path points to (issue 38): every reader opens only regular files and says so otherwise -- a FIFO, a
device, or a symlink to one is one clear error before any read, never a hang or an unbounded read; JSON and JSONL
readers read with a size cap; a benchmark folder whose files are links is refused, never written through; an
output that names a device is refused before anything is written; a table set rebuilt with other settings is
refused rather than kept stale.

Every call that could hang on a FIFO runs through :func:`_quick` (a thread joined with a timeout), so a broken
check fails the test instead of hanging the suite."""

from __future__ import annotations

import json
import os
import stat
import threading
from dataclasses import replace
from pathlib import Path

import pytest

from cuniform_torch.common.fileio import (
    FileKindError,
    FileTooLargeError,
    atomic_path,
    read_capped_bytes,
    read_capped_text,
    write_json,
)
from eval.navigate.records.store import EpisodeStore, StoreError
from precompute.cli import CLIError, check_output_file, check_output_folder
from tests.test_bench_records import bench_record, bench_settings

pytestmark = pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="POSIX special files")


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
    os.mkfifo(path)
    return path


# ------------------------------------------------------------------------------------------ the shared readers

@pytest.mark.parametrize("kind", ["fifo", "zero", "urandom", "folder"])
def test_the_capped_reader_refuses_what_is_not_a_regular_file(tmp_path, kind):
    path = tmp_path / "tables.json"
    if kind == "fifo":
        _fifo(path)
    elif kind == "folder":
        path.mkdir()
    else:
        path.symlink_to(f"/dev/{kind}")
    with pytest.raises(FileKindError, match="not a regular file") as err:
        _quick(read_capped_text, path, 1 << 20, "the table-set index")
    assert str(path) in str(err.value)
    if kind in ("zero", "urandom"):
        assert "character device (through a symlink)" in str(err.value)


def test_the_capped_reader_refuses_a_file_over_its_cap_from_its_size(tmp_path):
    path = tmp_path / "big.json"
    with open(path, "wb") as fh:  # sparse: 2 GB claimed, nothing stored, never read
        fh.truncate(2 << 30)
    with pytest.raises(FileTooLargeError, match="over the limit of 1024 bytes"):
        read_capped_bytes(path, 1024)
    path.write_bytes(b"x" * 1024)
    assert read_capped_bytes(path, 1024) == b"x" * 1024  # at the cap: read


def test_an_atomic_write_never_replaces_a_special_file(tmp_path):
    fifo = _fifo(tmp_path / "out.json")
    with pytest.raises(FileKindError, match="FIFO"):
        write_json(fifo, {"a": 1})
    assert stat.S_ISFIFO(os.stat(fifo).st_mode)  # still the FIFO
    link = tmp_path / "null.json"  # never /dev/null itself: a regression run as root would replace the device
    link.symlink_to("/dev/null")
    with pytest.raises(FileKindError, match="character device"), atomic_path(link):
        pass
    assert link.is_symlink() and stat.S_ISCHR(os.stat("/dev/null").st_mode)


@pytest.mark.parametrize("target", ["fifo", "/dev/zero"])
def test_a_barn_file_that_is_a_special_file_is_refused(tmp_path, target):
    from precompute.worlds.barn import load_barn
    from precompute.worlds.barn_format import BarnFormatError

    path = tmp_path / "barn.npz"
    if target == "fifo":
        _fifo(path)
    else:
        path.symlink_to(target)
    with pytest.raises(BarnFormatError, match="the BARN file is a (FIFO|character device)"):
        _quick(load_barn, path)


def test_a_world_file_and_a_training_state_that_are_fifos_are_refused(tmp_path):
    from precompute.worlds.barn_format import BarnFormatError
    from precompute.worlds.barn_worlds import _parse_world
    from training.tables.train_state import UsageError, load_train_state

    world = _fifo(tmp_path / "world_0.world")
    with pytest.raises(BarnFormatError, match="FIFO"):
        _quick(_parse_world, world)
    state = tmp_path / "state.pt"
    state.symlink_to("/dev/zero")
    with pytest.raises(UsageError, match="character device"):
        _quick(load_train_state, state, {})


@pytest.mark.parametrize("target", ["fifo", "/dev/zero", "/dev/urandom"])
def test_an_npz_that_is_a_special_file_is_refused_by_name(tmp_path, target):
    from cuniform_torch.common.npz import NpzError, member_headers, read_npz

    path = tmp_path / "t.npz"
    if target == "fifo":
        _fifo(path)
    else:
        path.symlink_to(target)
    for read in (read_npz, member_headers):
        with pytest.raises(NpzError, match=r"t\.npz: a (FIFO|character device).*, not a regular file"):
            _quick(read, path)


# ------------------------------------------------------------------------------------------ the table-set index

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


@pytest.mark.parametrize("name, said", [("a" * 300 + ".npz", "is not usable .*File name too long"),
                                        ("nul\0.npz", "but missing")], ids=["too-long", "nul"])
def test_a_table_set_member_name_the_system_cannot_use_is_one_table_error(tmp_path, name, said):
    from cuniform_torch.policies.table_set import load_table_set
    from cuniform_torch.tables.file import TableError

    (tmp_path / "tables.json").write_text(json.dumps({"format": "cuniform-table-set/1", "system": "random_walk_1d",
                                                      "tables": [{"file": name, "start": [0.0]}]}))
    with pytest.raises(TableError, match=said):
        load_table_set(tmp_path)


# ------------------------------------------------------------------------------------------ benchmark folders

def _store(folder: Path) -> EpisodeStore:
    store = EpisodeStore(folder)
    store.open(bench_settings())
    store.append(bench_record(0))
    return store


def test_benchmark_records_that_are_a_fifo_are_refused_not_waited_on(tmp_path):
    store = _store(tmp_path / "run")
    store.records_file.unlink()
    _fifo(store.records_file)
    for read in (store.load, store.check, lambda: store.open(bench_settings())):
        with pytest.raises(StoreError, match="FIFO"):
            _quick(read)


def test_benchmark_settings_that_are_a_fifo_are_refused(tmp_path):
    store = _store(tmp_path / "run")
    store.settings_file.unlink()
    _fifo(store.settings_file)
    for read in (store.load, store.check):
        with pytest.raises(StoreError, match="FIFO"):
            _quick(read)


def test_benchmark_records_linked_to_a_device_are_refused(tmp_path):
    store = _store(tmp_path / "run")
    store.records_file.unlink()
    store.records_file.symlink_to("/dev/zero")
    for use in (store.load, lambda: store.open(bench_settings())):  # never an endless read, never written through
        with pytest.raises(StoreError, match="is a symlink \\(to /dev/zero\\)"):
            _quick(use)


@pytest.mark.parametrize("target", ["other", "/dev/null"])
def test_a_benchmark_folder_whose_records_link_elsewhere_is_refused_never_written_through(tmp_path, target):
    other = _store(tmp_path / "other")
    before = other.records_file.read_bytes()
    store = _store(tmp_path / "run")
    store.records_file.unlink()
    store.records_file.symlink_to(other.records_file if target == "other" else target)
    for use in (store.check, lambda: store.open(bench_settings()), store.load):  # a reader: not another's records
        with pytest.raises(StoreError, match="is a symlink .*replace the link"):
            use()
    with pytest.raises(OSError):  # the append itself never follows a link either
        store.append(bench_record(5))
    assert other.records_file.read_bytes() == before
    assert stat.S_ISCHR(os.stat("/dev/null").st_mode)


@pytest.mark.parametrize("kind", ["symlink loop", "file"])
def test_a_benchmark_folder_that_cannot_be_made_is_one_store_error(tmp_path, kind):
    """EpisodeStore.open of a folder path that is a symlink loop or a regular file (the attack's appending reader:
    a raw FileExistsError before)."""
    folder = tmp_path / "bench"
    if kind == "file":
        folder.write_text("not a folder")
    else:
        folder.symlink_to(folder.name)
    with pytest.raises(StoreError, match=f"{folder}: cannot be used as a benchmark folder"):
        EpisodeStore(folder).open(bench_settings())


def test_benchmark_settings_linked_elsewhere_are_refused(tmp_path):
    other = _store(tmp_path / "other")
    store = EpisodeStore(tmp_path / "run")
    store.folder.mkdir()
    store.settings_file.symlink_to(other.settings_file)
    with pytest.raises(StoreError, match="is a symlink"):
        store.open(bench_settings())


# ------------------------------------------------------------------------------------------ outputs and devices

@pytest.mark.parametrize("path", ["/dev/null", "/dev/full", "/dev/stdout"])
def test_an_output_naming_a_device_is_refused(path):
    if not os.path.exists(path):
        pytest.skip(f"{path} is missing here")
    with pytest.raises(CLIError, match=f"--json {path} is "):
        check_output_file(path, "--json")
    with pytest.raises(CLIError, match=f"--out {path} is "):
        check_output_folder(path, "--out")


def test_an_output_that_is_a_fifo_is_refused(tmp_path):
    fifo = _fifo(tmp_path / "out.json")
    with pytest.raises(CLIError, match="FIFO"):
        check_output_file(fifo, "--json")


def test_build_to_a_device_is_one_line_and_leaves_it_a_device(tmp_path, capsys):
    from precompute.build import main

    out = tmp_path / "null.npz"  # a link to /dev/null, not the device: a regression never replaces /dev/null
    out.symlink_to("/dev/null")
    assert main(["--system", "random_walk_1d", "--horizon", "3", "--quiet", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"error: --out {out} is a character device (through a symlink)" in err
    assert out.is_symlink() and not (tmp_path / "null.report.json").exists()


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


# ------------------------------------------------------------------------------------------ a rebuilt table set

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


# ------------------------------------------------------------------------------------------ runaway counts

@pytest.mark.parametrize("spec, count", [("0=-1:1:20001", "20,001"), ("random:1000000 0=-1:1", "1,000,000")])
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


def _index(folder: Path, entries: list[dict]) -> None:
    (folder / "tables.json").write_text(json.dumps({"format": "cuniform-table-set/1", "system": "random_walk_1d",
                                                    "tables": entries}))


def test_a_table_set_index_of_too_many_entries_is_refused_at_once(tmp_path):
    import time

    from cuniform_torch.policies.table_set import MAX_SET_TABLES, load_table_set
    from cuniform_torch.tables.file import TableError

    _index(tmp_path, [{"file": f"start_{i:06d}.npz", "start": [float(i)]} for i in range(MAX_SET_TABLES + 1)])
    begin = time.perf_counter()
    with pytest.raises(TableError, match="lists 100,001 tables, more than the 100,000"):
        load_table_set(tmp_path)
    assert time.perf_counter() - begin < 5.0


def test_one_member_listed_20000_times_is_refused_in_a_moment(tmp_path):
    import time

    from cuniform_torch.policies.table_set import load_table_set
    from cuniform_torch.tables.file import TableError

    (tmp_path / "start_0000.npz").write_bytes(b"not read")
    _index(tmp_path, [{"file": "start_0000.npz", "start": [float(i)]} for i in range(20_000)])
    begin = time.perf_counter()
    with pytest.raises(TableError, match="start_0000.npz listed more than once"):
        load_table_set(tmp_path)
    assert time.perf_counter() - begin < 10.0  # was 47 s: a count per entry


# ------------------------------------------------------------------------------------------ a lock on a full disk

def test_a_lock_that_cannot_be_written_is_removed_and_names_the_file(tmp_path, monkeypatch):
    import errno

    from cuniform_torch.common import fileio

    real_fdopen = os.fdopen

    class Full:
        def __init__(self, fd):
            self.fh = real_fdopen(fd, "w")

        def __enter__(self):
            return self

        def write(self, text):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

        def __exit__(self, *exc):
            self.fh.close()

    lock = tmp_path / "out.npz.lock"
    monkeypatch.setattr(fileio.os, "fdopen", lambda fd, mode="r", *a, **k: Full(fd))
    with pytest.raises(OSError) as err, fileio.exclusive_lock(lock):
        pass
    assert err.value.errno == errno.ENOSPC and err.value.filename == str(lock)
    assert not lock.exists()  # no empty lock left behind
    monkeypatch.undo()
    with fileio.exclusive_lock(lock):  # a rerun at once takes it
        assert lock.read_text().split()[0] == str(os.getpid())


# ------------------------------------------------------------------------------------------ a shared cold cache

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


# ------------------------------------------------------------------------------------------ a worker killed

def test_a_worker_that_dies_is_one_clear_error_not_a_broken_pool_traceback():
    from precompute.cli import error_message
    from precompute.parallel import WorkerDiedError, run_jobs

    with pytest.raises(WorkerDiedError) as err:
        run_jobs(os.abort, [(), ()], workers=2)  # each worker dies by a signal, as the OOM killer's SIGKILL does
    line = error_message(err.value)
    assert line is not None and "a worker process died" in line and "rerun to resume" in line


def test_simulate_refuses_a_time_limit_of_runaway_steps_before_the_first_step():
    import time

    import torch

    from cuniform_torch.envs.environment import Environment
    from cuniform_torch.envs.sim import simulate
    from cuniform_torch.systems import make_system

    class Counting:
        commands = 0

        def command(self, state):
            Counting.commands += 1
            assert Counting.commands <= 1000, "simulate ran the runaway limit"  # a regression fails, never hangs
            return state.new_zeros(1)

    args = dict(system=make_system("dubins"), controller=Counting(), x0=torch.zeros(3), env=Environment([]),
                goal=(50.0, 50.0), goal_tolerance=0.1)  # unreachable: only the time limit ends the run
    begin = time.perf_counter()
    with pytest.raises(ValueError, match=r"time_limit 1000000000.0 s at dt 0.2 s is 5,000,000,000 steps, more than "
                                         r"the limit of 100,000; .*step_limit=5000000000"):
        simulate(**args, time_limit=1e9)
    assert time.perf_counter() - begin < 2.0 and Counting.commands == 0
    assert simulate(**args, time_limit=0.4, step_limit=2).steps == 2  # within a given limit: runs
    with pytest.raises(ValueError, match="step_limit must be a positive integer"):
        simulate(**args, time_limit=0.4, step_limit=0)


def test_a_profile_that_is_a_fifo_is_refused(tmp_path, capsys):
    from eval.bench.profile_split import main

    fifo = _fifo(tmp_path / "run.prof")
    assert _quick(main, [str(fifo)]) == 2
    assert "a cProfile output is a FIFO" in capsys.readouterr().err
