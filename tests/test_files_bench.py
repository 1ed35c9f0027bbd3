"""Benchmark folders (``EpisodeStore``: ``settings.json`` and ``episodes.jsonl``): records that are a
folder, a broken symlink, a FIFO or a link elsewhere (``RECORD_LINKS`` of tests/cases.py, which .ci/attack.py also
runs); JSON nested too deeply; settings the run does not write; a cut-short last line, said once."""

from __future__ import annotations

import json
import os
import stat
from pathlib import Path

import pytest
from cases import DEEP, RECORD_LINK_TARGETS
from hardening_helpers import _fifo, _quick
from test_bench_records import bench_record, bench_settings

from eval.navigate.records.store import EpisodeStore, StoreError

pytestmark = pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="POSIX special files")


def _store(tmp_path) -> EpisodeStore:
    store = EpisodeStore(tmp_path / "run")
    store.open(bench_settings())
    store.append(bench_record(0))
    return store


def _refused(store: EpisodeStore, match: str) -> None:
    for read in (store.check, store.load, lambda: store.open(bench_settings())):
        with pytest.raises(StoreError, match=match):
            read()


def _bench_store(folder: Path) -> EpisodeStore:
    store = EpisodeStore(folder)
    store.open(bench_settings())
    store.append(bench_record(0))
    return store


# ---------------------------------------------------------------------------------------- damaged records and settings

def test_records_that_are_a_folder_are_one_error(tmp_path):
    store = _store(tmp_path)
    store.records_file.unlink()
    store.records_file.mkdir()
    _refused(store, r"episodes.jsonl.*(Is a directory|is a folder, not a regular file)")


@pytest.mark.parametrize("target", ["episodes.jsonl", "nowhere.jsonl"])
def test_records_behind_a_broken_symlink_are_not_an_empty_folder(tmp_path, target):
    """A symlink loop (or one to nothing) is not 'no records yet': what the episodes were is unknown."""
    store = _store(tmp_path)
    store.records_file.unlink()
    store.records_file.symlink_to(target)
    _refused(store, r"episodes.jsonl(: unreadable| is a symlink)")  # a reader: unreadable; a run: no links


@pytest.mark.parametrize("last", [True, False])
def test_a_record_nested_too_deeply_is_refused_not_dropped(tmp_path, last):
    """Not JSON the module can parse, but whole: refused on any line (a cut-short last line would be dropped)."""
    store = _store(tmp_path)
    line = json.dumps(bench_record(1), separators=(",", ":"))
    text = DEEP + "\n" + line + "\n" if not last else line + "\n" + DEEP  # last: no newline, as if cut short
    with open(store.records_file, "a") as f:
        f.write(text)
    _refused(store, r"episodes.jsonl: line \d is not a record \(nested too deeply")


def test_settings_nested_too_deeply_are_one_error(tmp_path):
    store = _store(tmp_path)
    store.settings_file.write_text(DEEP)
    _refused(store, r"settings.json: unreadable \(nested too deeply")


# ------------------------------------------------------------------------- settings and records the run does not write

@pytest.mark.parametrize("settings, match", [
    (bench_settings(barn_file="x"), r"field 'barn_file' must be a digest \(16 hex digits\) or null, got 'x'"),
    (bench_settings("barn", barn_file="0123456789ABCDEF"), r"field 'barn_file' must be a digest"),
    (bench_settings(barn_file="0123456789abcdef"), r"field 'barn_file' must be null outside the barn suite"),
    (bench_settings(sources={"table": "0123456789abcde"}), r"field 'sources' must be an object of digests"),
    (bench_settings(sources={"table": "0123456789abcdef0"}), r"field 'sources' must be an object of digests"),
    (bench_settings(gap_widths=[0.6, 0.6, 1.2]), r"field 'gap_widths' must be .*sorted and distinct"),
    (bench_settings(gap_widths=[1.2, 0.6]), r"field 'gap_widths' must be .*sorted and distinct"),
    (bench_settings(gap_widths=[]), r"field 'gap_widths' must be .*non-empty"),
])
def test_settings_the_run_does_not_write_are_refused(tmp_path, settings, match):
    store = _store(tmp_path)
    store.settings_file.write_text(json.dumps(settings))
    _refused(store, match)


