"""What CFU-MPPI's per-command work keeps between commands, and that it follows the weights.

``MapPolicy.set_maps`` encodes every map afresh but folds the weights (the level term, the scaled first layer, the
body's transposes) once per set of weights: a weight written in place (an optimizer step, ``load_state_dict``)
or swapped for another tensor must be seen by the next ``set_maps``, exactly as a fresh policy would see it.
"""

from __future__ import annotations

import math

import pytest
import torch

from cuniform_torch.maps.encoder import PatchSpec
from cuniform_torch.maps.policy import MapPolicy, MapPolicyConfig
from cuniform_torch.systems import make_system

T = 4
SYSTEM = make_system("dubins", speed=1.0, dt=0.2, num_actions=5, max_omega=math.pi / 2,
                     cell_size=[0.1, 0.1, 2 * math.pi / 16])
SPEC = PatchSpec((24, 24), 0.1, (-1.2, -1.2))


def _policy(seed: int = 0, local: int = 3) -> MapPolicy:
    torch.manual_seed(seed)
    config = MapPolicyConfig(state_dim=3, num_actions=5, horizon=T, periodic=[False, False, True],
                             feature_scale=[0.8, 0.6, 1.0], patch=SPEC.to_dict(), hidden=32, layers=2, embed=8,
                             channels=4, local_features=local)
    return MapPolicy(config, SYSTEM, SYSTEM.action_set()).eval()


def _maps() -> torch.Tensor:
    occ = torch.zeros((2, *SPEC.shape), dtype=torch.bool)
    occ[0, 10:14, 18:20] = True
    occ[1, 4:9, 12:15] = True
    return occ


def _probs(policy: MapPolicy, x: torch.Tensor) -> torch.Tensor:
    policy.set_maps(_maps())
    return torch.stack([policy.action_probs(x, t) for t in range(T)])  # [T, N, A]


def _fresh_probs(policy: MapPolicy, x: torch.Tensor) -> torch.Tensor:
    """What a policy that never set a map, holding ``policy``'s weights now, answers."""
    fresh = _policy(seed=99, local=policy.config.local_features)
    fresh.load_state_dict(policy.state_dict())
    return _probs(fresh, x)


def _step(policy: MapPolicy) -> None:  # an optimizer's step: every parameter written in place
    opt = torch.optim.SGD(policy.parameters(), lr=0.5)
    for p in policy.parameters():
        p.grad = torch.randn_like(p)
    opt.step()


def _load(policy: MapPolicy) -> None:
    policy.load_state_dict(_policy(seed=7, local=policy.config.local_features).state_dict())


def _one_in_place(policy: MapPolicy) -> None:  # one folded tensor written in place, the rest untouched
    with torch.no_grad():
        if policy.inp_l is not None:
            policy.inp_l.weight.add_(0.5)
        else:
            policy.body[-1].bias.add_(torch.arange(5.0))  # not the same for every action: the softmax sees it


def _swap(policy: MapPolicy) -> None:  # a parameter replaced by another one
    policy.body[1].weight = torch.nn.Parameter(torch.randn_like(policy.body[1].weight))


def _set_data(policy: MapPolicy) -> None:  # the same parameter holding another tensor
    policy.inp_x.weight.data = torch.randn_like(policy.inp_x.weight)


@pytest.mark.parametrize("local", [0, 3])
@pytest.mark.parametrize("change", [_step, _load, _one_in_place, _swap, _set_data])
def test_set_maps_sees_new_weights(local, change):
    policy = _policy(local=local)
    x = torch.randn(16, 3) * 0.2  # 8 states per map, inside the box
    before = _probs(policy, x)
    assert torch.equal(_probs(policy, x), before)  # the folded weights kept: the same answer
    change(policy)
    after = _probs(policy, x)
    assert float((after - before).abs().max()) > 1e-4, "the new weights changed nothing"
    assert torch.equal(after, _fresh_probs(policy, x))


def test_moving_the_policy_refolds_its_weights():
    policy = _policy()
    x = torch.randn(16, 3) * 0.2
    before = _probs(policy, x)
    policy.to(torch.float64)
    policy.set_maps(_maps())
    assert policy._w_state is not None and policy._w_state.dtype == torch.float64
    policy.to(torch.float32)
    assert torch.equal(_probs(policy, x), before)
