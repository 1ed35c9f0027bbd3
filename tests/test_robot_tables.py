"""No hidden builds (issue 37): the navigation robot's tables ship as package data with their manifest (sizes,
sha256, content digests), the benchmark uses them without building, and the shipping command writes exactly what
the builder gives."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace

import numpy as np
import pytest

from cuniform_torch.systems import system_to_json
from cuniform_torch.tables.file import NOGRAPH_DIGEST_KEY, read_table, table_digests
from eval.navigate import robot_files
from eval.navigate.robot_files import (
    CHECK_TOLERANCE,
    MANIFEST,
    METHODS,
    SHIPPED_DIR,
    ShippedTableError,
    build_policy_table,
    compare_tables,
    ensure_table,
    ship_tables,
    shipped_table,
)
from precompute.worlds.robot import NAV_ROBOT, preset_dict

SMALL = replace(NAV_ROBOT, horizon=5)  # both 5-step tables build in about a second


@pytest.fixture(scope="module")
def small_shipped(tmp_path_factory):
    """The 5-step robot's tables shipped into a temporary folder, with the manifest."""
    folder = tmp_path_factory.mktemp("shipped")
    return folder, ship_tables(SMALL, folder)


@pytest.mark.parametrize("method", METHODS)
def test_the_shipped_tables_match_their_manifest_and_the_robot(method):
    manifest = json.loads((SHIPPED_DIR / MANIFEST).read_text())
    entry = next(e for e in manifest["tables"] if e["method"] == method)
    path = shipped_table(NAV_ROBOT, method)  # size and sha256 checked against the manifest
    assert path == SHIPPED_DIR / entry["file"]
    table = read_table(path, graph=False)  # the reader checks the content digest
    assert str(table_digests(table.to_arrays())[NOGRAPH_DIGEST_KEY]) == entry["content_sha256_nograph"]
    assert entry["robot"] == preset_dict(NAV_ROBOT) and entry["fingerprint"] == NAV_ROBOT.fingerprint(method)
    assert table.method == method and table.horizon == NAV_ROBOT.horizon
    assert table.system == system_to_json(robot_files._system(NAV_ROBOT), NAV_ROBOT.horizon)
    assert int(table.level_offsets[-1]) == entry["cells"]


def test_the_benchmark_uses_the_shipped_tables_without_building(tmp_path, capsys, monkeypatch):
    import precompute.build  # noqa: F401  (imported first: it binds the real build_table_file, not the patch below)
    import precompute.one_table as one_table

    def refuse(job):
        raise AssertionError(f"built {job.out}")

    monkeypatch.setattr(one_table, "build_table_file", refuse)
    for method in METHODS:
        assert ensure_table(NAV_ROBOT, tmp_path, method) == shipped_table(NAV_ROBOT, method)
    assert capsys.readouterr().out == "" and list(tmp_path.iterdir()) == []  # nothing said, nothing cached


def test_a_shipped_table_is_what_the_builder_gives(small_shipped, tmp_path):
    folder, manifest = small_shipped
    assert [e["method"] for e in manifest["tables"]] == list(METHODS)
    assert json.loads((folder / MANIFEST).read_text()) == manifest
    for entry in manifest["tables"]:
        method = entry["method"]
        path = shipped_table(SMALL, method, folder)
        assert path == folder / entry["file"]
        shipped = read_table(path, graph=False)
        assert shipped.transitions is None and shipped.arcs is None  # the flow graph is not shipped
        built, _, _ = build_policy_table(SMALL, method)
        for key, value in built.to_arrays().items():  # every key a policy reads, bit for bit
            assert np.array_equal(shipped.to_arrays()[key], value), (method, key)
        diff = compare_tables(built, shipped)
        assert diff == {"same_cells": True, "action_probs": 0.0, "cell_probs": 0.0}
        # the whole table the benchmark would cache has the same content digest over those keys
        full = np.load(ensure_table(SMALL, tmp_path, method, quiet=True))
        assert str(full[NOGRAPH_DIGEST_KEY]) == entry["content_sha256_nograph"]
        assert "transitions" in full.files  # ... and holds the graph the shipped file leaves out


def test_a_damaged_shipped_table_or_manifest_is_one_clear_error(small_shipped, tmp_path):
    folder = tmp_path / "copy"
    shutil.copytree(small_shipped[0], folder)
    entry = small_shipped[1]["tables"][1]
    path = folder / entry["file"]
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 1
    path.write_bytes(bytes(data))
    with pytest.raises(ShippedTableError, match="does not match its manifest.*rebuild the tables"):
        shipped_table(SMALL, entry["method"], folder)
    assert shipped_table(SMALL, "maxflow", folder) is not None  # the other table is untouched
    path.unlink()
    with pytest.raises(ShippedTableError, match="is missing"):
        shipped_table(SMALL, entry["method"], folder)
    (folder / MANIFEST).write_text('{"format": "cuniform-shipped-tables/1", "tables": [{"file": "../x.npz"}]}')
    with pytest.raises(ShippedTableError, match="not a 'cuniform-shipped-tables/1' manifest"):
        shipped_table(SMALL, "maxflow", folder)
    assert shipped_table(SMALL, "maxflow", tmp_path) is None  # no manifest: nothing shipped
    assert shipped_table(replace(SMALL, horizon=4), "maxflow", small_shipped[0]) is None  # another robot


def test_the_command_refuses_a_flag_of_another_mode(tmp_path, capsys):
    assert robot_files.main(["--check", "--out", str(tmp_path)]) == 2
    assert "--out applies to --ship" in capsys.readouterr().err
    assert robot_files.main(["--ship", "--horizons", "6"]) == 2
    assert "--horizons applies to --time" in capsys.readouterr().err


@pytest.mark.slow
@pytest.mark.parametrize("method", METHODS)
def test_the_shipped_15_step_tables_equal_a_rebuild(method):
    diff = compare_tables(build_policy_table(NAV_ROBOT, method)[0], read_table(shipped_table(NAV_ROBOT, method),
                                                                               graph=False))
    assert diff["same_cells"] and diff["action_probs"] <= CHECK_TOLERANCE, diff


# ------------------------------------------------------------------ the coverage build's compiled passes
