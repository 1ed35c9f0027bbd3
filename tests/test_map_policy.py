"""The map-conditioned policy at run time: checkpoint, patch checks, one encoding per command, sensing, CFU-MPPI.

Untrained networks on a Dubins car of 4 steps and 24 x 24 patches of 0.1 m (the training is tested in
tests/test_distill_maps.py).
"""

from __future__ import annotations

import io
import math

import pytest
import torch

from cuniform_torch.controllers.cfu import CFUMPPI
from cuniform_torch.envs import OccupancyGrid
from cuniform_torch.maps.checkpoint import MapCheckpointError, load_map_policy, map_policy_checkpoint, save_map_policy
from cuniform_torch.maps.encoder import PatchSpec
from cuniform_torch.maps.policy import MapPolicy, MapPolicyConfig
from cuniform_torch.maps.sensing import local_map, sense_patch
from cuniform_torch.sampling.rollout import rollout
from cuniform_torch.systems import make_system, system_to_json

T = 4
SYSTEM = make_system("dubins", speed=1.0, dt=0.2, num_actions=5, max_omega=math.pi / 2,
                     cell_size=[0.1, 0.1, 2 * math.pi / 16])
SPEC = PatchSpec((24, 24), 0.1, (-1.2, -1.2))


def _policy(seed: int = 0, device: str = "cpu") -> MapPolicy:
    torch.manual_seed(seed)
    config = MapPolicyConfig(state_dim=3, num_actions=5, horizon=T, periodic=[False, False, True],
                             feature_scale=[0.8, 0.6, 1.0], patch=SPEC.to_dict(), hidden=32, layers=2, embed=8,
                             channels=4)
    return MapPolicy(config, SYSTEM, SYSTEM.action_set()).to(device).eval()


def _patch(occupied: torch.Tensor | None = None, spec: PatchSpec = SPEC) -> OccupancyGrid:
    occ = torch.zeros(spec.shape, dtype=torch.bool) if occupied is None else occupied
    return OccupancyGrid(occ, spec.origin, spec.resolution)


def _wall() -> torch.Tensor:
    occ = torch.zeros(SPEC.shape, dtype=torch.bool)
    occ[10:14, 18:20] = True
    return occ


def test_checkpoint_round_trip_weights_only(tmp_path):
    policy = _policy()
    path = tmp_path / "p.pt"
    save_map_policy(path, map_policy_checkpoint(policy, system_to_json(SYSTEM, T), {"map_0": "x"}, {"epochs": 3}))
    back = load_map_policy(path)
    x = torch.randn(16, 3) * 0.3
    for p in (policy, back):
        p.set_map(_patch(_wall()))
    assert torch.equal(policy.action_probs(x, 2), back.action_probs(x, 2))
    assert back.patch_spec == SPEC
    torch.load(path, weights_only=True)  # plain types and tensors only


def _broken(key: str):
    def edit(ckpt: dict) -> None:
        sd = ckpt["state_dict"]
        if key == "format":
            ckpt["format"] = "cuniform-policy/1"
        elif key == "missing":
            del ckpt["metrics"]
        elif key == "unknown":
            ckpt["extra"] = 1
        elif key == "nan":
            sd["inp_x.weight"] = sd["inp_x.weight"].clone().fill_(math.nan)
        elif key == "shape":
            sd["inp_e.weight"] = torch.zeros(3, 3)
        elif key == "missing_weight":
            del sd["encoder.out.bias"]
        elif key == "inv_scale":
            sd["inv_scale"] = sd["inv_scale"] * 2
        elif key == "actions":
            ckpt["actions"] = ckpt["actions"] * 2
        elif key == "patch":
            ckpt["config"]["patch"] = {"shape": [0, 24], "resolution": 0.1, "origin": [0, 0]}
        elif key == "horizon":
            ckpt["config"]["horizon"] = T + 1
        elif key == "metrics":
            ckpt["metrics"] = {"loss": math.inf}
        elif key == "system":
            ckpt["system"] = ckpt["system"].replace("dubins", "nonesuch")
    return edit


@pytest.mark.parametrize("key, message", [
    ("format", "unknown format"), ("missing", "missing key"), ("unknown", "unknown key"), ("nan", "non-finite"),
    ("shape", "does not match the network"), ("missing_weight", "does not match the network"),
    ("inv_scale", "inv_scale"), ("actions", "actions"), ("patch", "patch shape"), ("horizon", "horizon"),
    ("metrics", "metrics"), ("system", "system cannot be rebuilt"),
])
def test_broken_checkpoints_are_refused_by_name(key, message):
    ckpt = map_policy_checkpoint(_policy(), system_to_json(SYSTEM, T))
    buf = io.BytesIO()
    torch.save(ckpt, buf)
    ckpt = torch.load(io.BytesIO(buf.getvalue()), weights_only=True)  # a fresh copy to break
    _broken(key)(ckpt)
    with pytest.raises(MapCheckpointError, match=message):
        load_map_policy(ckpt)


