"""Untrusted files run no code and cannot exhaust memory; tables and checkpoints that would load silently
wrong are refused, each with an error naming the file and the key.

The trust model (README, "The trust model"): reading a table or checkpoint never imports or calls anything
the file names. A system comes from the registry, or from a ``trust_factory`` the caller names.
"""

from __future__ import annotations

import json
import math
import sys
import uuid
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch

from cuniform_torch.common.fileio import write_npz
from cuniform_torch.policies.checkpoint import PolicyCheckpointError, load_policy, policy_checkpoint, save_policy
from cuniform_torch.policies.mlp import MLPConfig, MLPPolicy
from cuniform_torch.policies.table import load_table
from cuniform_torch.systems import _REGISTRY, RandomWalk1D, UnknownSystemError, system_from_json, system_to_json
from cuniform_torch.tables.file import TableError, read_table, write_table

EVIL_MODULE = """
from pathlib import Path
Path({import_marker!r}).write_text("imported")

def Car(**params):
    Path({call_marker!r}).write_text("called")
    raise RuntimeError("the factory ran")
"""


@pytest.fixture(scope="module")
def walk_arrays(walk_table, tmp_path_factory) -> dict[str, np.ndarray]:
    return written_arrays(walk_table, tmp_path_factory.mktemp("walk") / "walk.npz")


def written_arrays(table, path) -> dict[str, np.ndarray]:
    """The arrays of ``table`` as :func:`write_table` writes them to ``path`` (digests included)."""
    write_table(path, table)
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


@pytest.fixture()
def arrays(walk_arrays) -> dict[str, np.ndarray]:
    """A writable copy without the content digests (an older file: the digest would refuse any edit first)."""
    return {k: np.array(v, copy=True) for k, v in walk_arrays.items() if not k.startswith("content_sha256")}


def _with_system(arrays: dict[str, np.ndarray], **spec) -> dict[str, np.ndarray]:
    base = {"name": "random_walk_1d", "params": {}, "dt": 1.0, "horizon": 8}
    arrays["system"] = np.array(json.dumps({**base, **spec}, sort_keys=True))
    return arrays


@pytest.fixture()
def evil(tmp_path, monkeypatch):
    """A module next to the table, on sys.path and in the working directory, that leaves markers when it is
    imported or its factory is called."""
    name = f"evil_{uuid.uuid4().hex[:8]}"
    markers = {"import": tmp_path / "imported", "call": tmp_path / "called"}
    (tmp_path / f"{name}.py").write_text(EVIL_MODULE.format(import_marker=str(markers["import"]),
                                                          call_marker=str(markers["call"])))
    monkeypatch.chdir(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))
    yield name, markers
    sys.modules.pop(name, None)
    _REGISTRY.pop("evil_car", None)


# ----------------------------------------------------------------------------------- no code from data

def test_a_table_naming_os_system_runs_nothing(arrays, tmp_path):
    marker = tmp_path / "pwned"
    _with_system(arrays, name="sys_car", factory="os:system", params={"command": f"touch {marker}"})
    path = tmp_path / "evil.npz"
    write_npz(path, arrays)
    for load in (read_table, load_table):
        with pytest.raises(TableError, match=r"unknown system 'sys_car'.*the file names factory 'os:system'.*"
                                             r"Reading a file never imports code it names"):
            load(path)
    assert not marker.exists(), "reading the table ran the command its system JSON names"
    assert "sys_car" not in _REGISTRY


def test_a_module_next_to_the_table_is_never_imported(arrays, tmp_path, evil):
    name, markers = evil
    _with_system(arrays, name="evil_car", factory=f"{name}:Car")
    path = tmp_path / "evil.npz"
    write_npz(path, arrays)
    with pytest.raises(TableError, match=rf"unknown system 'evil_car'.*trust_factory='{name}:Car'"):
        read_table(path)
    with pytest.raises(UnknownSystemError):
        system_from_json(str(arrays["system"][()]))
    assert not markers["import"].exists() and not markers["call"].exists() and name not in sys.modules
    assert "evil_car" not in _REGISTRY  # and a later table that only names the system finds nothing either
    with pytest.raises(UnknownSystemError):
        system_from_json(json.dumps({"name": "evil_car", "params": {}, "horizon": 8}))


