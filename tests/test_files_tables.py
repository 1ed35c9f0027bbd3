"""Table files (``.npz``, ``read_table`` / ``load_table``): every damaged, forged or hostile variant is one
``TableError`` naming the file and the key, never a traceback from numpy or zipfile, never a silent wrong table.

Grouped by what is checked: round trips; unreadable files (empty, truncated, garbage, other zips); pickled arrays
(never unpickled); corrupted content (dtypes, shapes, offsets, probabilities: the ``TABLE_CORRUPTIONS`` table of
tests/cases.py, which .ci/attack.py also runs); the system JSON (malformed: ``SYSTEM_JSON_MALFORMED``; factories;
dt); content digests and the cross-checks; no code from data (the trust model: README, "The trust model"); bounded
reads (decompression bombs, lying headers); tables that would load silently wrong; special files."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import sys
import zipfile
from dataclasses import replace
from pathlib import Path
from typing import ClassVar

import numpy as np
import pytest
import torch
from cases import SYSTEM_JSON_MALFORMED, TABLE_CORRUPTIONS, UNREADABLE_TABLES
from hardening_helpers import HORIZON, _fifo, _flip_byte, _notes, _quick

from cuniform_torch.common.digest import DIGEST_KEY
from cuniform_torch.common.fileio import (
    write_npz,
)
from cuniform_torch.common.npz import NpzError, member_headers, read_npz
from cuniform_torch.policies.table import load_table
from cuniform_torch.systems import (
    _REGISTRY,
    RandomWalk1D,
    UnknownSystemError,
    make_system,
    register_system,
    system_from_json,
    system_to_json,
)
from cuniform_torch.tables.file import (
    NOGRAPH_DIGEST_KEY,
    TableError,
    read_table,
    table_digests,
    write_table,
)
from precompute.coverage.method import CoverageConfig, build_coverage_table
from precompute.flow.builder import BuildConfig, build_table
from precompute.levels.safe_map import LocalMap, MapError, read_map_file, write_map_file

REQUIRED_KEYS = ("system", "actions", "cell_size", "periodic", "cell_offset", "level_offsets", "cells",
                 "action_probs", "cell_probs", "flow_value", "flow_target")


ARRAY_FIELDS = REQUIRED_KEYS[1:] + ("arc_offsets", "arcs", "arc_flow", "transition_offsets", "transitions",
                                    "transition_frac")




@pytest.fixture(scope="module")
def good_path(small_table, tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("table") / "good.npz"
    write_table(path, small_table)
    return path


@pytest.fixture(scope="module")
def good_arrays(good_path) -> dict[str, np.ndarray]:
    with np.load(good_path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


@pytest.fixture()
def arrays(good_arrays) -> dict[str, np.ndarray]:
    """A fresh, writable copy of the valid table's arrays, to corrupt; without the content digests (an older file:
    the digest would refuse any edit before the checks these tests exercise)."""
    return {k: np.array(v, copy=True) for k, v in good_arrays.items() if not k.startswith("content_sha256")}




def _write(tmp_path: Path, arrays: dict[str, np.ndarray], name: str = "bad.npz") -> Path:
    path = tmp_path / name
    write_npz(path, arrays)
    return path


class _OpensFileWhenUnpickled:
    """Unpickling this creates a file: proof that the reader unpickled something."""

    def __init__(self, path: Path):
        self.path = str(path)

    def __reduce__(self):
        return (open, (self.path, "w"))


def _object_array(marker: Path) -> np.ndarray:
    arr = np.empty(1, dtype=object)
    arr[0] = _OpensFileWhenUnpickled(marker)
    return arr




def _system_spec(arrays: dict[str, np.ndarray]) -> dict:
    return json.loads(str(arrays["system"][()]))


def _set_system(arrays: dict[str, np.ndarray], spec: dict | str) -> None:
    arrays["system"] = np.array(spec if isinstance(spec, str) else json.dumps(spec, sort_keys=True))


def _local_map(path):
    occ = torch.zeros(30, 40, dtype=torch.uint8).numpy()
    occ[10:14, 5:30] = 1
    write_map_file(path, LocalMap(occ, (-1.5, -2.0), 0.1))
    return path


WALK_JSON = json.loads(system_to_json(RandomWalk1D(), 8))


@dataclasses.dataclass(frozen=True)
class DamageWalk(RandomWalk1D):
    """A user system (not built in): its JSON names its factory, this class."""

    name: ClassVar[str] = "damage_walk"


@pytest.fixture(scope="module")
def table():
    """A small Dubins max-flow table (levels 1, 5, 13), with its flow graph."""
    return build_table(make_system("dubins"), BuildConfig(horizon=2))[0]


GRAPH_KEYS = ("arc_offsets", "arcs", "arc_flow", "transition_offsets", "transitions", "transition_frac")




@pytest.fixture(scope="module")
def table_arrays(table, tmp_path_factory) -> dict[str, np.ndarray]:
    return written_arrays(table, tmp_path_factory.mktemp("t") / "good.npz")




def _rewritten(arrays: dict[str, np.ndarray], path: Path) -> Path:
    """``arrays`` written with fresh digests: a well-formed file whose content is inconsistent."""
    arrays = {k: v for k, v in arrays.items() if k not in (DIGEST_KEY, NOGRAPH_DIGEST_KEY)}
    write_npz(path, {**arrays, **table_digests(arrays)})
    return path


@pytest.fixture(scope="module")
def walk_arrays(walk_table, tmp_path_factory) -> dict[str, np.ndarray]:
    return written_arrays(walk_table, tmp_path_factory.mktemp("walk") / "walk.npz")


def written_arrays(table, path) -> dict[str, np.ndarray]:
    """The arrays of ``table`` as :func:`write_table` writes them to ``path`` (digests included)."""
    write_table(path, table)
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


@pytest.fixture()
def walk_copy(walk_arrays) -> dict[str, np.ndarray]:
    """A writable copy without the content digests (an older file: the digest would refuse any edit first)."""
    return {k: np.array(v, copy=True) for k, v in walk_arrays.items() if not k.startswith("content_sha256")}


def _with_system(walk_copy: dict[str, np.ndarray], **spec) -> dict[str, np.ndarray]:
    base = {"name": "random_walk_1d", "params": {}, "dt": 1.0, "horizon": 8}
    walk_copy["system"] = np.array(json.dumps({**base, **spec}, sort_keys=True))
    return walk_copy






def _zip_member(zf: zipfile.ZipFile, name: str, header_shape: tuple, dtype: str, nbytes: int) -> None:
    """A member whose .npy header declares ``header_shape`` and whose data is ``nbytes`` zeros, streamed."""
    header = {"descr": np.dtype(dtype).str, "fortran_order": False, "shape": header_shape}
    with zf.open(name, "w", force_zip64=True) as fh:
        np.lib.format.write_array_header_1_0(fh, header)
        chunk = bytes(1 << 22)
        while nbytes > 0:
            fh.write(chunk[:min(nbytes, len(chunk))])
            nbytes -= len(chunk)


def _write_zip(path: Path, walk_copy: dict[str, np.ndarray], extra=None) -> None:
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=1) as zf:
        for key, value in walk_copy.items():
            with zf.open(f"{key}.npy", "w") as fh:
                np.lib.format.write_array(fh, np.asarray(value), allow_pickle=False)
        if extra is not None:
            extra(zf)


def _level(walk_copy, t: int) -> slice:
    lo = walk_copy["level_offsets"]
    return slice(int(lo[t]), int(lo[t + 1]))


def _duplicate_cell(a):
    rows = _level(a, 2)
    a["cells"][rows.start + 1] = a["cells"][rows.start]


def _reverse_level(a):
    rows = _level(a, 3)
    a["cells"][rows] = a["cells"][rows][::-1]


def _far_cell(a):
    a["cells"][-1, 0] = 2**62 - 5


def _level0_off_origin(a):
    a["cells"][0, 0] = 1


def _unknown_method(a):
    a["method"] = np.array("magic")


# ----------------------------------------------------------------------------------------- valid files and round trips

def test_valid_file_round_trips(small_table, good_path):
    table = read_table(good_path)
    for key in ARRAY_FIELDS:
        ours, theirs = getattr(table, key), getattr(small_table, key)
        assert ours.dtype == theirs.dtype, key
        np.testing.assert_array_equal(ours, theirs, err_msg=key)
    assert table.system == small_table.system
    assert table.method == small_table.method
    assert table.build_info == small_table.build_info
    assert table.extra == {}
    assert table.horizon == HORIZON


def test_graph_false_leaves_the_flow_graph_unread(small_table, arrays, tmp_path):
    """A policy's read skips the flow graph: its fields are None, and a broken graph array does not matter."""
    graph_keys = ("arc_offsets", "arcs", "arc_flow", "transition_offsets", "transitions", "transition_frac")
    assert all(getattr(small_table, key) is not None for key in graph_keys)
    arrays["arc_flow"] = arrays["arc_flow"][:-1]  # inconsistent with the arcs: read_table rejects it
    path = _write(tmp_path, arrays)
    with pytest.raises(TableError, match=r"'arc_flow' must have shape \[\d+\]"):
        read_table(path)
    table = read_table(path, graph=False)
    assert all(getattr(table, key) is None for key in graph_keys)
    for key in ("cells", "action_probs", "cell_probs", "level_offsets"):
        np.testing.assert_array_equal(getattr(table, key), getattr(small_table, key), err_msg=key)
    small_policy = load_table(path)
    assert small_policy.table.arcs is None and small_policy.num_cells == small_table.cells.shape[0]