@pytest.mark.parametrize("hist, match", [
    ({"120": 15}, r"line 2: cycle_hist counts 15 commands, but cycles is 16"),
    ({}, r"line 2: cycle_hist counts 0 commands"),
    ({"120": 16, "121": 0}, r"line 2: field 'cycle_hist' must map bins '0'..'279' to counts >= 1"),
    ({"280": 16}, r"field 'cycle_hist' must map bins"),
    ({"012": 16}, r"field 'cycle_hist' must map bins"),
])
def test_a_cycle_histogram_that_is_not_its_cycles_is_refused(tmp_path, hist, match):
    store = _store(tmp_path)
    with open(store.records_file, "a") as f:
        f.write(json.dumps(bench_record(1, cycle_hist=hist)) + "\n")
    _refused(store, match)


def test_a_barn_folders_settings_with_digests_read_back(tmp_path):
    settings = bench_settings("barn", barn_file="0123456789abcdef", sources={"table": "fedcba9876543210"})
    settings.pop("gap_widths", None)
    store = EpisodeStore(tmp_path / "run")
    store.open(settings)
    assert store.load()[0] == settings


def test_a_cut_short_last_line_is_said_once_by_a_read_only_load(tmp_path, capsys):
    store = _store(tmp_path)
    with open(store.records_file, "a") as f:
        f.write(json.dumps(bench_record(1))[:40])  # a run writing its next record, or killed while it did
    size = store.records_file.stat().st_size
    store.check()  # the run's early check: open() warns and drops the line (tests/test_bench_records.py)
    assert capsys.readouterr().err == ""
    for _ in range(2):
        assert list(store.load()[1]) == ["gaps/0/mppi_1.0/16/0"]
    err = capsys.readouterr().err.splitlines()
    assert err == [f"note: {store.records_file}: line 2 is cut short (40 bytes, not a record; a run may be writing "
                   "it now): left out, the file left as it is"]
    assert store.records_file.stat().st_size == size  # read only
    assert list(EpisodeStore(store.folder).read()) == ["gaps/0/mppi_1.0/16/0"]  # another reader says it too
    assert len(capsys.readouterr().err.splitlines()) == 1


# --------------------------------------------------------------------------------------------- special files and links

def test_benchmark_records_that_are_a_fifo_are_refused_not_waited_on(tmp_path):
    store = _bench_store(tmp_path / "run")
    store.records_file.unlink()
    _fifo(store.records_file)
    for read in (store.load, store.check, lambda: store.open(bench_settings())):
        with pytest.raises(StoreError, match="FIFO"):
            _quick(read)


def test_benchmark_settings_that_are_a_fifo_are_refused(tmp_path):
    store = _bench_store(tmp_path / "run")
    store.settings_file.unlink()
    _fifo(store.settings_file)
    for read in (store.load, store.check):
        with pytest.raises(StoreError, match="FIFO"):
            _quick(read)


def test_benchmark_records_linked_to_a_device_are_refused(tmp_path):
    store = _bench_store(tmp_path / "run")
    store.records_file.unlink()
    store.records_file.symlink_to("/dev/zero")
    for use in (store.load, lambda: store.open(bench_settings())):  # never an endless read, never written through
        with pytest.raises(StoreError, match="is a symlink \\(to /dev/zero\\)"):
            _quick(use)


@pytest.mark.parametrize("target", RECORD_LINK_TARGETS)
def test_a_benchmark_folder_whose_records_link_elsewhere_is_refused_never_written_through(tmp_path, target):
    other = _bench_store(tmp_path / "other")
    before = other.records_file.read_bytes()
    store = _bench_store(tmp_path / "run")
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
    other = _bench_store(tmp_path / "other")
    store = EpisodeStore(tmp_path / "run")
    store.folder.mkdir()
    store.settings_file.symlink_to(other.settings_file)
    with pytest.raises(StoreError, match="is a symlink"):
        store.open(bench_settings())
