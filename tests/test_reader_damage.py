"""Damaged inputs that the attack run (``python .ci/attack.py``) found escaping as tracebacks or passing silently,
each now one clear error of its family naming the file: a zip whose directory points at no local header, a sparse
tensor in a checkpoint, JSON nested deeper than the json module parses, a benchmark folder whose episodes.jsonl is
a folder or a symlink loop; a system JSON naming a factory other than the registered one, or a dt its params do
not give; a map data set's patch origin or resolution that the farm did not write; a local map's resolution of
another dtype; a start-MLP's start beyond any robot's state; benchmark settings whose digests or gap widths are not
what the run writes. A cut-short last record is left out by the read-only readers with one line on stderr."""

from __future__ import annotations

import contextlib
import dataclasses
import json
import resource
from typing import ClassVar

import numpy as np
import pytest
import torch
from test_bench_records import bench_record, bench_settings
from test_map_files_strict import _plant, tiny  # noqa: F401 - tiny: the module's fixture, a farm's data set

from cuniform_torch.common.digest import DIGEST_KEY, content_digest
from cuniform_torch.common.fileio import write_npz
from cuniform_torch.common.npz import NpzError, member_headers, read_npz
from cuniform_torch.policies.checkpoint import PolicyCheckpointError, load_policy, policy_checkpoint, save_policy
from cuniform_torch.policies.mlp import MLPConfig, MLPPolicy
from cuniform_torch.policies.start_mlp import StartMLPPolicy, StartRegion
from cuniform_torch.policies.table_set import load_table_set
from cuniform_torch.systems import RandomWalk1D, register_system, system_from_json, system_to_json
from cuniform_torch.systems.registry import _REGISTRY
from cuniform_torch.tables.file import TableError, read_table, table_digests, write_table
from eval.navigate.records.store import EpisodeStore, StoreError
from precompute.levels.safe_map import LocalMap, MapError, read_map_file, write_map_file
from precompute.maps.dataset import MapDatasetError, read_map_dataset

DEEP = "[" * 100000 + "]" * 100000
"""valid JSON nested deeper than the json module's recursion allows (it raises RecursionError)"""


def _local_map(path):
    occ = torch.zeros(30, 40, dtype=torch.uint8).numpy()
    occ[10:14, 5:30] = 1
    write_map_file(path, LocalMap(occ, (-1.5, -2.0), 0.1))
    return path


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


def test_a_sparse_tensor_in_a_checkpoint_is_one_error(tmp_path):
    walk = RandomWalk1D()
    config = MLPConfig(state_dim=1, num_actions=5, horizon=8, periodic=[False], feature_scale=[4.0], hidden=8,
                       layers=2)
    save_policy(tmp_path / "p.pt", policy_checkpoint(MLPPolicy(config, walk, walk.action_set()),
                                                     system_to_json(walk, 8)))
    ckpt = torch.load(tmp_path / "p.pt", weights_only=True)
    ckpt["state_dict"]["net.0.weight"] = ckpt["state_dict"]["net.0.weight"].to_sparse()
    torch.save(ckpt, tmp_path / "bad.pt")
    with pytest.raises(PolicyCheckpointError, match=r"bad.pt: its content has no digest: tensor "
                                                    r"'state_dict/net.0.weight' is torch.sparse_coo"):
        load_policy(tmp_path / "bad.pt")


def test_a_dataset_json_nested_too_deeply_is_one_error(tmp_path):
    (tmp_path / "dataset.json").write_text(DEEP)
    with pytest.raises(MapDatasetError, match=r"dataset.json: not readable JSON \(RecursionError"):
        read_map_dataset(tmp_path)


def _store(tmp_path) -> EpisodeStore:
    store = EpisodeStore(tmp_path / "run")
    store.open(bench_settings())
    store.append(bench_record(0))
    return store


def _refused(store: EpisodeStore, match: str) -> None:
    for read in (store.check, store.load, lambda: store.open(bench_settings())):
        with pytest.raises(StoreError, match=match):
            read()


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


def test_a_table_set_index_nested_too_deeply_is_one_error(tmp_path):
    (tmp_path / "tables.json").write_text(DEEP)
    with pytest.raises(TableError, match=r"tables.json: not a readable table-set index \(JSON nested too deep"):
        load_table_set(tmp_path)


# ------------------------------------------------------------------------------------------- system JSON

@dataclasses.dataclass(frozen=True)
class DamageWalk(RandomWalk1D):
    """A user system (not built in): its JSON names its factory, this class."""

    name: ClassVar[str] = "damage_walk"


WALK_JSON = json.loads(system_to_json(RandomWalk1D(), 8))


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


# ------------------------------------------------------------------------------------------- map data set