def test_two_writes_are_byte_identical(small_table, good_path, tmp_path):
    write_table(tmp_path / "a.npz", small_table)
    write_table(tmp_path / "b.npz", small_table)
    assert (tmp_path / "a.npz").read_bytes() == (tmp_path / "b.npz").read_bytes()
    assert (tmp_path / "a.npz").read_bytes() == good_path.read_bytes()
    # read -> write reproduces the file exactly
    write_table(tmp_path / "c.npz", read_table(good_path))
    assert (tmp_path / "c.npz").read_bytes() == good_path.read_bytes()


def test_unknown_extra_keys_are_ignored_unread(arrays, small_table, tmp_path):
    arrays["my_extra"] = np.arange(7, dtype=np.int16)
    arrays["my_note"] = np.array("hello from a newer builder")
    table = read_table(_write(tmp_path, arrays))
    assert table.extra == {}
    np.testing.assert_array_equal(table.action_probs, small_table.action_probs)


# ---------------------------------------------------------------------------------------------- unreadable table files

@pytest.mark.parametrize("make, match", [pytest.param(m, r, id=i) for i, m, r in UNREADABLE_TABLES])
def test_an_unreadable_table_file_is_one_error(good_path, tmp_path, make, match):
    """Each of tests/cases.py's UNREADABLE_TABLES (missing, a folder, empty, truncated, garbage, another zip, ...)
    made at ``bad.npz`` from the valid table: one TableError."""
    path = tmp_path / "bad.npz"
    make(path, good_path)
    with pytest.raises(TableError, match=match):
        read_table(path)


