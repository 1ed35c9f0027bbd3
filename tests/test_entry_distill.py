"""``python -m training.distill``: outputs that are folders or files, a full disk, an output another
live process writes, Ctrl-C (one line, exit code 130) and a user table read after ``--system-module``."""

from __future__ import annotations

import errno
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from hardening_helpers import _one_error

import precompute.build as build
import training.distill as distill
from cuniform_torch.common import fileio
from cuniform_torch.systems import _REGISTRY

pytestmark = pytest.mark.usefixtures("restore_threads")

TINY_DISTILL = ["--quiet", "--epochs", "1", "--hidden", "8", "--layers", "1", "--jitter", "1", "--batch-size", "64",
                "--eval-samples", "16", "--eval-every", "1000"]




def _distill(walk: Path, folder: Path, *extra: str) -> list[str]:
    return ["--tables", str(walk), "--out", str(folder / "p.pt"), "--logdir", str(folder / "runs"), *TINY_DISTILL,
            *extra]


REPO = Path(__file__).resolve().parents[1]


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


# ------------------------------------------------------------------------------------------------------------- distill

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


@pytest.mark.slow  # a distill subprocess, interrupted (pytest --durations: 18.7 s at load 11, 4.5 s at 3)
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
