"""Bad input gets a clear error: a specific exception type and a message naming the problem.

Never a traceback from deep inside numpy/torch/zipfile, and never a silent wrong answer. Covers the table file
reader (``read_table`` -> ``TableError``), the system registry and dynamics, the build CLI
(``precompute.build.main`` -> "error: ..." and exit code 2), ``rollout`` and ``TablePolicy.rows``.
"""

from __future__ import annotations

import io
import json
import math
import re
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch

from cuniform_torch.common.fileio import write_npz
from cuniform_torch.policies.table import TablePolicy, load_table
from cuniform_torch.sampling.rollout import rollout
from cuniform_torch.systems import Dubins, RandomWalk1D, UnknownSystemError, make_system
from cuniform_torch.tables.file import TABLE_FORMAT, Table, TableError, read_table, write_table
from precompute.build import main as build_main
from precompute.flow.builder import BuildConfig, build_table

HORIZON = 3
REQUIRED_KEYS = ("system", "actions", "cell_size", "periodic", "cell_offset", "level_offsets", "cells",
                 "action_probs", "cell_probs", "flow_value", "flow_target")
ARRAY_FIELDS = REQUIRED_KEYS[1:] + ("arc_offsets", "arcs", "arc_flow", "transition_offsets", "transitions",
                                    "transition_frac")


# ------------------------------------------------------------------------------------------------ fixtures

@pytest.fixture(scope="module")
def small_table() -> Table:
    """A small valid Dubins table (levels 1, 5, 13, 25), built once for this module."""
    table, _ = build_table(make_system("dubins"), BuildConfig(horizon=HORIZON))
    return table


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


@pytest.fixture(scope="module")
def policy(small_table) -> TablePolicy:
    return TablePolicy(small_table)


def _system_spec(arrays: dict[str, np.ndarray]) -> dict:
    return json.loads(str(arrays["system"][()]))


def _set_system(arrays: dict[str, np.ndarray], spec: dict | str) -> None:
    arrays["system"] = np.array(spec if isinstance(spec, str) else json.dumps(spec, sort_keys=True))


def _write(tmp_path: Path, arrays: dict[str, np.ndarray], name: str = "bad.npz") -> Path:
    path = tmp_path / name
    write_npz(path, arrays)
    return path


# ------------------------------------------------------------------------------ valid files and round trips

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
    policy = load_table(path)
    assert policy.table.arcs is None and policy.num_cells == small_table.cells.shape[0]


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


# --------------------------------------------------------------------------------- unreadable table files

def test_missing_file(tmp_path):
    with pytest.raises(TableError, match="no table file there"):
        read_table(tmp_path / "nope.npz")


def test_directory_instead_of_file(tmp_path):
    (tmp_path / "dir.npz").mkdir()
    with pytest.raises(TableError, match="no table file there"):
        read_table(tmp_path / "dir.npz")


def test_empty_file(tmp_path):
    (tmp_path / "empty.npz").write_bytes(b"")
    with pytest.raises(TableError, match="not a readable .npz table"):
        read_table(tmp_path / "empty.npz")


def test_truncated_file(good_path, tmp_path):
    data = good_path.read_bytes()
    path = tmp_path / "truncated.npz"
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(TableError, match="not a readable .npz table|corrupt or truncated"):
        read_table(path)


def test_damaged_middle_of_file(good_path, tmp_path):
    data = bytearray(good_path.read_bytes())
    mid = len(data) // 2
    data[mid - 64: mid + 64] = bytes(128)
    path = tmp_path / "damaged.npz"
    path.write_bytes(bytes(data))
    with pytest.raises(TableError, match="not a readable .npz table|corrupt or truncated"):
        read_table(path)


def test_random_garbage(tmp_path):
    path = tmp_path / "garbage.npz"
    path.write_bytes(np.random.default_rng(0).bytes(4096))
    with pytest.raises(TableError, match="not a readable .npz table"):
        read_table(path)


def test_valid_zip_that_is_not_a_table(tmp_path):
    path = tmp_path / "other.npz"
    np.savez(path, foo=np.arange(3))
    with pytest.raises(TableError, match="no 'format' key"):
        read_table(path)


def test_zip_without_npy_members(tmp_path):
    path = tmp_path / "plain.npz"
    with zipfile.ZipFile(path, "w") as zf:
        zf.writestr("readme.txt", b"not arrays")
    with pytest.raises(TableError, match="no 'format' key"):
        read_table(path)