# --------------------------------------------------------------------------------------- pickled (object-dtype) arrays

def test_pickle_payload_really_runs_when_unpickled(tmp_path):
    """Sanity check of the payload below: np.load(allow_pickle=True) does create the marker."""
    marker = tmp_path / "unpickled"
    np.savez(tmp_path / "p.npz", payload=_object_array(marker))
    with np.load(tmp_path / "p.npz", allow_pickle=True) as z:
        z["payload"][0].close()
    assert marker.exists()


def test_object_array_is_refused_without_unpickling(arrays, tmp_path):
    marker = tmp_path / "unpickled"
    arrays["action_probs"] = _object_array(marker)
    path = tmp_path / "pickled.npz"
    np.savez(path, **arrays)  # np.savez pickles object arrays
    with pytest.raises(TableError, match=r"'action_probs' (must be float32|holds Python objects)"):
        read_table(path)
    assert not marker.exists(), "read_table unpickled data from the file"


def test_unknown_object_array_is_never_read(arrays, tmp_path):
    marker = tmp_path / "unpickled"
    arrays["payload"] = _object_array(marker)
    path = tmp_path / "pickled.npz"
    np.savez(path, **arrays)
    assert read_table(path).extra == {}
    assert not marker.exists(), "read_table unpickled data from the file"


# --------------------------------------------------------------------------------------------- corrupted table content

@pytest.mark.parametrize("mutate, match", [pytest.param(m, r, id=i) for i, m, r in TABLE_CORRUPTIONS])
def test_corrupt_content(arrays, tmp_path, mutate, match):
    mutate(arrays)
    path = _write(tmp_path, arrays)
    with pytest.raises(TableError, match=match) as info:
        read_table(path)
    assert str(path) in str(info.value), "the message should name the file"


def test_unknown_format(arrays, tmp_path):
    arrays["format"] = np.array("cuniform-table/99")
    with pytest.raises(TableError, match=r"unknown table format 'cuniform-table/99'.*cuniform-table/1"):
        read_table(_write(tmp_path, arrays))