def test_a_file_needing_unpickling_is_refused(tmp_path):
    path = tmp_path / "evil.pt"
    torch.save({"format": "cuniform-map-policy/1", "obj": PatchSpec((2, 2), 1.0, (0, 0))}, path)
    with pytest.raises(MapCheckpointError, match="not a readable map-policy checkpoint"):
        load_map_policy(path)


@pytest.mark.parametrize("patch, message", [
    (_patch(spec=PatchSpec((20, 24), 0.1, (-1.2, -1.2))), r"\[20, 24\] cells .* \[24, 24\]"),
    (_patch(spec=PatchSpec((24, 24), 0.05, (-1.2, -1.2))), "resolution 0.05 m .* 0.1 m"),
    (_patch(spec=PatchSpec((24, 24), 0.1, (0.0, -1.2))), "origin"),
    (torch.zeros(24, 24), "must be an OccupancyGrid"),
])
def test_a_patch_of_another_spec_is_one_clear_error(patch, message):
    with pytest.raises(ValueError, match=message):
        _policy().set_map(patch)


def test_lookups_need_a_map_and_match_the_training_path():
    policy = _policy()
    x = torch.randn(32, 3) * 0.15  # inside the box: no fallback rows
    with pytest.raises(ValueError, match="no map set"):
        policy.action_probs(x, 0)
    policy.set_map(_patch(_wall()))
    with torch.no_grad():  # the folded first layer (W_e e + b computed once) equals the training path
        ref = torch.softmax(policy.logits(x, 3, policy.encode(_wall().unsqueeze(0))), dim=1)
    assert torch.allclose(policy.action_probs(x, 3), ref, atol=1e-6)
    other = _policy()
    other.load_state_dict(policy.state_dict())
    other.set_map(_patch())
    assert float((other.action_probs(x, 3) - ref).abs().max()) > 1e-5  # an empty map answers otherwise


def test_draws_follow_the_probabilities():
    policy = _policy(seed=3)
    policy.set_map(_patch(_wall()))
    x = torch.tensor([[0.2, -0.1, 0.4]]).expand(40000, 3)
    probs = policy.action_probs(x[:1], 2)[0]  # [A]
    drawn = policy.sample(x, 2, torch.Generator().manual_seed(0))  # [N, 1]
    freq = (drawn == policy.actions.T).float().mean(dim=0)  # [A]
    assert float((freq - probs).abs().max()) < 0.01, (freq, probs)  # about 4 standard errors


def test_states_outside_the_box_are_counted_misses():
    policy = _policy()
    policy.set_map(_patch())
    x = torch.tensor([[0.0, 0.0, 0.0], [0.8 + 0.05 + 0.05, 0.0, 0.0], [5.0, 0.0, 0.0], [math.nan, 0.0, 0.0]])
    probs = policy.action_probs(x, 1)
    assert policy.queries == 4 and int(policy.nearest_hits) == 1 and int(policy.misses) == 2
    assert torch.allclose(probs[2:], torch.full((2, 5), 0.2))


def test_sensing_crops_the_world_in_the_robot_frame():
    world_occ = torch.zeros(60, 60, dtype=torch.bool)  # 0.1 m cells from (-3, -3)
    world_occ[48:51, 38:41] = True  # a 0.3 m block around world (0.95, 1.95)
    world = OccupancyGrid(world_occ, (-3.0, -3.0), 0.1)
    pose = torch.tensor([1.95, 1.95, math.pi / 2])  # facing +y: the block is 1 m to the robot's left
    patch = sense_patch(world, pose, SPEC)
    assert 4 <= int(patch.sum()) <= 16
    rows, cols, _ = _patch().cell_index(torch.tensor([[0.03, 0.97], [0.03, -0.97], [-0.97, 0.03]]))
    assert patch[rows, cols].tolist() == [True, False, False]  # left, not right, not behind
    assert int(sense_patch(world, pose, SPEC, max_range=0.5).sum()) == 0  # out of range: unseen
    both = sense_patch(world, torch.stack((pose, torch.tensor([0.95, 1.95, 0.0]))), SPEC)
    assert torch.equal(both[0], patch) and bool(both[1][12, 12])  # the second robot stands on it
    h = math.sqrt(0.5)
    diagonal = sense_patch(world, torch.tensor([0.95 - h, 1.95 - h, math.pi / 4]), SPEC)  # the block 1 m ahead
    assert diagonal[rows, cols].tolist() == [False, False, False] and bool(diagonal[12, 21])
    assert local_map(world, pose, SPEC).origin == SPEC.origin