def test_a_checkpoint_naming_a_factory_runs_nothing(tmp_path, evil):
    name, markers = evil
    policy = _walk_policy()
    ckpt = policy_checkpoint(policy, json.dumps({"name": "evil_car", "params": {}, "dt": 1.0, "horizon": 8,
                                                 "factory": f"{name}:Car"}))
    save_policy(tmp_path / "evil.pt", ckpt)
    with pytest.raises(PolicyCheckpointError, match=r"unknown system 'evil_car'"):
        load_policy(tmp_path / "evil.pt")
    assert not markers["import"].exists() and not markers["call"].exists()


def test_the_trusted_factory_must_be_the_one_the_file_names(arrays, tmp_path, evil):
    name, markers = evil
    _with_system(arrays, name="evil_car", factory=f"{name}:Car")
    write_npz(tmp_path / "evil.npz", arrays)
    with pytest.raises(TableError, match=rf"the file names factory '{name}:Car', not the trusted "
                                         r"'cuniform_torch.systems:RandomWalk1D'"):
        read_table(tmp_path / "evil.npz", trust_factory="cuniform_torch.systems:RandomWalk1D")
    assert not markers["call"].exists() and "evil_car" not in _REGISTRY


def test_params_are_bound_before_the_trusted_factory_is_called(arrays, tmp_path):
    calls = []

    def make_walk(dt: float = 1.0):  # a function factory: calls are visible
        calls.append(dt)
        return RandomWalk1D(dt=dt)

    _with_system(arrays, params={"command": "rm -rf /"})
    write_npz(tmp_path / "t.npz", arrays)
    _REGISTRY.pop("random_walk_1d")
    try:
        with pytest.raises(TableError, match=r"does not accept \['command'\]"):
            read_table(tmp_path / "t.npz", trust_factory=make_walk)
        assert calls == [] and "random_walk_1d" not in _REGISTRY  # not called, not registered
        _with_system(arrays, params={"dt": -1.0})  # binds, builds nothing valid: still not registered
        write_npz(tmp_path / "t.npz", arrays)
        with pytest.raises(TableError, match=r"dt must be a positive number"):
            read_table(tmp_path / "t.npz", trust_factory=make_walk)
        assert calls == [-1.0] and "random_walk_1d" not in _REGISTRY
        _with_system(arrays, params={"dt": 1.0})
        write_npz(tmp_path / "t.npz", arrays)
        assert read_table(tmp_path / "t.npz", trust_factory=make_walk).horizon == 8
        assert _REGISTRY["random_walk_1d"] is make_walk  # registered once the load succeeded
    finally:
        _REGISTRY["random_walk_1d"] = RandomWalk1D


# ------------------------------------------------------------------------------------------ bounded reads

def _zip_member(zf: zipfile.ZipFile, name: str, header_shape: tuple, dtype: str, nbytes: int) -> None:
    """A member whose .npy header declares ``header_shape`` and whose data is ``nbytes`` zeros, streamed."""
    header = {"descr": np.dtype(dtype).str, "fortran_order": False, "shape": header_shape}
    with zf.open(name, "w", force_zip64=True) as fh:
        np.lib.format.write_array_header_1_0(fh, header)
        chunk = bytes(1 << 22)
        while nbytes > 0:
            fh.write(chunk[:min(nbytes, len(chunk))])
            nbytes -= len(chunk)


def _write_zip(path: Path, arrays: dict[str, np.ndarray], extra=None) -> None:
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=1) as zf:
        for key, value in arrays.items():
            with zf.open(f"{key}.npy", "w") as fh:
                np.lib.format.write_array(fh, np.asarray(value), allow_pickle=False)
        if extra is not None:
            extra(zf)


def test_an_unknown_member_is_never_decompressed(arrays, tmp_path, monkeypatch):
    path = tmp_path / "t.npz"
    _write_zip(path, arrays, lambda zf: _zip_member(zf, "bomb.npy", (1 << 24,), "<f8", 8 << 24))
    opened = []
    real_open = zipfile.ZipFile.open
    monkeypatch.setattr(zipfile.ZipFile, "open", lambda self, name, *a, **k: (
        opened.append(getattr(name, "filename", name)), real_open(self, name, *a, **k))[1])
    assert read_table(path).extra == {}
    assert "bomb.npy" not in opened and "cells.npy" in opened