@pytest.mark.parametrize("key", REQUIRED_KEYS)
def test_missing_required_key(arrays, tmp_path, key):
    del arrays[key]
    with pytest.raises(TableError, match=rf"missing required key\(s\) {key}$"):
        read_table(_write(tmp_path, arrays))


def test_missing_format_key(arrays, tmp_path):
    del arrays["format"]
    with pytest.raises(TableError, match=r"no 'format' key"):
        read_table(_write(tmp_path, arrays))


# ----------------------------------------------------------------------------------------------------- the system JSON

def test_system_json_unknown_system(arrays, tmp_path):
    spec = _system_spec(arrays)
    spec["name"] = "hovercraft"
    _set_system(arrays, spec)
    with pytest.raises(TableError, match=r"system cannot be rebuilt: unknown system 'hovercraft'.*dubins"):
        read_table(_write(tmp_path, arrays))


def test_system_json_num_actions_does_not_match_actions(arrays, tmp_path):
    spec = _system_spec(arrays)
    spec["params"]["num_actions"] = 7
    _set_system(arrays, spec)
    with pytest.raises(TableError, match=r"actions do not match the system 'dubins' \(7 actions expected\)"):
        read_table(_write(tmp_path, arrays))


def test_system_json_max_omega_does_not_match_actions(arrays, tmp_path):
    spec = _system_spec(arrays)
    spec["params"]["max_omega"] = 1.0
    _set_system(arrays, spec)
    with pytest.raises(TableError, match=r"actions do not match the system"):
        read_table(_write(tmp_path, arrays))


def test_system_json_cell_size_does_not_match(arrays, tmp_path):
    spec = _system_spec(arrays)
    spec["params"]["cell_size"][0] = 0.1
    _set_system(arrays, spec)
    with pytest.raises(TableError, match=r"cell_size .* does not match the system"):
        read_table(_write(tmp_path, arrays))


def test_system_json_horizon_does_not_match_level_offsets(arrays, tmp_path):
    spec = _system_spec(arrays)
    spec["horizon"] = HORIZON + 2
    _set_system(arrays, spec)
    with pytest.raises(TableError, match=rf"horizon {HORIZON + 2} but the table has {HORIZON} steps"):
        read_table(_write(tmp_path, arrays))


def test_system_json_dt_does_not_match_params(arrays, tmp_path):
    spec = _system_spec(arrays)
    spec["dt"] = 0.5
    _set_system(arrays, spec)
    with pytest.raises(TableError, match=r"dt does not match"):
        read_table(_write(tmp_path, arrays))


@pytest.mark.parametrize("bad, match", SYSTEM_JSON_MALFORMED)
def test_system_json_malformed(arrays, tmp_path, bad, match):
    _set_system(arrays, bad)
    with pytest.raises(TableError, match=match):
        read_table(_write(tmp_path, arrays))


@pytest.mark.parametrize("params", [[1, 2], "fast", None])
def test_system_json_params_not_an_object(arrays, tmp_path, params):
    spec = _system_spec(arrays)
    spec["params"] = params
    _set_system(arrays, spec)
    with pytest.raises(TableError, match=r"params"):
        read_table(_write(tmp_path, arrays))


def test_system_json_name_not_a_string(arrays, tmp_path):
    spec = _system_spec(arrays)
    spec["name"] = ["dubins"]
    _set_system(arrays, spec)
    with pytest.raises(TableError, match=r"name"):
        read_table(_write(tmp_path, arrays))


# ------------------------------------------------------------------------------------------------------- zip structure

def test_a_zip_whose_directory_points_at_no_member_is_one_error(tmp_path):
    path = _local_map(tmp_path / "map.npz")
    raw = bytearray(path.read_bytes())
    raw[raw.rfind(b"PK\x05\x06") + 16] ^= 0x10  # the end record's central-directory offset: zipfile reads garbage
    path.write_bytes(bytes(raw))
    for read in (member_headers, read_npz):
        with pytest.raises(NpzError, match=rf"^{path}: member .*not readable \(BadZipFile"):
            read(path)
    with pytest.raises(MapError, match=rf"^--map {path}: not a readable .npz map"):
        read_map_file(path)


# ----------------------------------------------------------------------------------- the system JSON: factories and dt

@pytest.mark.parametrize("factory", ["evil:make", "cuniform_torch.systems.models:RandomWalk1D"])
def test_a_builtin_systems_json_naming_a_factory_is_refused(factory):
    """Nothing is imported either way; but the string would be carried into every checkpoint distilled from it."""
    with pytest.raises(ValueError, match=rf"names factory '{factory}', but 'random_walk_1d' is a built-in system"):
        system_from_json(json.dumps({**WALK_JSON, "factory": factory}))
    assert system_from_json(json.dumps(WALK_JSON))[0] == RandomWalk1D()