def test_npy_file_instead_of_npz(tmp_path):
    path = tmp_path / "array.npz"
    with open(path, "wb") as fh:
        np.save(fh, np.arange(5))
    with pytest.raises(TableError, match="not a .*table|npz"):
        read_table(path)


def test_format_member_that_is_not_an_array(tmp_path):
    path = tmp_path / "rawformat.npz"
    with zipfile.ZipFile(path, "w") as zf:
        zf.writestr("format", TABLE_FORMAT.encode())
    with pytest.raises(TableError, match="format"):
        read_table(path)


def test_required_member_that_is_not_an_array(good_arrays, tmp_path):
    path = tmp_path / "rawcells.npz"
    with zipfile.ZipFile(path, "w") as zf:
        for key, value in good_arrays.items():
            if key == "cells":
                zf.writestr("cells", b"not an array")
            else:
                buf = io.BytesIO()
                np.lib.format.write_array(buf, value, allow_pickle=False)
                zf.writestr(f"{key}.npy", buf.getvalue())
    with pytest.raises(TableError, match="cells"):
        read_table(path)


# ------------------------------------------------------------------------- pickled (object-dtype) arrays

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


# --------------------------------------------------------------------------------- corrupted table content

def _scale_row(a):
    a["action_probs"][0] *= 0.5


def _negative_prob(a):
    a["action_probs"][1] = 0.0
    a["action_probs"][1, :2] = (1.5, -0.5)


def _nan_prob(a):
    a["action_probs"][2, 0] = np.nan


def _nan_cell_prob(a):
    a["cell_probs"][3] = np.nan


def _inf_cell_size(a):
    a["cell_size"][0] = np.inf


def _offsets_end_short(a):
    a["level_offsets"][-1] -= 1


def _offsets_end_long(a):
    a["level_offsets"][-1] += 1


def _offsets_not_increasing(a):
    a["level_offsets"][2] = a["level_offsets"][1]


def _offsets_not_from_zero(a):
    a["level_offsets"][0] = 1


def _cell_probs_short(a):
    a["cell_probs"] = a["cell_probs"][:-1]


def _action_probs_narrow(a):
    a["action_probs"] = np.ascontiguousarray(a["action_probs"][:, :-1])


def _cell_probs_level_sum(a):
    a["cell_probs"][-1] += 0.01


def _flow_target(a):
    a["flow_target"][0] += 1


def _flow_value(a):
    a["flow_value"][0] = a["flow_target"][0] + 1


def _angle_cell(a):
    a["cells"][-1, 2] = 40  # K = 40 angle cells: valid indices are 0..39


def _arc_outside(a):
    a["arcs"][0, 1] = len(a["cells"]) + 5


def _arc_wrong_level(a):
    a["arcs"][0, 1] = 0  # step 0 arcs must end in level 1


def _transitions_alone(a):
    del a["transition_frac"]


def _periodic_changed(a):
    a["periodic"][2] = False


def _format_bytes(a):
    a["format"] = np.array(TABLE_FORMAT.encode())


def _format_list(a):
    a["format"] = np.array([TABLE_FORMAT])


def _system_not_string(a):
    a["system"] = np.array(3)


def _method_not_string(a):
    a["method"] = np.arange(2)


