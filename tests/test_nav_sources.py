"""The benchmark's source files given on the command line are checked before anything is built: a missing path,
an empty folder or file, a damaged file, or a file no chosen method reads is one clear error."""

from __future__ import annotations

import pytest

from eval.navigate.run import _check_given


def _file(folder, name: str, data: bytes):
    (folder / name).write_bytes(data)
    return folder / name


@pytest.mark.parametrize("name, make, match", [
    ("table", lambda d: d / "missing.npz", "does not exist"),
    ("table", lambda d: d, "does not exist"),  # a folder without tables.json
    ("table", lambda d: _file(d, "empty.npz", b""), "not a readable .npz table"),
    ("coverage_table", lambda d: _file(d, "x.npz", b"PK\x03\x04junk"), "--coverage-table"),
    ("policy", lambda d: _file(d, "p.pt", b""), "--policy"),
])
def test_a_bad_given_source_is_refused_before_any_work(tmp_path, name, make, match):
    with pytest.raises((ValueError, FileNotFoundError), match=match):
        _check_given({name: make(tmp_path)}, {"table", "coverage_table", "policy"})


def test_a_source_no_chosen_method_reads_is_refused(tmp_path):
    with pytest.raises(ValueError, match="--policy .*no chosen method reads it .*cu_mlp"):
        _check_given({"policy": tmp_path / "p.pt"}, {"table"})
    with pytest.raises(ValueError, match="--map-policy .*cfu_mppi"):
        _check_given({"map_policy": tmp_path / "m.pt"}, {"table", "policy"})
    _check_given({"table": None, "policy": None}, {"table"})  # nothing given: nothing to check