def test_a_user_systems_json_names_only_its_registered_factory():
    register_system("damage_walk", DamageWalk)
    try:
        spec = json.loads(system_to_json(DamageWalk(), 8))
        assert spec["factory"] == f"{__name__}:DamageWalk"
        assert system_from_json(json.dumps(spec))[0] == DamageWalk()
        assert system_from_json(json.dumps({k: v for k, v in spec.items() if k != "factory"}))[0] == DamageWalk()
        with pytest.raises(ValueError, match=rf"names factory 'evil:make', but 'damage_walk' is registered from "
                                             rf"'{__name__}:DamageWalk'"):
            system_from_json(json.dumps({**spec, "factory": "evil:make"}))
    finally:
        _REGISTRY.pop("damage_walk", None)


@pytest.mark.parametrize("dt, match", [(1e38, r"dt does not match its params: 1e\+38"), (0.5, r"dt does not match"),
                                       ("1.0", r"dt must be a finite number \(s\), got '1.0'")])
def test_a_system_json_dt_that_its_params_do_not_give_is_refused(dt, match):
    with pytest.raises(ValueError, match=match):
        system_from_json(json.dumps({**WALK_JSON, "dt": dt}))


def test_a_table_naming_a_factory_for_its_builtin_system_is_refused(walk_table, tmp_path):
    write_table(tmp_path / "t.npz", walk_table)
    with np.load(tmp_path / "t.npz", allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files if not k.startswith("content_sha256")}
    spec = json.loads(str(arrays["system"][()]))
    arrays["system"] = np.array(json.dumps({**spec, "factory": "evil:make"}, sort_keys=True))
    write_npz(tmp_path / "forged.npz", {**arrays, **table_digests(arrays)})  # a fresh digest: a forger's copy
    with pytest.raises(TableError, match=r"forged.npz.*names factory 'evil:make', but 'random_walk_1d' is a built-in"):
        read_table(tmp_path / "forged.npz")


# ------------------------------------------------------------------------------------ content digests and cross-checks

def test_a_written_table_carries_both_digests_and_reads_without_a_note(table, tmp_path, capsys):
    path = tmp_path / "t.npz"
    write_table(path, table)
    with np.load(path, allow_pickle=False) as z:
        assert {DIGEST_KEY, NOGRAPH_DIGEST_KEY} <= set(z.files)
        assert len(str(z[DIGEST_KEY][()])) == 64
    for graph in (True, False):
        back = read_table(path, graph=graph)
        assert not hasattr(back, DIGEST_KEY) and back.extra == {}
    assert capsys.readouterr().err == ""


@pytest.mark.parametrize("key", ["action_probs", "cell_probs", "cells", "level_offsets", "system", "start_flip",
                                 "arc_flow", "transition_frac", "transitions"])
@pytest.mark.parametrize("graph", [True, False])
def test_a_flipped_byte_in_a_table_is_refused_naming_the_file(table_arrays, tmp_path, key, graph):
    arrays = dict(table_arrays)
    if key == "start_flip":  # an array the builder left out, added: the digest covers the set of keys too
        arrays["start"], key = np.zeros(3), "start"
    elif key == "system":
        arrays[key] = np.array(str(arrays[key][()]).replace('"speed": 1.0', '"speed": 1.5'))
        assert arrays[key] != table_arrays[key]
    else:
        arrays[key] = _flip_byte(arrays[key])
    path = tmp_path / "bad.npz"
    write_npz(path, arrays)  # the old digests kept
    if not graph and key in GRAPH_KEYS:  # graph=False reads neither the graph nor the digest that covers it
        assert read_table(path, graph=False).arcs is None
        return
    with pytest.raises(TableError, match=rf"^{path} is damaged: its content does not match the digest"):
        read_table(path, graph=graph)


def test_a_table_without_digests_loads_after_one_note(table_arrays, tmp_path, capsys):
    path = tmp_path / "old.npz"
    write_npz(path, {k: v for k, v in table_arrays.items() if k not in (DIGEST_KEY, NOGRAPH_DIGEST_KEY)})
    capsys.readouterr()
    read_table(path)
    read_table(path, graph=False)
    assert len(_notes(capsys.readouterr().err, path)) == 1