CORRUPTIONS = [
    # dtype / ndim
    ("action_probs-float64", lambda a: a.update(action_probs=a["action_probs"].astype(np.float64)),
     r"'action_probs' must be float32"),
    ("cells-int32", lambda a: a.update(cells=a["cells"].astype(np.int32)), r"'cells' must be int64"),
    ("level_offsets-float64", lambda a: a.update(level_offsets=a["level_offsets"].astype(np.float64)),
     r"'level_offsets' must be int64"),
    ("periodic-uint8", lambda a: a.update(periodic=a["periodic"].astype(np.uint8)), r"'periodic' must be bool"),
    ("actions-float64", lambda a: a.update(actions=a["actions"].astype(np.float64)), r"'actions' must be float32"),
    ("cell_probs-2d", lambda a: a.update(cell_probs=a["cell_probs"][:, None]), r"'cell_probs' must be float64 with 1"),
    ("arcs-float", lambda a: a.update(arcs=a["arcs"].astype(np.float64)), r"'arcs' must be int64"),
    ("format-bytes", _format_bytes, r"'format' must be a string"),
    ("format-list", _format_list, r"'format' must be a string"),
    ("system-int", _system_not_string, r"'system' must be a string"),
    ("method-array", _method_not_string, r"'method' must be a string"),
    # probabilities
    ("nan-action_probs", _nan_prob, r"action_probs contains NaN"),
    ("nan-cell_probs", _nan_cell_prob, r"cell_probs contains NaN"),
    ("inf-cell_size", _inf_cell_size, r"cell_size contains NaN or infinite"),
    ("row-sum", _scale_row, r"action_probs rows must sum to 1; row 0 sums to 0\.5"),
    ("negative-prob", _negative_prob, r"action_probs must lie in \[0, 1\]"),
    ("level-sum", _cell_probs_level_sum, r"cell_probs must sum to 1 in every level"),
    # shapes and offsets
    ("cell_probs-short", _cell_probs_short, r"'cell_probs' must have shape \[44\] .*header says \[43\]"),
    ("action_probs-narrow", _action_probs_narrow, r"'action_probs' must have shape \[44, 5\] .*header says \[44, 4\]"),
    ("offsets-end-short", _offsets_end_short, r"'cells' must have shape \[43, 3\] .*header says \[44, 3\]"),
    ("offsets-end-long", _offsets_end_long, r"'cells' must have shape \[45, 3\] .*header says \[44, 3\]"),
    ("offsets-flat", _offsets_not_increasing, r"level_offsets must .*increase strictly"),
    ("offsets-start", _offsets_not_from_zero, r"level_offsets must start at 0"),
    ("flow_target", _flow_target, r"flow_target must be n_t \* n_\{t\+1\}"),
    ("flow_value", _flow_value, r"flow_value must lie in \[0, flow_target\]"),
    ("angle-cell", _angle_cell, r"cells of angle dimension 2 must lie in \[0, 40\)"),
    ("arc-outside", _arc_outside, r"arcs refer to rows outside the table"),
    ("arc-level", _arc_wrong_level, r"arcs of step t must go from level t to level t\+1"),
    ("transitions-alone", _transitions_alone, r"transition_offsets, transitions and transition_frac must be stored together"),
    ("periodic-changed", _periodic_changed, r"periodic .* does not match the system"),
]


@pytest.mark.parametrize("mutate, match", [pytest.param(m, r, id=i) for i, m, r in CORRUPTIONS])
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


# --------------------------------------------------------------------------------------- the system JSON

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


@pytest.mark.parametrize("bad, match", [
    ("{not json", r"system JSON does not parse"),
    ("[1, 2]", r"system JSON must be an object with name, params and horizon"),
    ('{"name": "dubins", "params": {}}', r"system JSON must be an object with name, params and horizon"),
    ('{"name": "dubins", "params": {"speeed": 1}, "horizon": 3}', r"no parameter\(s\) speeed"),
    ('{"name": "dubins", "params": {"num_actions": 0}, "horizon": 3}', r"num_actions must be a positive integer"),
    ('{"name": "dubins", "params": {}, "horizon": "3"}', r"horizon must be a positive integer"),
])
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


# ------------------------------------------------------------------------------------------------ systems

def test_unknown_system_lists_known_names():
    with pytest.raises(UnknownSystemError, match=r"unknown system 'nope'") as info:
        make_system("nope")
    assert isinstance(info.value, ValueError)
    assert "dubins" in str(info.value) and "random_walk_1d" in str(info.value)


@pytest.mark.parametrize("name, params, bad", [
    ("dubins", {"speeed": 1.0}, "speeed"),
    ("dubins", {"max_speed": 1.0}, "max_speed"),
    ("random_walk_1d", {"speed": 2.0}, "speed"),
    ("random_walk_1d", {"horizon": 3, "v": 1}, "horizon, v"),
])
def test_unknown_parameter_names(name, params, bad):
    with pytest.raises(ValueError, match=rf"system '{name}' has no parameter\(s\) {bad}; its parameters: .*cell_size"):
        make_system(name, **params)


