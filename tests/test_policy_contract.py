"""The rollout's policy contract: every optional hook is settled once, in :class:`RolloutPlan`, never probed per
rollout (issue 33 item 3)."""
from __future__ import annotations

import torch
from torch import Tensor

from cuniform_torch.sampling.rollout import RolloutPlan
from cuniform_torch.systems import make_system


class CountingPolicy:
    """A uniform policy over the system's actions; ``__getattr__`` counts lookups of names it does not have (the
    optional hooks a rollout may probe for)."""

    def __init__(self, actions: Tensor) -> None:
        self.actions = actions  # [A, q]
        self.probes: list[str] = []

    def action_probs(self, x: Tensor, t: int) -> Tensor:
        """Uniform ``[N, A]``."""
        return x.new_full((x.shape[0], self.actions.shape[0]), 1.0 / self.actions.shape[0])

    def __getattr__(self, name: str) -> object:
        if name == "probes":
            raise AttributeError(name)
        self.probes.append(name)
        raise AttributeError(name)


def test_hooks_settled_at_construction() -> None:
    system = make_system("dubins")
    policy = CountingPolicy(system.action_set(dtype=torch.float64))
    plan = RolloutPlan.of(system, policy)
    assert plan.fused_rollout is None and plan.watch_start is None and plan.for_start is None
    policy.probes.clear()
    x0 = torch.zeros(system.state_dim, dtype=torch.float64)
    for _ in range(2):
        states, _actions = plan.run(system, policy, x0, 8, 5, torch.Generator().manual_seed(0))
        assert states.shape[:2] == (8, 6)
    assert policy.probes == [], f"hooks probed per rollout: {policy.probes}"