def test_a_decompression_bomb_in_a_known_key_is_refused_before_reading(arrays, tmp_path, monkeypatch):
    E = 4_000_000  # 96 + 32 MB declared, a few hundred KB on disk
    T = len(arrays["level_offsets"]) - 2
    arrays["transition_offsets"] = np.linspace(0, E, T + 1).astype(np.int64)
    for key in ("transitions", "transition_frac"):
        arrays.pop(key, None)
    path = tmp_path / "bomb.npz"
    _write_zip(path, arrays, lambda zf: (_zip_member(zf, "transitions.npy", (E, 3), "<i8", 24 * E),
                                         _zip_member(zf, "transition_frac.npy", (E,), "<f8", 8 * E)))
    assert path.stat().st_size < 1 << 20
    read = []
    real = np.lib.format.read_array
    monkeypatch.setattr(np.lib.format, "read_array", lambda fh, **k: (read.append(fh.name), real(fh, **k))[1])
    with pytest.raises(TableError, match=r"bomb.npz: its arrays would take \d+ bytes decompressed "
                                         r"\('transitions': 96000128\), more than 200x the file's size"):
        read_table(path)
    assert read == []


def test_a_header_that_lies_about_its_size_is_refused(arrays, tmp_path):
    cells = arrays.pop("cells")
    path = tmp_path / "t.npz"
    _write_zip(path, arrays, lambda zf: _zip_member(zf, "cells.npy", cells.shape, "<i8", cells.nbytes + 8000))
    with pytest.raises(TableError, match=r"array 'cells' holds \d+ bytes, but its header declares"):
        read_table(path)


def test_a_duplicate_zip_member_is_refused(arrays, tmp_path):
    path = tmp_path / "t.npz"
    probs = np.full_like(arrays["action_probs"], 1.0 / arrays["action_probs"].shape[1])

    def second_copy(zf):
        with pytest.warns(UserWarning, match="Duplicate name"):
            with zf.open("action_probs.npy", "w") as fh:
                np.lib.format.write_array(fh, probs)

    _write_zip(path, arrays, second_copy)
    with pytest.raises(TableError, match=r"t.npz: the zip holds 'action_probs.npy' twice"):
        read_table(path)


def test_an_absurd_action_count_in_the_system_json_is_a_clear_error(arrays, tmp_path):
    _with_system(arrays, params={"num_actions": 10**12})
    write_npz(tmp_path / "t.npz", arrays)
    with pytest.raises(TableError, match=r"num_actions must be a positive integer \(at most 65536\), got 10+"):
        read_table(tmp_path / "t.npz")


def test_an_absurd_horizon_is_refused_from_the_header(arrays, tmp_path):
    arrays.pop("level_offsets")
    path = tmp_path / "t.npz"
    _write_zip(path, arrays, lambda zf: _zip_member(zf, "level_offsets.npy", (10**6,), "<i8", 8 * 10**6))
    with pytest.raises(TableError, match=r"key 'level_offsets' has 1000000 entries; at most 10002"):
        read_table(path)


# ------------------------------------------------------------------------ tables that load silently wrong

def _level(arrays, t: int) -> slice:
    lo = arrays["level_offsets"]
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


@pytest.mark.parametrize("mutate, match", [
    (_duplicate_cell, r"cells of level 2 must be distinct and in ascending order; row \d+ \[-?\d+\] repeats"),
    (_reverse_level, r"cells of level 3 must be distinct and in ascending order; row \d+ \[-?\d+\] comes before"),
    (_far_cell, r"the cells span a box of \d+ cells .*too large to pack into keys"),
    (_level0_off_origin, r"level 0 must be the single start cell \[0\]"),
    (_unknown_method, r"unknown method 'magic'; known: maxflow, coverage"),
], ids=["duplicate-cell", "reversed-rows", "cell-near-2^62", "level-0-off-origin", "unknown-method"])
def test_tables_that_would_load_silently_wrong(arrays, tmp_path, mutate, match):
    mutate(arrays)
    path = tmp_path / "bad.npz"
    write_npz(path, arrays)
    with pytest.raises(TableError, match=rf"bad.npz: {match}"):
        load_table(path)


# ----------------------------------------------------------------------------------- cross-checked checkpoints