def test_sensing_an_environment_of_shapes():
    """A rectangle 1 m ahead, sensed from shapes: the same cells as from its grid; beyond the bounds: occupied;
    an obstacle appearing later is unseen until then."""
    from cuniform_torch.envs import Environment, Rect
    env = Environment([Rect(0.9, -0.1, 1.1, 0.1), Rect(-0.6, -0.1, -0.4, 0.1, appear_time=5.0)],
                      bounds=(-5.0, -5.0, 5.0, 5.0))
    occ = torch.zeros(100, 100, dtype=torch.bool)
    occ[49:51, 59:61] = True  # the cells of [0.9, 1.1) x [-0.1, 0.1) on a 0.1 m grid from (-5, -5)
    grid = OccupancyGrid(occ, (-5.0, -5.0), 0.1)
    pose = torch.zeros(3)
    assert torch.equal(sense_patch(env, pose, SPEC, time=0.0), sense_patch(grid, pose, SPEC))
    assert int(sense_patch(env, pose, SPEC).sum()) == 8  # the later obstacle too, with time=None
    edge = sense_patch(env, torch.tensor([4.5, 0.0, 0.0]), SPEC, time=0.0)
    assert bool(edge[:, -1].all()) and not bool(edge[:, 12].any())  # past x = 5: out of bounds


def _world() -> OccupancyGrid:
    occ = torch.zeros(80, 80, dtype=torch.bool)  # 0.1 m cells from (-2, -4)
    occ[35:45, 30:34] = True  # a wall 1 m ahead of the start
    return OccupancyGrid(occ, (-2.0, -4.0), 0.1)


def _cost(states: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
    hit = _world().to(states.device).contains(states[:, 1:, :2]).any(dim=1)
    return (states[:, -1, :2] - torch.tensor([3.0, 0.0], device=states.device)).square().sum(dim=1) + 1e3 * hit


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(
    not torch.cuda.is_available(), reason="needs CUDA"))])
def test_cfu_mppi_encodes_once_per_command_and_returns_finite_actions(device):
    policy = _policy(device=device)
    calls = []
    policy.encoder.register_forward_hook(lambda *args: calls.append(1))
    controller = CFUMPPI(policy, _world(), _cost, num_samples=64, seed=0)
    assert controller.cuniform.num_samples == 32 and controller.local.num_samples == 32  # the budget split
    x = torch.zeros(3, device=device)
    for k in range(3):
        u = controller.command(x)
        assert u.shape == (1,) and u.device.type == device and bool(torch.isfinite(u).all())
        assert len(calls) == k + 1  # one encoding per command, whatever K and T
        x = SYSTEM.step(x.unsqueeze(0), u.unsqueeze(0))[0]
    assert policy.encodes == 3 and policy.miss_rate < 0.5


def test_cfu_mppi_senses_the_map_at_the_pose():
    """The first stage's rollouts are the policy's for the patch sensed at the pose (its embedding)."""
    policy = _policy()
    controller = CFUMPPI(policy, _world(), _cost, num_samples=64, seed=0)
    pose = torch.tensor([0.2, 0.1, 0.3])
    controller.command(pose)
    seen = policy.action_probs(torch.zeros(1, 3), 0)
    policy.set_map(local_map(_world(), pose, SPEC))
    assert torch.equal(seen, policy.action_probs(torch.zeros(1, 3), 0))
    policy.set_map(_patch())
    assert float((seen - policy.action_probs(torch.zeros(1, 3), 0)).abs().max()) > 1e-5


def test_cfu_mppi_from_a_checkpoint_and_bad_arguments(tmp_path):
    path = tmp_path / "p.pt"
    save_map_policy(path, map_policy_checkpoint(_policy(), system_to_json(SYSTEM, T)))
    controller = CFUMPPI(str(path), _world(), _cost, num_samples=16, seed=1)
    assert bool(torch.isfinite(controller.command(torch.zeros(3))).all())
    with pytest.raises(ValueError, match="world must be an OccupancyGrid"):
        CFUMPPI(_policy(), "map", _cost, num_samples=16)
    controller.sense(torch.zeros(1, 3))  # the controller senses; the map policy takes the map as its input
    states, _ = rollout(SYSTEM, controller.map_policy, torch.zeros(3), 8, T, torch.Generator().manual_seed(0))
    assert states.shape == (8, T + 1, 3)
