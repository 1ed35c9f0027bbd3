"""The shared readers and writers every file family goes through (``cuniform_torch.common.fileio`` and
``.npz``): capped reads that open only regular files, atomic writes that never replace a special file, outputs that
name a device, bounded ``.npz`` headers, locks (one writer per output, a dead holder's lock taken over, a lock on a
full disk) and the temporary files a killed writer leaves."""

from __future__ import annotations

import json
import os
import signal
import stat
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest
from hardening_helpers import _dead_pid, _fifo, _forged_member, _quick

from cuniform_torch.common import fileio
from cuniform_torch.common.fileio import (
    FileKindError,
    FileTooLargeError,
    atomic_path,
    read_capped_bytes,
    read_capped_text,
    write_json,
    write_npz,
)
from cuniform_torch.common.npz import NpzError, read_npz
from precompute.cli import CLIError, check_output_file, check_output_folder

pytestmark = [pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="POSIX special files"), pytest.mark.usefixtures("restore_threads")]




REPO = Path(__file__).resolve().parents[1]


# -------------------------------------------------------------------------------------- capped reads and atomic writes

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


# ------------------------------------------------------------------------------------------ outputs that name a device

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


# --------------------------------------------------------------------------------------------------------------- locks

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


# ----------------------------------------------------------------------------------------------------- the .npz reader

def test_read_npz_bounds_headers_and_refuses_objects(tmp_path):
    path = tmp_path / "a.npz"
    write_npz(path, {"x": np.arange(10), "y": np.zeros((3, 2), np.float32)})
    got = read_npz(path)
    assert np.array_equal(got["x"], np.arange(10)) and got["y"].shape == (3, 2) and got["x"].flags.writeable
    with pytest.raises(NpzError, match=r"a\.npz: member 'y': must have shape \[3, 3\], got \[3, 2\]"):
        read_npz(path, expect={"y": ((3, 3), np.float32)})
    with pytest.raises(NpzError, match=r"more than this file may hold"):
        read_npz(path, max_bytes=100)
    obj = tmp_path / "o.npz"
    np.savez(obj, o=np.array([None, 1], dtype=object))
    with pytest.raises(NpzError, match=r"member 'o': dtype object holds Python objects"):
        read_npz(obj)
    lying = tmp_path / "l.npz"  # a header claiming more than the member holds (a few bytes short)
    with zipfile.ZipFile(lying, "w", zipfile.ZIP_STORED) as zf:
        zf.writestr("z.npy", _forged_member("z", (100,), np.int64, b"\0" * 80))
    with pytest.raises(NpzError, match=r"member 'z': its header claims \[100\] int64 \(800 bytes\) but the member "
                                       r"holds 80 data bytes"):
        read_npz(lying)


# ---------------------------------------------------------------------------------------- locks: one writer per output

def test_lock_is_exclusive_within_a_run(tmp_path):
    from cuniform_torch.common.fileio import FileLockedError, exclusive_lock

    lock = tmp_path / "x.lock"
    with exclusive_lock(lock, what="x"):
        assert lock.read_text().split()[0] == str(os.getpid())
        with pytest.raises(FileLockedError, match=r"x is being written by process"):
            with exclusive_lock(lock, what="x"):
                pass
    assert not lock.exists()


# ---------------------------------------------------------------------------------------------------- stale temp files

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
