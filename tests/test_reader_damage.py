"""Damaged inputs that the attack run (``python .ci/attack.py``) found escaping as tracebacks or passing silently,
each now one clear error of its family naming the file: a zip whose directory points at no local header, a sparse
tensor in a checkpoint, JSON nested deeper than the json module parses, a benchmark folder whose episodes.jsonl is
a folder or a symlink loop."""

from __future__ import annotations

import json

import pytest
import torch
from test_bench_records import bench_record, bench_settings

from cuniform_torch.common.npz import NpzError, member_headers, read_npz
from cuniform_torch.policies.checkpoint import PolicyCheckpointError, load_policy, policy_checkpoint, save_policy
from cuniform_torch.policies.mlp import MLPConfig, MLPPolicy
from cuniform_torch.systems import RandomWalk1D, system_to_json
from eval.navigate.store import EpisodeStore, StoreError
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
    _refused(store, r"episodes.jsonl: unreadable \(Is a directory\)")


@pytest.mark.parametrize("target", ["episodes.jsonl", "nowhere.jsonl"])
def test_records_behind_a_broken_symlink_are_not_an_empty_folder(tmp_path, target):
    """A symlink loop (or one to nothing) is not 'no records yet': what the episodes were is unknown."""
    store = _store(tmp_path)
    store.records_file.unlink()
    store.records_file.symlink_to(target)
    _refused(store, r"episodes.jsonl: unreadable")


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