TAU = 2.0 * math.pi
BAD_PARAMS = [
    ("dubins", {"speed": 0.0}, r"dubins: speed must be a positive number, got 0\.0"),
    ("dubins", {"speed": -1.0}, r"dubins: speed must be a positive number"),
    ("dubins", {"speed": float("nan")}, r"dubins: speed must be a positive number"),
    ("dubins", {"dt": 0.0}, r"dubins: dt must be a positive number"),
    ("dubins", {"dt": -0.2}, r"dubins: dt must be a positive number"),
    ("dubins", {"dt": "0.2"}, r"dubins: dt must be a positive number, got '0\.2'"),
    ("dubins", {"max_omega": -1.0}, r"dubins: max_omega must be a non-negative number"),
    ("random_walk_1d", {"dt": 0}, r"random_walk_1d: dt must be a positive number"),
    ("random_walk_1d", {"max_speed": 0.0}, r"random_walk_1d: max_speed must be a positive number"),
    ("dubins", {"cell_size": (0.0, 0.05, TAU / 40)}, r"dubins: cell_size must be positive"),
    ("dubins", {"cell_size": (0.05, -0.05, TAU / 40)}, r"dubins: cell_size must be positive"),
    ("random_walk_1d", {"cell_size": (0.0,)}, r"random_walk_1d: cell_size must be positive"),
    ("dubins", {"cell_size": (0.05, 0.05, 0.3)}, r"dubins: the angle cell size must divide 2\*pi"),
    ("dubins", {"cell_size": (0.05, 0.05, 7.0)}, r"dubins: the angle cell size must divide 2\*pi"),
    ("dubins", {"cell_size": (0.05, 0.05, TAU / 40 * 1.01)}, r"dubins: the angle cell size must divide 2\*pi"),
    ("dubins", {"cell_offset": (0.0, 0.0, 0.5)}, r"dubins: cell_offset .*\|offset\| < 0\.5"),
    ("dubins", {"cell_offset": (-0.5, 0.0, 0.0)}, r"dubins: cell_offset .*\|offset\| < 0\.5"),
    ("random_walk_1d", {"cell_offset": (0.7,)}, r"random_walk_1d: cell_offset .*\|offset\| < 0\.5"),
    ("dubins", {"cell_offset": (0.0, 0.0, float("nan"))}, r"dubins: cell_offset must be finite"),
    ("dubins", {"cell_size": (0.05, 0.05)}, r"dubins: cell_size needs 3 value\(s\).*got 2"),
    ("dubins", {"cell_size": (0.05,) * 4}, r"dubins: cell_size needs 3 value\(s\).*got 4"),
    ("random_walk_1d", {"cell_size": (0.5, 0.5)}, r"random_walk_1d: cell_size needs 1 value\(s\).*got 2"),
    ("dubins", {"cell_offset": (0.0,)}, r"dubins: cell_offset needs 3 value\(s\)"),
    ("dubins", {"cell_size": 0.05}, r"dubins: cell_size must be a sequence of 3 numbers"),
    ("dubins", {"num_actions": 0}, r"dubins: num_actions must be a positive integer .at most 65536., got 0"),
    ("dubins", {"num_actions": -3}, r"dubins: num_actions must be a positive integer"),
    ("dubins", {"num_actions": 2.5}, r"dubins: num_actions must be a positive integer"),
    ("dubins", {"num_actions": True}, r"dubins: num_actions must be a positive integer"),
    ("random_walk_1d", {"num_actions": 0}, r"random_walk_1d: num_actions must be a positive integer"),
]


@pytest.mark.parametrize("name, params, match", BAD_PARAMS,
                         ids=[f"{n}-{'-'.join(f'{k}={v!r}' for k, v in p.items())}" for n, p, _ in BAD_PARAMS])
def test_bad_system_parameters(name, params, match):
    with pytest.raises(ValueError, match=match):
        make_system(name, **params)


def test_non_numeric_cell_size_names_the_field():
    with pytest.raises(ValueError, match=r"dubins: cell_size"):
        make_system("dubins", cell_size=("a", "b", "c"))


@pytest.mark.parametrize("x_shape, u_shape, match", [
    ((4, 2), (4, 1), r"dubins\.step: x must have shape \[N, 3\], got \[4, 2\]"),
    ((3,), (1,), r"dubins\.step: x must have shape \[N, 3\], got \[3\]"),
    ((4, 3, 1), (4, 1), r"dubins\.step: x must have shape \[N, 3\], got \[4, 3, 1\]"),
    ((4, 3), (4,), r"dubins\.step: u must have shape \[4, 1\], got \[4\]"),
    ((4, 3), (4, 2), r"dubins\.step: u must have shape \[4, 1\], got \[4, 2\]"),
    ((4, 3), (5, 1), r"dubins\.step: u must have shape \[4, 1\], got \[5, 1\]"),
])
def test_dubins_step_bad_shapes(x_shape, u_shape, match):
    with pytest.raises(ValueError, match=match):
        Dubins().step(torch.zeros(x_shape), torch.zeros(u_shape))


