"""Policy files: MLP, start-MLP and map-policy checkpoints (``.pt``) and the shipped policy cards.

A damaged checkpoint (a sparse tensor, a flipped byte or bit, an edited value with the old digest, weights beyond the
bound, a config larger than any network) is one clear error naming the file; a checkpoint runs no code it names; a
card edited to another robot (``CARD_EDITS`` of tests/cases.py, which .ci/attack.py also runs), or weights larger
than the card says, are refused before the weights are read."""

from __future__ import annotations

import hashlib
import json
import math
import re
import shutil
import time
from pathlib import Path

import pytest
import torch
from cases import CARD_EDITS, edit_card
from hardening_helpers import _flip_byte, _mlp, _notes

import cuniform_torch.maps.pretrained as pretrained
from cuniform_torch import load_policy, make_system
from cuniform_torch.common.digest import DIGEST_KEY
from cuniform_torch.maps import MapPolicy, load_map_policy
from cuniform_torch.maps.checkpoint import MapCheckpointError, map_policy_checkpoint, save_map_policy
from cuniform_torch.maps.encoder import PatchSpec
from cuniform_torch.maps.policy import MAX_MAP_PARAMETERS, MapPolicyConfig
from cuniform_torch.maps.pretrained import PretrainedError
from cuniform_torch.policies import MLPConfig, MLPPolicy, PolicyCheckpointError
from cuniform_torch.policies.checkpoint import MAX_ABS_WEIGHT, policy_checkpoint, save_policy
from cuniform_torch.policies.mlp import MAX_WEIGHTS
from cuniform_torch.policies.start_mlp import StartMLPPolicy, StartRegion
from cuniform_torch.systems import _REGISTRY, RandomWalk1D, system_to_json

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




def _never_built(monkeypatch, cls) -> None:
    def refuse(*args, **kwargs):
        raise AssertionError(f"{cls.__name__} was built: the config was not refused before allocation")
    monkeypatch.setattr(cls, "__init__", refuse)






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
    c["config"]["hidden"], c["config"]["layers"] = 1000, 30  # within MLPConfig's limits (test_an_oversized_mlp_config_is_refused_before_allocation)


SHIPPED = "unicycle-0.5"


@pytest.fixture
def shelf(tmp_path, monkeypatch):
    """A copy of the shipped weights folder (its card and file), which the loaders then read."""
    folder = tmp_path / "weights"
    folder.mkdir()
    for path in pretrained.PRETRAINED_DIR.glob(f"{SHIPPED}*"):
        shutil.copy(path, folder / path.name)
    monkeypatch.setattr(pretrained, "PRETRAINED_DIR", folder)
    return folder


def _edit_card(folder, **robot) -> None:
    edit_card(folder / f"{SHIPPED}.json", **robot)




# ------------------------------------------------------------------------------------------------- damaged checkpoints

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


# ----------------------------------------------------------------------------------------------------------- start-MLP

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


# ---------------------------------------------------------------------------- digests, weight bounds and config limits

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


# --------------------------------------------------------------------------------------------------- no code from data

def test_a_checkpoint_naming_a_factory_runs_nothing(tmp_path, evil):
    name, markers = evil
    policy = _walk_policy()
    ckpt = policy_checkpoint(policy, json.dumps({"name": "evil_car", "params": {}, "dt": 1.0, "horizon": 8,
                                                 "factory": f"{name}:Car"}))
    save_policy(tmp_path / "evil.pt", ckpt)
    with pytest.raises(PolicyCheckpointError, match=r"unknown system 'evil_car'"):
        load_policy(tmp_path / "evil.pt")
    assert not markers["import"].exists() and not markers["call"].exists()


# ------------------------------------------------------------------------------------------- cross-checked checkpoints

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


# --------------------------------------------------------------------------------------------- the shipped policy card

def test_the_shipped_card_and_file_agree_and_load(shelf):
    assert isinstance(load_map_policy(SHIPPED), MapPolicy)


@pytest.mark.parametrize("edit, said", CARD_EDITS)
def test_a_card_edited_to_another_robot_is_refused(shelf, edit, said):
    _edit_card(shelf, **edit)
    with pytest.raises(PretrainedError, match=f"does not describe the robot .*{said}"):
        load_map_policy(SHIPPED)


def test_weights_of_another_robot_under_an_updated_digest_are_refused(shelf):
    import torch

    from cuniform_torch.maps.checkpoint import save_map_policy

    weights = shelf / f"{SHIPPED}.map_policy.pt"
    ckpt = torch.load(weights, weights_only=True)
    system = json.loads(ckpt["system"])
    system["params"]["speed"] = 0.7  # another robot's file (still self-consistent: its digest is rewritten)
    ckpt["system"] = json.dumps(system, sort_keys=True)
    ckpt.pop("content_sha256")
    save_map_policy(weights, ckpt)
    card_path = shelf / f"{SHIPPED}.json"
    card = json.loads(card_path.read_text())
    raw = weights.read_bytes()
    card.update(file_sha256=hashlib.sha256(raw).hexdigest(), bytes=len(raw))
    card_path.write_text(json.dumps(card))
    with pytest.raises(PretrainedError, match="speed: card 0.5, file 0.7"):
        load_map_policy(SHIPPED)


def test_a_weights_file_larger_than_its_card_is_refused_before_it_is_read(shelf):
    weights = shelf / f"{SHIPPED}.map_policy.pt"
    with open(weights, "r+b") as fh:  # sparse: 2 GB claimed, nothing stored
        fh.truncate(2 << 30)
    begin = time.perf_counter()
    with pytest.raises(PretrainedError, match=r"2147483648 bytes, the card says \d+"):
        load_map_policy(SHIPPED)
    assert time.perf_counter() - begin < 5.0  # from its size: not hashed, not loaded


@pytest.mark.parametrize("load, error", [(load_map_policy, MapCheckpointError), (load_policy, PolicyCheckpointError)])
def test_a_checkpoint_over_any_networks_size_is_refused_from_its_size(tmp_path, load, error):
    path = tmp_path / "huge.pt"
    with open(path, "wb") as fh:
        fh.truncate(2 << 30)
    begin = time.perf_counter()
    with pytest.raises(error, match="2147483648 bytes, over the"):
        load(path)
    assert time.perf_counter() - begin < 5.0


# --------------------------------------------------------------------------------------------------- the MLP's support

def test_mlp_checkpoint_with_a_bad_support_is_refused(walk_table):
    system = walk_table.make_system()
    ckpt = policy_checkpoint(_mlp(walk_table, support=True), system_to_json(system, walk_table.horizon))
    ckpt["support"] = dict(ckpt["support"], level_offsets=ckpt["support"]["level_offsets"][:-1])
    with pytest.raises(PolicyCheckpointError, match="support level_offsets must be an int64"):
        load_policy(ckpt)
