"""Nothing silently wrong: content digests, weight bounds, config limits and the table cross-checks.

Each family (table, MLP policy, start-conditioned MLP, map policy) is written by its writer, then one value of the
stored data is changed with the old digest kept (what a flipped bit on disk does): the reader refuses it by
naming the file. A file without a digest (an older writer) still loads, after a one-line note.
"""

from __future__ import annotations

import math
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from test_trust import written_arrays

from cuniform_torch.common.digest import DIGEST_KEY
from cuniform_torch.common.fileio import write_npz
from cuniform_torch.maps.checkpoint import MapCheckpointError, load_map_policy, map_policy_checkpoint, save_map_policy
from cuniform_torch.maps.encoder import PatchSpec
from cuniform_torch.maps.policy import MAX_MAP_PARAMETERS, MapPolicy, MapPolicyConfig
from cuniform_torch.policies.checkpoint import (
    MAX_ABS_WEIGHT,
    PolicyCheckpointError,
    load_policy,
    policy_checkpoint,
    save_policy,
)
from cuniform_torch.policies.mlp import MAX_WEIGHTS, MLPConfig, MLPPolicy
from cuniform_torch.policies.start_mlp import StartMLPPolicy, StartRegion
from cuniform_torch.systems import RandomWalk1D, make_system, system_to_json
from cuniform_torch.tables.file import NOGRAPH_DIGEST_KEY, TableError, read_table, table_digests, write_table
from precompute.coverage.method import CoverageConfig, build_coverage_table
from precompute.flow.builder import BuildConfig, build_table
from precompute.levels.safe_map import LocalMap

GRAPH_KEYS = ("arc_offsets", "arcs", "arc_flow", "transition_offsets", "transitions", "transition_frac")


