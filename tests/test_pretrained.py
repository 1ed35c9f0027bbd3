"""Shipped map policies: loaded by name only when the file matches its model card; a policy of another robot is
refused by the benchmark and by CFU-MPPI, naming what differs; with none given, the benchmark picks the shipped
policy of its robot."""

from __future__ import annotations

import hashlib
import json
from dataclasses import replace

import pytest
import torch

import cuniform_torch.maps.pretrained as pretrained
from cuniform_torch.controllers.cfu import CFUMPPI
from cuniform_torch.envs import OccupancyGrid
from cuniform_torch.maps import MapPolicy, MapPolicyConfig, load_map_policy, map_policy_checkpoint, save_map_policy
from cuniform_torch.maps.pretrained import CARD_FORMAT, PretrainedError, pretrained_path
from cuniform_torch.systems import system_to_json
from eval.navigate.run import map_policy_for
from precompute.worlds.robot import NAV_ROBOT, preset_dict

SHIPPED = "unicycle-0.5"


def _policy_file(path, robot=NAV_ROBOT, metrics=None):
    system = robot.make_system()
    config = MapPolicyConfig(state_dim=3, num_actions=7, horizon=robot.horizon, periodic=[False, False, True],
                             feature_scale=[1.0, 1.0, 1.0],
                             patch={"shape": [24, 24], "resolution": 0.1, "origin": [-1.2, -1.2]},
                             hidden=16, layers=1, embed=8, channels=4)
    policy = MapPolicy(config, system, system.action_set(dtype=torch.float32))
    save_map_policy(path, map_policy_checkpoint(policy, system_to_json(system, robot.horizon), metrics=metrics))
    return path


@pytest.fixture
def shelf(tmp_path, monkeypatch):
    """A weights folder holding one policy ``toy-1`` (trained, as the card says, for the benchmark robot)."""
    folder = tmp_path / "weights"
    folder.mkdir()
    _policy_file(folder / "toy-1.map_policy.pt")
    raw = (folder / "toy-1.map_policy.pt").read_bytes()
    card = {"format": CARD_FORMAT, "name": "toy-1", "file": "toy-1.map_policy.pt",
            "file_sha256": hashlib.sha256(raw).hexdigest(), "robot": preset_dict(NAV_ROBOT)}
    (folder / "toy-1.json").write_text(json.dumps(card))
    monkeypatch.setattr(pretrained, "PRETRAINED_DIR", folder)
    return folder


def test_a_shipped_policy_loads_by_name_and_a_changed_file_is_refused(shelf):
    assert pretrained.pretrained_names() == ["toy-1"]
    policy = load_map_policy("toy-1")
    assert isinstance(policy, MapPolicy) and policy.horizon == NAV_ROBOT.horizon
    raw = bytearray((shelf / "toy-1.map_policy.pt").read_bytes())
    raw[len(raw) // 2] ^= 0x01
    (shelf / "toy-1.map_policy.pt").write_bytes(bytes(raw))
    with pytest.raises(PretrainedError, match="does not match its model card"):
        load_map_policy("toy-1")
    with pytest.raises(PretrainedError, match="no pretrained map policy named 'nope'.*toy-1"):
        pretrained_path("nope")


def test_the_benchmark_picks_the_shipped_policy_of_its_robot_and_refuses_another_robots(shelf, tmp_path):
    assert map_policy_for(NAV_ROBOT, None) == shelf / "toy-1.map_policy.pt"
    assert map_policy_for(NAV_ROBOT, "toy-1") == shelf / "toy-1.map_policy.pt"
    faster = replace(NAV_ROBOT, params={**NAV_ROBOT.params, "speed": 1.0})
    with pytest.raises(ValueError, match="'toy-1' was trained for another robot.*speed: trained 0.5, given 1.0"):
        map_policy_for(faster, None)
    with pytest.raises(ValueError, match="radius: trained 0.2, given 0.3"):
        map_policy_for(replace(NAV_ROBOT, radius=0.3), None)
    with pytest.raises(ValueError, match="radius: trained 0.2, given 0.3"):
        map_policy_for(replace(NAV_ROBOT, radius=0.3), "toy-1")
    with pytest.raises(ValueError, match="max_omega: trained 1.5, given 1.0"):
        map_policy_for(replace(NAV_ROBOT, params={**NAV_ROBOT.params, "max_omega": 1.0}), "toy-1")
    other = _policy_file(tmp_path / "other.pt", replace(NAV_ROBOT, horizon=6), metrics={"robot_radius": 0.25})
    with pytest.raises(ValueError, match="horizon: trained 6, given 15"):
        map_policy_for(NAV_ROBOT, other)
    with pytest.raises(ValueError, match="radius: trained 0.25, given 0.2"):
        map_policy_for(replace(NAV_ROBOT, horizon=6), other)


def test_cfu_mppi_refuses_a_policy_of_another_system(shelf):
    world = OccupancyGrid(torch.zeros(50, 50, dtype=torch.bool), (-2.5, -2.5), 0.1)
    cost = lambda states, actions: states[..., 0].sum(-1)  # noqa: E731
    CFUMPPI("toy-1", world, cost, num_samples=16, system=NAV_ROBOT.make_system())  # its own robot: fine
    slower = replace(NAV_ROBOT, params={**NAV_ROBOT.params, "speed": 0.3, "num_actions": 5}).make_system()
    with pytest.raises(ValueError, match="num_actions: trained 7, given 5; speed: trained 0.5, given 0.3"):
        CFUMPPI("toy-1", world, cost, num_samples=16, system=slower)



def test_the_shipped_policy_matches_its_card_and_its_robot():
    """The file in the package: its card is readable, its sha256 is the card's, it is small, it was trained for the
    benchmark robot, and it loads (weights only) into a CFU-MPPI that commands that robot."""
    card = pretrained.pretrained_card(SHIPPED)
    path = pretrained_path(SHIPPED)
    raw = path.read_bytes()
    assert hashlib.sha256(raw).hexdigest() == card["file_sha256"] and len(raw) == card["bytes"] < 1 << 20
    assert card["robot"] == json.loads(json.dumps(preset_dict(NAV_ROBOT)))
    assert {d["suite"] for d in card["data"]} == {"barn", "forest", "clutter"}
    assert all(d["split"] == "train" for d in card["data"])
    policy = load_map_policy(SHIPPED)
    system = NAV_ROBOT.make_system()
    assert policy.horizon == NAV_ROBOT.horizon and policy.system == system
    world = OccupancyGrid(torch.zeros(100, 100, dtype=torch.bool), (-2.5, -2.5), 0.05)
    controller = CFUMPPI(policy, world, lambda s, a: s[:, 1:, 0].neg().sum(dim=1), num_samples=16, seed=0,
                         system=system)
    assert bool(torch.isfinite(controller.command(torch.zeros(3))).all())