def test_a_malformed_digest_is_refused(table_arrays, tmp_path):
    path = tmp_path / "bad.npz"
    write_npz(path, {**table_arrays, DIGEST_KEY: np.array("0" * 63 + "g")})
    with pytest.raises(TableError, match="not a 64-digit hex sha256"):
        read_table(path)


def test_cell_probs_that_transitions_do_not_give_are_refused(table, table_arrays, tmp_path):
    lo = table.level_offsets
    probs = table_arrays["cell_probs"].copy()
    level2 = slice(int(lo[2]), int(lo[3]))
    probs[level2] = probs[level2][::-1]  # still >= 0 and summing to 1: only the propagation can tell
    assert not np.allclose(probs, table_arrays["cell_probs"])
    path = _rewritten({**table_arrays, "cell_probs": probs}, tmp_path / "bad.npz")
    with pytest.raises(TableError, match=rf"{path}: cell_probs do not match transitions: cell row \d+ of level 2"):
        read_table(path)
    assert read_table(path, graph=False).transitions is None  # nothing to compare with: it loads
    with pytest.raises(TableError, match="cell_probs do not match transitions"):
        write_table(tmp_path / "out.npz", replace(table, cell_probs=probs))


def test_cell_probs_within_the_documented_tolerance_pass(table, table_arrays, tmp_path):
    """A relative change of 1e-7 (what float32 action probabilities cause) passes; 1e-3 does not."""
    for scale, ok in ((1 + 1e-7, True), (1 + 1e-3, False)):
        probs = table_arrays["cell_probs"].copy()
        lo = table.level_offsets
        probs[lo[1]] *= scale  # one cell of level 1 ...
        probs[lo[1] + 1] -= probs[lo[1]] - table_arrays["cell_probs"][lo[1]]  # ... the level still sums to 1
        path = _rewritten({**table_arrays, "cell_probs": probs}, tmp_path / f"t{ok}.npz")
        if ok:
            read_table(path)
        else:
            with pytest.raises(TableError, match="cell_probs do not match transitions"):
                read_table(path)


def test_arc_flow_that_does_not_add_up_to_flow_value_is_refused(table, table_arrays, tmp_path):
    flow = table_arrays["arc_flow"].copy()
    step1 = int(table_arrays["arc_offsets"][1])
    flow[step1] += 1  # one more unit into level 2 than flow_value[1] says
    path = _rewritten({**table_arrays, "arc_flow": flow}, tmp_path / "bad.npz")
    with pytest.raises(TableError, match=rf"{path}: arc_flow does not match flow_value: the arcs of step 1 carry "
                                         rf"{int(table.flow_value[1]) + 1} into level 2"):
        read_table(path)
    with pytest.raises(TableError, match="arc_flow does not match flow_value"):
        write_table(tmp_path / "out.npz", replace(table, arc_flow=flow))


@pytest.mark.slow  # a safe-coverage build over a local map (pytest --durations: 5.0 s at load 11, 1.0 s at 3)
def test_a_safe_coverage_table_round_trips(tmp_path):
    """Its cell_probs are a state-level propagation that a map prunes state by state: exempt from the
    cell-level cross-check (documented), so the builder's own table must still write and read."""
    occ = np.zeros((72, 72), np.uint8)
    occ[:, 48:50] = 1  # a wall at x = 0.6 m
    local = LocalMap(occ, (-1.8, -1.8), 0.05)
    system = make_system("dubins", speed=0.5, dt=0.2, max_omega=1.5, num_actions=7,
                         cell_size=(0.05, 0.05, 2 * math.pi / 36))
    built, _ = build_coverage_table(system, CoverageConfig(horizon=4, steps=3, local_map=local, radius=0.2))
    write_table(tmp_path / "safe.npz", built)
    assert read_table(tmp_path / "safe.npz").map_sha256 == local.sha256()


# --------------------------------------------------------------------------------------------------- no code from data

def test_a_table_naming_os_system_runs_nothing(walk_copy, tmp_path):
    marker = tmp_path / "pwned"
    _with_system(walk_copy, name="sys_car", factory="os:system", params={"command": f"touch {marker}"})
    path = tmp_path / "evil.npz"
    write_npz(path, walk_copy)
    for load in (read_table, load_table):
        with pytest.raises(TableError, match=r"unknown system 'sys_car'.*the file names factory 'os:system'.*"
                                             r"Reading a file never imports code it names"):
            load(path)
    assert not marker.exists(), "reading the table ran the command its system JSON names"
    assert "sys_car" not in _REGISTRY