def _system(**over):
    def meta(m):
        m["system"] = json.dumps({**json.loads(m["system"]), **over}, sort_keys=True)
    return meta


def _patch(**over):
    return lambda m: m["patch"].update(over)


@pytest.mark.parametrize("meta, match", [
    (_system(factory="evil:make"), r"names factory 'evil:make', but 'dubins' is a built-in system"),
    (_system(dt=1e38), r"dt does not match its params"),
    (_patch(resolution=1e38), r"patch origin \[-0.5, -0.5\] must be the centred origin .* = \[-1e\+39, -1e\+39\]"),
    (_patch(origin=[-1, -0.5]), r"patch origin \[-1, -0.5\] must be the centred origin"),
    (_patch(origin=[-0.5, 1e38]), r"patch origin \[-0.5, 1e\+38\] must be the centred origin"),
    (_patch(resolution=0.1, origin=[-1.0, -1.0]), None),  # consistent: the reach and inflation checks' to refuse
    (lambda m: m["grid"]["periodic"].__setitem__(0, 0), r"grid .* does not match the system's"),  # 0 for false
    (lambda m: m["shards"][0].update(entries=10**30), r"4 entries, but the shards hold 10000000000000000000000000000"
                                                       r"02"),  # refused before a list of 10^30 pairs is made
])
def test_a_dataset_json_the_farm_did_not_write_is_refused(tiny, tmp_path, meta, match):  # noqa: F811
    m = json.loads((tiny / "dataset.json").read_text())
    assert m["patch"]["origin"] == [-0.5, -0.5] and m["patch"]["shape"] == [20, 20]  # what the patterns assume
    folder = _plant(tiny, tmp_path, meta=meta)
    if match is None:
        read_map_dataset(folder)  # the metadata alone is consistent
        return
    with _memory_capped(1 << 30), pytest.raises(MapDatasetError, match=rf"dataset.json: .*{match}"):
        read_map_dataset(folder)


@contextlib.contextmanager
def _memory_capped(extra: int):
    """The address space capped at what the process maps now + ``extra`` bytes (a reader that allocates what a
    forged count asks for fails with MemoryError here, not by taking the machine's memory)."""
    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    with open("/proc/self/status") as f:
        size = next(int(line.split()[1]) * 1024 for line in f if line.startswith("VmSize:"))
    cap = size + extra if hard == resource.RLIM_INFINITY else min(hard, size + extra)
    resource.setrlimit(resource.RLIMIT_AS, (cap, hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_AS, (soft, hard))


# ------------------------------------------------------------------------------------------- local map

def test_a_local_maps_resolution_of_another_dtype_is_refused(tmp_path):
    """float32 0.1 is 0.10000000149...: another map, though its digest is fresh."""
    arrays = {"format": np.array("cuniform-local-map/1"), "occupied": np.zeros((4, 4), np.uint8),
              "origin": np.zeros(2), "resolution": np.array(0.1, dtype=np.float32)}
    write_npz(tmp_path / "m.npz", {**arrays, DIGEST_KEY: np.array(content_digest(arrays))})
    with pytest.raises(MapError, match=r"m.npz: 'resolution' must be float64, got float32"):
        read_map_file(tmp_path / "m.npz")
    arrays["resolution"] = np.array(0.1)
    write_npz(tmp_path / "m.npz", {**arrays, DIGEST_KEY: np.array(content_digest(arrays))})
    assert read_map_file(tmp_path / "m.npz").resolution == 0.1


# ------------------------------------------------------------------------------------------- start-MLP

@pytest.mark.parametrize("value, ok", [(1e38, False), (-2e6, False), (1e6, True)])
def test_a_start_beyond_any_robots_state_is_refused(tmp_path, value, ok):
    walk = RandomWalk1D()
    config = MLPConfig(state_dim=1, num_actions=5, horizon=8, periodic=[False], feature_scale=[4.0], hidden=8,
                       layers=2, start_dims=[0])
    region = StartRegion(torch.tensor([[-1.0], [0.0], [1.0]], dtype=torch.float64), [0])
    ckpt = policy_checkpoint(StartMLPPolicy(config, walk, walk.action_set(), region), system_to_json(walk, 8))
    ckpt["start_region"]["starts"][0, 0] = value
    save_policy(tmp_path / "p.pt", ckpt)  # a fresh digest
    if ok:
        assert float(load_policy(tmp_path / "p.pt").region.starts[0, 0]) == value
        return
    with pytest.raises(PolicyCheckpointError, match=r"p.pt: start_region starts hold a value of magnitude .*, beyond "
                                                    r"the bound 1e\+06"):
        load_policy(tmp_path / "p.pt")


# ------------------------------------------------------------------------------------------- benchmark folder

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
