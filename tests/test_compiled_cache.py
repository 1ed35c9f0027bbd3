"""numba's disk cache of the compiled loops can only help (:mod:`cuniform_torch.common.compiled`): a damaged cache
(a truncated index ``.nbi`` or data file ``.nbc``) is one ``CompiledCacheWarning`` naming the damaged files it
removed, and the loop is compiled and saved afresh (the next run loads it again); where they cannot be removed, or
no cache folder is writable at all, one warning saying what to do and the loop is compiled in memory: the same
answer, no traceback. Each case runs in a fresh process with its own cache folder (``NUMBA_CACHE_DIR``), never the
install's ``__pycache__``."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("numba")

ROOT = Path(__file__).resolve().parents[1]

USE_A_LOOP = """
import numpy as np
from cuniform_torch.envs.contains_loops import any_contains
hit = np.zeros(2, dtype=np.bool_)
any_contains(np.array([[0.0, 0.0], [5.0, 5.0]]), np.array([[0.0, 0.0, 1.0]]), np.zeros((0, 4)), hit)
print("hit", hit.tolist())
print("cache hits", sum(any_contains.stats.cache_hits.values()))
"""


def _run(env_changes: dict[str, str | None]) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    for key, value in env_changes.items():
        if value is None:
            env.pop(key, None)
        else:
            env[key] = value
    return subprocess.run([sys.executable, "-c", USE_A_LOOP], cwd=ROOT, env=env, capture_output=True, text=True,
                          timeout=300)


def _warnings(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines() if "CompiledCacheWarning" in line]


@pytest.mark.parametrize("suffix", [".nbi", ".nbc"])
def test_a_truncated_cache_file_is_removed_and_compiled_afresh_with_one_warning(tmp_path, suffix):
    cache = tmp_path / "numba-cache"
    first = _run({"NUMBA_CACHE_DIR": str(cache)})
    assert first.returncode == 0 and "hit [True, False]" in first.stdout, first.stderr
    assert not _warnings(first.stderr)
    intact = _run({"NUMBA_CACHE_DIR": str(cache)})  # the guard leaves a good cache in use: loaded, not compiled
    assert intact.returncode == 0 and "cache hits 1" in intact.stdout and not _warnings(intact.stderr), intact.stderr
    damaged = sorted(cache.rglob(f"contains_loops.*{suffix}"))
    assert damaged, f"numba wrote no {suffix} file under {cache}"
    for path in damaged:
        data = path.read_bytes()
        path.write_bytes(data[: len(data) // 2])
    again = _run({"NUMBA_CACHE_DIR": str(cache)})
    assert again.returncode == 0, again.stderr  # was: _pickle.UnpicklingError: pickle data was truncated
    assert "hit [True, False]" in again.stdout and "cache hits 0" in again.stdout
    assert "Traceback" not in again.stderr
    lines = _warnings(again.stderr)
    assert len(lines) == 1, again.stderr
    assert str(damaged[0].parent) in lines[0] and "could not be read" in lines[0], lines
    assert "removed its damaged files" in lines[0] and damaged[0].name in lines[0], lines
    repaired = _run({"NUMBA_CACHE_DIR": str(cache)})  # repaired on disk: loaded again, no warning
    assert repaired.returncode == 0 and "cache hits 1" in repaired.stdout, repaired.stdout + repaired.stderr
    assert not _warnings(repaired.stderr), repaired.stderr


def test_a_damaged_cache_that_cannot_be_removed_is_set_aside_with_one_warning(tmp_path):
    """Where the damaged files' folder is not writable (a read-only install; simulated here by ``os.access``, since
    root may write anywhere) the loop is compiled in memory in every run, and the warning says what to do."""
    cache = tmp_path / "numba-cache"
    assert _run({"NUMBA_CACHE_DIR": str(cache)}).returncode == 0
    (index,) = cache.rglob("contains_loops.any_contains-*.nbi")
    index.write_bytes(index.read_bytes()[:10])
    read_only = ("import os\n_access = os.access\n"
                 "os.access = lambda p, mode, **kw: False if mode & os.W_OK else _access(p, mode, **kw)\n")
    env = dict(os.environ, PYTHONPATH=str(ROOT), NUMBA_CACHE_DIR=str(cache))
    for _ in range(2):
        run = subprocess.run([sys.executable, "-c", read_only + USE_A_LOOP], cwd=ROOT, env=env, capture_output=True,
                             text=True, timeout=300)
        assert run.returncode == 0 and "hit [True, False]" in run.stdout and "cache hits 0" in run.stdout, run.stderr
        lines = _warnings(run.stderr)
        assert len(lines) == 1 and "Delete that folder" in lines[0] and "removed" not in lines[0], run.stderr
    assert index.stat().st_size == 10  # left as it was


def test_no_writable_cache_folder_compiles_in_memory_with_one_warning(tmp_path):
    """A read-only install run by a user whose home is not writable: numba finds no folder for its cache (here its
    only locator is the user-wide one, and the home is a regular file, so not even root can make the folder)."""
    home = tmp_path / "home-is-a-file"
    home.write_text("")
    run = _run({"HOME": str(home), "XDG_CACHE_HOME": None, "NUMBA_CACHE_DIR": None,
                "NUMBA_CACHE_LOCATOR_CLASSES": "UserWideCacheLocator"})
    assert run.returncode == 0, run.stderr  # was: RuntimeError: cannot cache function ...: no locator available
    assert "hit [True, False]" in run.stdout and "Traceback" not in run.stderr
    lines = _warnings(run.stderr)
    assert len(lines) == 1 and "numba cannot cache" in lines[0] and "NUMBA_CACHE_DIR" in lines[0], run.stderr


def test_a_data_file_of_another_loop_is_not_run(tmp_path):
    """Two data files swapped (each unpickles cleanly): the loaded code is another function's, called with the wrong
    arguments (a TypeError, or a crash when the counts agree); it is refused and compiled afresh."""
    cache = tmp_path / "numba-cache"
    script = ("import numpy as np\n"
              "from cuniform_torch.sampling import frame_loops as f\n"
              "print('heading', round(float(f.heading(0.5, 0.25, np.pi, 2 * np.pi)), 6))\n") + USE_A_LOOP
    env = dict(os.environ, PYTHONPATH=str(ROOT), NUMBA_CACHE_DIR=str(cache))

    def run():
        return subprocess.run([sys.executable, "-c", script], cwd=ROOT, env=env, capture_output=True, text=True,
                              timeout=300)

    first = run()
    assert first.returncode == 0 and "heading 0.75" in first.stdout and "hit [True, False]" in first.stdout, first.stderr
    (heading,) = cache.rglob("frame_loops.heading-*.nbc")
    (contains,) = cache.rglob("contains_loops.any_contains-*.nbc")
    a, b = heading.read_bytes(), contains.read_bytes()
    heading.write_bytes(b)
    contains.write_bytes(a)
    again = run()
    assert again.returncode == 0, again.stderr
    assert "heading 0.75" in again.stdout and "hit [True, False]" in again.stdout and "Traceback" not in again.stderr
    lines = _warnings(again.stderr)
    assert lines and all("holds the code of" in line for line in lines), again.stderr
    repaired = run()  # both loops' files were removed and saved afresh: loaded again, no warning
    assert repaired.returncode == 0 and "heading 0.75" in repaired.stdout and "cache hits 1" in repaired.stdout
    assert not _warnings(repaired.stderr), repaired.stderr