def test_a_module_next_to_the_table_is_never_imported(walk_copy, tmp_path, evil):
    name, markers = evil
    _with_system(walk_copy, name="evil_car", factory=f"{name}:Car")
    path = tmp_path / "evil.npz"
    write_npz(path, walk_copy)
    with pytest.raises(TableError, match=rf"unknown system 'evil_car'.*trust_factory='{name}:Car'"):
        read_table(path)
    with pytest.raises(UnknownSystemError):
        system_from_json(str(walk_copy["system"][()]))
    assert not markers["import"].exists() and not markers["call"].exists() and name not in sys.modules
    assert "evil_car" not in _REGISTRY  # and a later table that only names the system finds nothing either
    with pytest.raises(UnknownSystemError):
        system_from_json(json.dumps({"name": "evil_car", "params": {}, "horizon": 8}))


def test_the_trusted_factory_must_be_the_one_the_file_names(walk_copy, tmp_path, evil):
    name, markers = evil
    _with_system(walk_copy, name="evil_car", factory=f"{name}:Car")
    write_npz(tmp_path / "evil.npz", walk_copy)
    with pytest.raises(TableError, match=rf"the file names factory '{name}:Car', not the trusted "
                                         r"'cuniform_torch.systems:RandomWalk1D'"):
        read_table(tmp_path / "evil.npz", trust_factory="cuniform_torch.systems:RandomWalk1D")
    assert not markers["call"].exists() and "evil_car" not in _REGISTRY


def test_params_are_bound_before_the_trusted_factory_is_called(walk_copy, tmp_path):
    calls = []

    def make_walk(dt: float = 1.0):  # a function factory: calls are visible
        calls.append(dt)
        return RandomWalk1D(dt=dt)

    _with_system(walk_copy, params={"command": "rm -rf /"})
    write_npz(tmp_path / "t.npz", walk_copy)
    _REGISTRY.pop("random_walk_1d")
    try:
        with pytest.raises(TableError, match=r"does not accept \['command'\]"):
            read_table(tmp_path / "t.npz", trust_factory=make_walk)
        assert calls == [] and "random_walk_1d" not in _REGISTRY  # not called, not registered
        _with_system(walk_copy, params={"dt": -1.0})  # binds, builds nothing valid: still not registered
        write_npz(tmp_path / "t.npz", walk_copy)
        with pytest.raises(TableError, match=r"dt must be a positive number"):
            read_table(tmp_path / "t.npz", trust_factory=make_walk)
        assert calls == [-1.0] and "random_walk_1d" not in _REGISTRY
        _with_system(walk_copy, params={"dt": 1.0})
        write_npz(tmp_path / "t.npz", walk_copy)
        assert read_table(tmp_path / "t.npz", trust_factory=make_walk).horizon == 8
        assert _REGISTRY["random_walk_1d"] is make_walk  # registered once the load succeeded
    finally:
        _REGISTRY["random_walk_1d"] = RandomWalk1D


# ------------------------------------------------------------------------------------------------------- bounded reads

def test_an_unknown_member_is_never_decompressed(walk_copy, tmp_path, monkeypatch):
    path = tmp_path / "t.npz"
    _write_zip(path, walk_copy, lambda zf: _zip_member(zf, "bomb.npy", (1 << 24,), "<f8", 8 << 24))
    opened = []
    real_open = zipfile.ZipFile.open
    monkeypatch.setattr(zipfile.ZipFile, "open", lambda self, name, *a, **k: (
        opened.append(getattr(name, "filename", name)), real_open(self, name, *a, **k))[1])
    assert read_table(path).extra == {}
    assert "bomb.npy" not in opened and "cells.npy" in opened


def test_a_decompression_bomb_in_a_known_key_is_refused_before_reading(walk_copy, tmp_path, monkeypatch):
    E = 4_000_000  # 96 + 32 MB declared, a few hundred KB on disk
    T = len(walk_copy["level_offsets"]) - 2
    walk_copy["transition_offsets"] = np.linspace(0, E, T + 1).astype(np.int64)
    for key in ("transitions", "transition_frac"):
        walk_copy.pop(key, None)
    path = tmp_path / "bomb.npz"
    _write_zip(path, walk_copy, lambda zf: (_zip_member(zf, "transitions.npy", (E, 3), "<i8", 24 * E),
                                         _zip_member(zf, "transition_frac.npy", (E,), "<f8", 8 * E)))
    assert path.stat().st_size < 1 << 20
    read = []
    real = np.lib.format.read_array
    monkeypatch.setattr(np.lib.format, "read_array", lambda fh, **k: (read.append(fh.name), real(fh, **k))[1])
    with pytest.raises(TableError, match=r"bomb.npz: its arrays would take \d+ bytes decompressed "
                                         r"\('transitions': 96000128\), more than 200x the file's size"):
        read_table(path)
    assert read == []


