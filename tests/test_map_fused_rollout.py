"""The map policy's compiled rollout (cuniform_torch.maps.kernels) against the step-by-step path it replaces.

Both paths draw the same uniforms from the rollout's generator, so with the same seed they must take the same
actions and reach the same states (to float rounding), count the same support misses and near hits, and take
the uniform row for states outside the support box. A wall in the patch and local features on, so the probes'
bilinear reads matter; a small support box, so that rollouts leave it.
"""

from __future__ import annotations

import math

import pytest
import torch

from cuniform_torch.envs import OccupancyGrid
from cuniform_torch.maps import kernels
from cuniform_torch.maps.encoder import PatchSpec
from cuniform_torch.maps.policy import MapPolicy, MapPolicyConfig
from cuniform_torch.sampling.rollout import rollout
from cuniform_torch.systems import make_system

T = 6
SYSTEM = make_system("dubins", speed=1.0, dt=0.2, num_actions=5, max_omega=math.pi / 2,
                     cell_size=[0.1, 0.1, 2 * math.pi / 16])
SPEC = PatchSpec((24, 24), 0.1, (-1.2, -1.2))

pytestmark = pytest.mark.skipif(not kernels.usable(torch.device("cpu"), torch.float32), reason="needs numba")


def _policy(scale: float, local: int) -> MapPolicy:
    torch.manual_seed(1)
    config = MapPolicyConfig(state_dim=3, num_actions=5, horizon=T, periodic=[False, False, True],
                             feature_scale=[scale, scale, 1.0], patch=SPEC.to_dict(), hidden=16, layers=2, embed=8,
                             channels=4, local_features=local)
    policy = MapPolicy(config, SYSTEM, SYSTEM.action_set()).eval()
    with torch.no_grad():  # sharper than an initialisation: the draws depend on the inputs
        for p in policy.parameters():
            p.mul_(4.0)
    occ = torch.zeros(SPEC.shape, dtype=torch.bool)
    occ[8:16, 15:18] = True  # a wall 0.3-0.6 m ahead
    policy.set_map(OccupancyGrid(occ, SPEC.origin, SPEC.resolution))
    return policy


def _both(policy: MapPolicy, pose: torch.Tensor, n: int = 3000):
    out = []
    for fused in (True, False):
        policy.reset_counters()
        policy.compiled = fused  # False: the step-by-step path
        states, actions = rollout(SYSTEM, policy, pose, n, T, torch.Generator().manual_seed(7))
        out.append((states, actions, policy.queries, int(policy.nearest_hits), int(policy.misses)))
    return out


@pytest.mark.parametrize("local", [0, 3])
@pytest.mark.parametrize("scale", [2.0, 0.62])  # 0.62 m: rollouts of 1 m/s pass the near band and leave the box
def test_the_compiled_rollout_is_the_step_by_step_one(scale, local):
    policy = _policy(scale, local)
    pose = torch.tensor([0.4, -0.3, 0.7])
    (s1, a1, q1, n1, m1), (s2, a2, q2, n2, m2) = _both(policy, pose)
    same = (a1 == a2).all(dim=(1, 2)).float().mean().item()
    assert same >= 0.999, same  # a draw may differ only where a uniform falls within rounding of a cdf step
    rows = (a1 == a2).all(dim=(1, 2))
    assert torch.allclose(s1[rows], s2[rows], atol=1e-5)
    assert (q1, n1, m1) == (q2, n2, m2)
    if scale < 1:
        assert m1 > 0 and n1 > 0  # the box is left: the uniform rows were exercised


def test_the_compiled_rollout_follows_the_policy_at_the_first_step():
    policy = _policy(2.0, 3)
    states, actions = rollout(SYSTEM, policy, torch.zeros(3), 40000, T, torch.Generator().manual_seed(3))
    probs = policy.action_probs(torch.zeros(1, 3), 0)[0]  # [A]
    freq = (actions[:, 0] == policy.actions.T).float().mean(dim=0)  # [A]
    assert float((freq - probs).abs().max()) < 0.01, (freq, probs)


def test_other_systems_and_devices_take_the_step_by_step_path():
    policy = _policy(2.0, 0)
    gen = torch.Generator().manual_seed(0)
    assert policy.fused_rollout(SYSTEM, torch.zeros(3), 4, T, gen) is not None
    assert policy.fused_rollout(SYSTEM, torch.zeros(3, dtype=torch.float64), 4, T, gen) is None
    assert policy.fused_rollout(SYSTEM, torch.zeros(2, 3), 4, T, gen) is None
    assert policy.fused_rollout(SYSTEM, torch.zeros(3), 4, T, None) is not None  # torch's default generator
    policy.compiled = False
    assert policy.fused_rollout(SYSTEM, torch.zeros(3), 4, T, gen) is None
    policy.compiled = True
    policy.clear_map()
    assert policy.fused_rollout(SYSTEM, torch.zeros(3), 4, T, gen) is None