def _walk_policy(hidden: int = 8) -> MLPPolicy:
    system = RandomWalk1D()
    config = MLPConfig(state_dim=1, num_actions=5, horizon=8, periodic=[False], feature_scale=[4.0], hidden=hidden,
                       layers=2)
    return MLPPolicy(config, system, system.action_set())


def _checkpoint() -> dict:
    return policy_checkpoint(_walk_policy(), system_to_json(RandomWalk1D(), 8))


def _state_actions(c):
    c["state_dict"]["actions"] = c["state_dict"]["actions"] * 10


def _state_scale(c):
    c["state_dict"]["inv_scale"] = c["state_dict"]["inv_scale"] * 100


def _config_horizon(c):
    c["config"]["horizon"] = 20


def _config_periodic(c):
    c["config"]["periodic"] = [True]


def _nan_weight(c):
    c["state_dict"]["net.0.weight"][0, 0] = math.nan


def _inf_scale(c):
    c["config"]["feature_scale"] = [math.inf]


def _huge_network(c):
    c["config"]["hidden"], c["config"]["layers"] = 1000, 30  # within MLPConfig's limits (tests/test_integrity.py)


@pytest.mark.parametrize("mutate, match", [
    (_state_actions, r"state_dict\['actions'\] does not match the actions of the system 'random_walk_1d'"),
    (_state_scale, r"state_dict\['inv_scale'\] does not match config.feature_scale"),
    (_config_horizon, r"config.horizon is 20 but the system JSON says 8"),
    (_config_periodic, r"config.periodic \[True\] does not match the system's \[False\]"),
    (_nan_weight, r"state_dict\['net.0.weight'\] holds non-finite"),
    (_inf_scale, r"config does not describe a policy \(MLPConfig: feature_scale must be positive finite"),
    (_huge_network, r"state_dict does not match the network of its config \(\d+ weights described, 141 held\)"),
], ids=["state-actions", "state-inv-scale", "config-horizon", "config-periodic", "nan-weight", "inf-scale",
        "huge-network"])
def test_checkpoints_that_would_load_silently_wrong(mutate, match, tmp_path):
    ckpt = _checkpoint()
    assert isinstance(load_policy(ckpt), MLPPolicy)
    mutate(ckpt)
    save_policy(tmp_path / "bad.pt", ckpt)
    with pytest.raises(PolicyCheckpointError, match=rf"bad.pt: {match}"):
        load_policy(tmp_path / "bad.pt")


def test_a_good_checkpoint_of_a_trusted_user_factory_loads(tmp_path):
    def make_walk(dt: float = 1.0, num_actions: int = 5, max_speed: float = 1.0, cell_size=(0.5,),
                  cell_offset=(0.0,)):
        return RandomWalk1D(dt=dt, num_actions=num_actions, max_speed=max_speed, cell_size=tuple(cell_size),
                            cell_offset=tuple(cell_offset))

    save_policy(tmp_path / "ok.pt", _checkpoint())
    _REGISTRY.pop("random_walk_1d")
    try:
        with pytest.raises(PolicyCheckpointError, match=r"unknown system 'random_walk_1d'"):
            load_policy(tmp_path / "ok.pt")
        policy = load_policy(tmp_path / "ok.pt", trust_factory=make_walk)
        assert policy.action_probs(torch.zeros(3, 1), 0).shape == (3, 5)
    finally:
        _REGISTRY["random_walk_1d"] = RandomWalk1D


def test_an_unsupported_compression_method_is_named(arrays, tmp_path):
    path = tmp_path / "t.npz"
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for key, value in arrays.items():
            with zf.open(zipfile.ZipInfo(f"{key}.npy"), "w") as fh:
                np.lib.format.write_array(fh, np.asarray(value), allow_pickle=False)
    with zipfile.ZipFile(path) as zf:  # rewrite one member with bzip2, which no table writer uses
        members = {i.filename: zf.read(i) for i in zf.infolist()}
    with zipfile.ZipFile(path, "w") as zf:
        for name, data in members.items():
            zf.writestr(name, data, compress_type=zipfile.ZIP_BZIP2 if name == "cells.npy" else zipfile.ZIP_DEFLATED)
    with pytest.raises(TableError, match=r"array 'cells' uses zip compression method 12; a table is stored or deflated"):
        read_table(path)