def test_a_header_that_lies_about_its_size_is_refused(walk_copy, tmp_path):
    cells = walk_copy.pop("cells")
    path = tmp_path / "t.npz"
    _write_zip(path, walk_copy, lambda zf: _zip_member(zf, "cells.npy", cells.shape, "<i8", cells.nbytes + 8000))
    with pytest.raises(TableError, match=r"array 'cells' holds \d+ bytes, but its header declares"):
        read_table(path)


def test_a_duplicate_zip_member_is_refused(walk_copy, tmp_path):
    path = tmp_path / "t.npz"
    probs = np.full_like(walk_copy["action_probs"], 1.0 / walk_copy["action_probs"].shape[1])

    def second_copy(zf):
        with pytest.warns(UserWarning, match="Duplicate name"):
            with zf.open("action_probs.npy", "w") as fh:
                np.lib.format.write_array(fh, probs)

    _write_zip(path, walk_copy, second_copy)
    with pytest.raises(TableError, match=r"t.npz: the zip holds 'action_probs.npy' twice"):
        read_table(path)


def test_an_absurd_action_count_in_the_system_json_is_a_clear_error(walk_copy, tmp_path):
    _with_system(walk_copy, params={"num_actions": 10**12})
    write_npz(tmp_path / "t.npz", walk_copy)
    with pytest.raises(TableError, match=r"num_actions must be a positive integer \(at most 65536\), got 10+"):
        read_table(tmp_path / "t.npz")


def test_an_absurd_horizon_is_refused_from_the_header(walk_copy, tmp_path):
    walk_copy.pop("level_offsets")
    path = tmp_path / "t.npz"
    _write_zip(path, walk_copy, lambda zf: _zip_member(zf, "level_offsets.npy", (10**6,), "<i8", 8 * 10**6))
    with pytest.raises(TableError, match=r"key 'level_offsets' has 1000000 entries; at most 10002"):
        read_table(path)


# ------------------------------------------------------------------------------------- tables that load silently wrong

@pytest.mark.parametrize("mutate, match", [
    (_duplicate_cell, r"cells of level 2 must be distinct and in ascending order; row \d+ \[-?\d+\] repeats"),
    (_reverse_level, r"cells of level 3 must be distinct and in ascending order; row \d+ \[-?\d+\] comes before"),
    (_far_cell, r"the cells span a box of \d+ cells .*too large to pack into keys"),
    (_level0_off_origin, r"level 0 must be the single start cell \[0\]"),
    (_unknown_method, r"unknown method 'magic'; known: maxflow, coverage"),
], ids=["duplicate-cell", "reversed-rows", "cell-near-2^62", "level-0-off-origin", "unknown-method"])
def test_tables_that_would_load_silently_wrong(walk_copy, tmp_path, mutate, match):
    mutate(walk_copy)
    path = tmp_path / "bad.npz"
    write_npz(path, walk_copy)
    with pytest.raises(TableError, match=rf"bad.npz: {match}"):
        load_table(path)


# ------------------------------------------------------------------------------------------ bounded reads: compression

def test_an_unsupported_compression_method_is_named(walk_copy, tmp_path):
    path = tmp_path / "t.npz"
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for key, value in walk_copy.items():
            with zf.open(zipfile.ZipInfo(f"{key}.npy"), "w") as fh:
                np.lib.format.write_array(fh, np.asarray(value), allow_pickle=False)
    with zipfile.ZipFile(path) as zf:  # rewrite one member with bzip2, which no table writer uses
        members = {i.filename: zf.read(i) for i in zf.infolist()}
    with zipfile.ZipFile(path, "w") as zf:
        for name, data in members.items():
            zf.writestr(name, data, compress_type=zipfile.ZIP_BZIP2 if name == "cells.npy" else zipfile.ZIP_DEFLATED)
    with pytest.raises(TableError, match=r"array 'cells' uses zip compression method 12; a table is stored or deflated"):
        read_table(path)


# ------------------------------------------------------------------------------------------------------- special files

@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="POSIX special files")
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