def test_random_walk_step_bad_shapes():
    with pytest.raises(ValueError, match=r"random_walk_1d\.step: x must have shape \[N, 1\], got \[4, 3\]"):
        RandomWalk1D().step(torch.zeros(4, 3), torch.zeros(4, 1))
    with pytest.raises(ValueError, match=r"random_walk_1d\.step: u must have shape \[4, 1\], got \[4, 5\]"):
        RandomWalk1D().step(torch.zeros(4, 1), torch.zeros(4, 5))


# ---------------------------------------------------------------------------------------------------- CLI

def _cli(tmp_path: Path, *args: str) -> tuple[list[str], Path]:
    out = tmp_path / "t.npz"
    return ["--out", str(out), "--quiet", "--no-report", *args], out


def _exit_code(main, argv) -> int:
    """``main(argv)``'s exit code: its return value, or argparse's exit for a flag value refused as it parses."""
    try:
        return main(argv)
    except SystemExit as exc:
        return exc.code


@pytest.mark.parametrize("args, match", [
    (["--system", "nope"], r"unknown system 'nope'; known systems: .*dubins"),
    (["--system", "dubins", "--horizon", "0"], r"argument --horizon: must be an integer in \[1, 1000\].*got 0"),
    (["--system", "dubins", "--horizon", "-2"], r"argument --horizon: must be an integer in \[1, 1000\]"),
    (["--system", "dubins", "--horizon", "1", "--cell-size", "0", "0.05", "0.157"], r"dubins: cell_size must be positive"),
    (["--system", "dubins", "--horizon", "1", "--cell-size", "0.05", "0.05"], r"dubins: cell_size needs 3 value\(s\)"),
    (["--system", "dubins", "--horizon", "1", "--cell-size", "0.05", "0.05", "0.3"], r"angle cell size must divide 2\*pi"),
    (["--system", "random_walk_1d", "--speed", "2"], r"system 'random_walk_1d' has no parameter\(s\) speed"),
    (["--system", "random_walk_1d", "--max-omega", "1"], r"system 'random_walk_1d' has no parameter\(s\) max_omega"),
    (["--system", "dubins", "--max-speed", "1"], r"system 'dubins' has no parameter\(s\) max_speed"),
    (["--system", "dubins", "--horizon", "1", "--num-actions", "0"], r"argument --num-actions: must be an integer in"),
    (["--system", "dubins", "--horizon", "1", "--dt", "0"], r"dubins: dt must be a positive number"),
    (["--system", "dubins", "--horizon", "1", "--cell-offset", "0", "0", "0.5"], r"\|offset\| < 0\.5"),
    (["--system", "random_walk_1d", "--horizon", "1", "--points", "random", "--points-per-cell", "0"],
     r"argument --points-per-cell: must be an integer in"),
])
def test_cli_bad_input(tmp_path, capsys, args, match):
    argv, out = _cli(tmp_path, *args)
    assert _exit_code(build_main, argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: "), err
    assert re.search(match, err), err
    assert "Traceback" not in err
    assert not out.exists()


def test_cli_bad_flag_value_is_an_argparse_error(tmp_path, capsys):
    argv, out = _cli(tmp_path, "--system", "dubins", "--horizon", "abc")
    with pytest.raises(SystemExit) as info:
        build_main(argv)
    assert info.value.code == 2
    assert "argument --horizon: invalid int value: 'abc'" in capsys.readouterr().err
    assert not out.exists()


def test_cli_valid_control(tmp_path, capsys):
    """The same flags with good values do build (so the failures above are about the values)."""
    argv, out = _cli(tmp_path, "--system", "random_walk_1d", "--horizon", "1")
    assert build_main(argv) == 0
    assert read_table(out).horizon == 1


def test_cli_out_is_a_directory(tmp_path, capsys):
    out = tmp_path / "adir"
    out.mkdir()
    rc = build_main(["--out", str(out), "--quiet", "--no-report", "--system", "random_walk_1d", "--horizon", "1"])
    assert rc == 2
    assert re.search(r"error: .*adir", capsys.readouterr().err)


def test_cli_out_parent_is_a_file(tmp_path, capsys):
    (tmp_path / "afile").write_text("x")
    out = tmp_path / "afile" / "t.npz"
    rc = build_main(["--out", str(out), "--quiet", "--no-report", "--system", "random_walk_1d", "--horizon", "1"])
    assert rc == 2
    assert re.search(r"error: .*afile", capsys.readouterr().err)


def test_cli_bad_device(tmp_path, capsys):
    out = tmp_path / "t.npz"
    rc = _exit_code(build_main, ["--out", str(out), "--quiet", "--system", "random_walk_1d", "--horizon", "1",
                                 "--rollouts", "10", "--device", "nope"])
    assert rc == 2
    assert re.search(r"error: .*device.*nope", capsys.readouterr().err)


# ------------------------------------------------------------------------------------ rollout and policy

def test_rollout_valid_control(policy):
    states, actions = rollout(policy.system, policy, torch.zeros(3), 8, HORIZON,
                              generator=torch.Generator().manual_seed(0))
    assert states.shape == (8, HORIZON + 1, 3) and actions.shape == (8, HORIZON, 1)


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_rollout_non_finite_x0(policy, bad):
    x0 = torch.tensor([0.0, bad, 0.0])
    with pytest.raises(ValueError, match=r"x0 contains NaN or infinite values"):
        rollout(policy.system, policy, x0, 4, 2)
    x0 = torch.zeros(4, 3)
    x0[2, 0] = bad
    with pytest.raises(ValueError, match=r"x0 contains NaN or infinite values"):
        rollout(policy.system, policy, x0, 4, 2)


def test_rollout_names_a_system_whose_step_returns_a_wrong_shape(policy):
    class Truncating(Dubins):
        def step(self, x, u):
            return super().step(x, u)[:, :2]

    # probed once, before the rollout (check_dynamics): the shape of the probe's batch, then what it must be
    with pytest.raises(ValueError, match=r"'dubins' \(Truncating\): step\(x, u\).* returned a \[4, 2\] tensor.*must "
                                         r"return \[4, 3\]"):
        rollout(Truncating(), policy, torch.zeros(3), 4, 2)


@pytest.mark.parametrize("shape", [(2,), (4,), (5, 3), (4, 2), (4, 3, 1), ()])
def test_rollout_wrong_x0_shape(policy, shape):
    with pytest.raises(ValueError, match=rf"x0 must have shape \[3\] or \[4, 3\], got {re.escape(str(list(shape)))}"):
        rollout(policy.system, policy, torch.zeros(shape), 4, 2)


def test_rollout_horizon_longer_than_table(policy):
    with pytest.raises(ValueError, match=rf"horizon {HORIZON + 1} is longer than the policy's table \({HORIZON} steps\)"):
        rollout(policy.system, policy, torch.zeros(3), 4, HORIZON + 1)


def test_rollout_negative_horizon(policy):
    with pytest.raises(ValueError, match=r"horizon"):
        rollout(policy.system, policy, torch.zeros(3), 4, -1)


def test_rollout_non_integer_horizon(policy):
    with pytest.raises((ValueError, TypeError), match=r"horizon"):
        rollout(policy.system, policy, torch.zeros(3), 4, 2.5)


def test_rollout_negative_num_samples(policy):
    with pytest.raises(ValueError, match=r"num_samples"):
        rollout(policy.system, policy, torch.zeros(3), -2, 2)


def test_rollout_integer_x0(policy):
    with pytest.raises(ValueError, match=r"dtype|floating"):
        rollout(policy.system, policy, torch.zeros(3, dtype=torch.int64), 4, 2)


def test_rows_valid_control(policy):
    assert policy.rows(torch.zeros(2, 3), 0).tolist() == [0, 0]


@pytest.mark.parametrize("shape", [(4, 2), (3,), (4, 3, 1), (4, 1)])
def test_rows_wrong_state_shape(policy, shape):
    with pytest.raises(ValueError, match=rf"states must have shape \[N, 3\], got {re.escape(str(list(shape)))}"):
        policy.rows(torch.zeros(shape), 0)


@pytest.mark.parametrize("t", [-1, HORIZON + 1, 100])
def test_rows_level_outside_table(policy, t):
    with pytest.raises(ValueError, match=rf"level t={t} is outside the table's levels 0\.\.{HORIZON}"):
        policy.rows(torch.zeros(2, 3), t)
    with pytest.raises(ValueError, match=rf"level t={t} is outside"):
        policy.action_probs(torch.zeros(2, 3), t)


def test_rows_non_integer_level(policy):
    with pytest.raises(ValueError, match=r"level"):
        policy.rows(torch.zeros(2, 3), 1.5)


def test_rows_integer_states(policy):
    with pytest.raises(ValueError, match=r"dtype|floating"):
        policy.rows(torch.zeros(2, 3, dtype=torch.int64), 0)


def test_table_policy_sample_names_a_generator_that_is_not_one(policy):
    with pytest.raises(TypeError, match=r"generator must be a torch.Generator or None, got int"):
        policy.sample(torch.zeros(4, 3), 0, generator=0)