def _flip_byte(value: np.ndarray) -> np.ndarray:
    """A copy of ``value`` with one bit of one byte in the middle of its data flipped."""
    out = np.array(value, copy=True)
    raw = out.reshape(-1).view(np.uint8)
    raw[len(raw) // 2] ^= 0x10
    return out


def _notes(err: str, path: Path) -> list[str]:
    return [line for line in err.splitlines() if line.startswith(f"note: {path} has no content digest")]


# ------------------------------------------------------------------------------------------------------ tables

@pytest.fixture(scope="module")
def table():
    """A small Dubins max-flow table (levels 1, 5, 13), with its flow graph."""
    return build_table(make_system("dubins"), BuildConfig(horizon=2))[0]


@pytest.fixture(scope="module")
def table_arrays(table, tmp_path_factory) -> dict[str, np.ndarray]:
    return written_arrays(table, tmp_path_factory.mktemp("t") / "good.npz")


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


def _rewritten(arrays: dict[str, np.ndarray], path: Path) -> Path:
    """``arrays`` written with fresh digests: a well-formed file whose content is inconsistent."""
    arrays = {k: v for k, v in arrays.items() if k not in (DIGEST_KEY, NOGRAPH_DIGEST_KEY)}
    write_npz(path, {**arrays, **table_digests(arrays)})
    return path


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


# ----------------------------------------------------------------------------------------------- checkpoints

WALK = RandomWalk1D()
SYSTEM = make_system("dubins", speed=1.0, dt=0.2, num_actions=5, max_omega=math.pi / 2,
                     cell_size=[0.1, 0.1, 2 * math.pi / 16])
SPEC = PatchSpec((24, 24), 0.1, (-1.2, -1.2))


def _mlp_config(**over) -> MLPConfig:
    return MLPConfig(**{"state_dim": 1, "num_actions": 5, "horizon": 8, "periodic": [False], "feature_scale": [4.0],
                        "hidden": 8, "layers": 2, **over})


def _mlp_ckpt() -> dict:
    torch.manual_seed(0)
    return policy_checkpoint(MLPPolicy(_mlp_config(), WALK, WALK.action_set()), system_to_json(WALK, 8))


def _start_ckpt() -> dict:
    torch.manual_seed(0)
    region = StartRegion(torch.tensor([[-1.0], [0.0], [1.0]], dtype=torch.float64), [0])
    policy = StartMLPPolicy(_mlp_config(start_dims=[0]), WALK, WALK.action_set(), region)
    return policy_checkpoint(policy, system_to_json(WALK, 8))


def _map_config(**over) -> MapPolicyConfig:
    return MapPolicyConfig(**{"state_dim": 3, "num_actions": 5, "horizon": 4, "periodic": [False, False, True],
                              "feature_scale": [0.8, 0.6, 1.0], "patch": SPEC.to_dict(), "hidden": 16, "layers": 2,
                              "embed": 8, "channels": 4, **over})


def _map_ckpt() -> dict:
    torch.manual_seed(0)
    return map_policy_checkpoint(MapPolicy(_map_config(), SYSTEM, SYSTEM.action_set()), system_to_json(SYSTEM, 4))


# family: (checkpoint maker, saver, loader, error class, a tensor's key path to damage)
FAMILIES = {
    "mlp": (_mlp_ckpt, save_policy, load_policy, PolicyCheckpointError, ("state_dict", "net.0.weight")),
    "start_mlp": (_start_ckpt, save_policy, load_policy, PolicyCheckpointError, ("start_region", "starts")),
    "map": (_map_ckpt, save_map_policy, load_map_policy, MapCheckpointError, ("state_dict", "encoder.out.weight")),
}


def _saved(family: str, path: Path) -> Path:
    make, save = FAMILIES[family][:2]
    save(path, make())
    return path


def _damaged(loaded: dict, key_path: tuple[str, ...]) -> dict:
    """``loaded`` with one bit of the tensor at ``key_path`` flipped, the old digest kept."""
    parent = loaded
    for key in key_path[:-1]:
        parent = parent[key]
    parent[key_path[-1]] = torch.from_numpy(_flip_byte(parent[key_path[-1]].numpy()))
    return loaded


@pytest.mark.parametrize("family", FAMILIES)
def test_a_checkpoint_round_trips_with_its_digest_and_no_note(family, tmp_path, capsys):
    path = _saved(family, tmp_path / "p.pt")
    assert len(torch.load(path, weights_only=True)[DIGEST_KEY]) == 64
    FAMILIES[family][2](path)
    assert capsys.readouterr().err == ""


@pytest.mark.parametrize("family", FAMILIES)
def test_a_flipped_byte_in_a_checkpoint_tensor_is_refused_naming_the_file(family, tmp_path):
    _, _, load, error, key_path = FAMILIES[family]
    loaded = torch.load(_saved(family, tmp_path / "p.pt"), weights_only=True)
    path = tmp_path / "bad.pt"
    torch.save(_damaged(loaded, key_path), path)
    with pytest.raises(error, match=rf"^{path} is damaged: its content does not match the digest"):
        load(path)


@pytest.mark.parametrize("family", FAMILIES)
def test_an_edited_plain_value_is_refused_too(family, tmp_path):
    """The digest covers the non-tensor values (here a metric) as well."""
    _, _, load, error, _ = FAMILIES[family]
    loaded = torch.load(_saved(family, tmp_path / "p.pt"), weights_only=True)
    loaded["metrics"] = {"kl": 0.5}
    path = tmp_path / "bad.pt"
    torch.save(loaded, path)
    with pytest.raises(error, match="is damaged"):
        load(path)


@pytest.mark.parametrize("family", FAMILIES)
def test_a_flipped_bit_in_the_file_is_one_clear_error(family, tmp_path):
    """A bit flipped in the file's bytes (inside the stored tensor data): refused, naming the file, whether
    torch's zip reader or the digest notices first (torch 2.x does not check the zip's CRC: the digest does)."""
    _, _, load, error, key_path = FAMILIES[family]
    path = _saved(family, tmp_path / "p.pt")
    tensor = torch.load(path, weights_only=True)
    for key in key_path:
        tensor = tensor[key]
    data, raw = tensor.numpy().tobytes(), bytearray(path.read_bytes())
    at = raw.find(data)
    assert at > 0 and raw.find(data, at + 1) < 0
    raw[at + len(data) // 2] ^= 0x10
    path.write_bytes(bytes(raw))
    with pytest.raises(error, match=rf"^{path}"):
        load(path)


@pytest.mark.parametrize("family", FAMILIES)
def test_a_checkpoint_without_a_digest_loads_after_one_note(family, tmp_path, capsys):
    make, _, load, _, _ = FAMILIES[family]
    path = tmp_path / "old.pt"
    torch.save(make(), path)  # as the writers before digests did
    capsys.readouterr()
    load(path)
    load(path)
    assert len(_notes(capsys.readouterr().err, path)) == 1


@pytest.mark.parametrize("family", FAMILIES)
@pytest.mark.parametrize("value", [1e38, -2 * MAX_ABS_WEIGHT])
def test_huge_weights_are_refused(family, value, tmp_path):
    make, save, load, error, _ = FAMILIES[family]
    ckpt = make()
    name = "net.0.weight" if family != "map" else "body.1.weight"
    ckpt["state_dict"][name] = ckpt["state_dict"][name].clone()
    ckpt["state_dict"][name][0, 0] = value
    path = tmp_path / "huge.pt"
    save(path, ckpt)  # a fresh digest: the file is intact, its content insane
    with pytest.raises(error, match=rf"{path}: state_dict\['{name}'\] holds a value of magnitude "
                                    rf"{re.escape(f'{abs(value):.3g}')}, beyond the bound 1e\+06"):
        load(path)


def test_weights_at_the_bound_load():
    ckpt = _mlp_ckpt()
    ckpt["state_dict"]["net.0.weight"][0, 0] = -MAX_ABS_WEIGHT
    load_policy(ckpt)


def _never_built(monkeypatch, cls) -> None:
    def refuse(*args, **kwargs):
        raise AssertionError(f"{cls.__name__} was built: the config was not refused before allocation")
    monkeypatch.setattr(cls, "__init__", refuse)


@pytest.mark.parametrize("over, words", [
    ({"hidden": 16384, "layers": 16}, "at most 32 layers of 8192 units"),
    ({"hidden": 8192, "layers": 32}, f"weights; at most {MAX_WEIGHTS}"),
    ({"hidden": 4096, "layers": 8}, f"weights; at most {MAX_WEIGHTS}"),
    ({"num_actions": 1 << 20}, "num_actions is 1048576; at most 65536"),
])
def test_an_oversized_mlp_config_is_refused_before_allocation(over, words, tmp_path, monkeypatch):
    ckpt = _mlp_ckpt()
    ckpt["config"] = {**ckpt["config"], **over}
    path = tmp_path / "big.pt"
    save_policy(path, ckpt)
    _never_built(monkeypatch, MLPPolicy)
    with pytest.raises(PolicyCheckpointError, match=rf"{path}: config does not describe a policy \(.*{words}"):
        load_policy(path)
    with pytest.raises(ValueError, match=words):
        _mlp_config(**over)


@pytest.mark.parametrize("over, words", [
    ({"hidden": 16384, "layers": 16}, "at most 16 layers, 4096 hidden units"),
    ({"hidden": 4096, "layers": 16}, f"parameters; at most {MAX_MAP_PARAMETERS}"),
    ({"channels": 200, "embed": 32, "patch": PatchSpec((1024, 1024), 0.01, (-5.0, -5.0)).to_dict()},
     f"parameters; at most {MAX_MAP_PARAMETERS}"),
    ({"local_features": 128, "patch": PatchSpec((1024, 1024), 0.01, (-5.0, -5.0)).to_dict()},
     r"feature maps of 134217728 values per map; at most 67108864"),
    ({"local_features": 512}, "local_features must be an integer in 0..256"),
])
def test_an_oversized_map_config_is_refused_before_allocation(over, words, tmp_path, monkeypatch):
    ckpt = _map_ckpt()
    ckpt["config"] = {**ckpt["config"], **over}
    path = tmp_path / "big.pt"
    save_map_policy(path, ckpt)
    _never_built(monkeypatch, MapPolicy)
    with pytest.raises(MapCheckpointError, match=rf"{path}: config does not describe a map policy \(.*{words}"):
        load_map_policy(path)


@pytest.mark.parametrize("over", [{}, {"local_features": 3, "layers": 3}, {"patch": PatchSpec((17, 30), 0.1, (
        -1.0, -1.0)).to_dict(), "channels": 2, "embed": 5, "hidden": 7, "layers": 1}])
def test_the_map_configs_parameter_count_is_the_networks(over):
    """num_parameters (the bound's count, computed without building) equals the built network's."""
    config = _map_config(**over)
    assert config.num_parameters == MapPolicy(config, SYSTEM, SYSTEM.action_set()).num_parameters
    mlp = _mlp_config(start_dims=[0])
    assert mlp.num_weights == sum(p.numel() for p in StartMLPPolicy(
        mlp, WALK, WALK.action_set(), StartRegion(torch.zeros(1, 1, dtype=torch.float64), [0])).net.parameters())
