"""The rollout's preallocated states (a system whose ``step`` takes ``out=``) against plain stepping, bit for bit."""

from __future__ import annotations

import pytest
import torch

from cuniform_torch import Dubins, TablePolicy, rollout
from cuniform_torch.sampling.rollout import RolloutPlan


class PlainDubins(Dubins):
    """Dubins stepped the plain way: it overrides ``step`` without declaring ``step_out``."""

    def step(self, x, u):
        return super().step(x, u)


@pytest.mark.parametrize("start", ["origin", "pose", "batch"])
@pytest.mark.parametrize("horizon", [0, 1, 7])
def test_buffered_rollout_is_plain_stepping_bit_for_bit(dubins_table, start, horizon):
    policy = TablePolicy(dubins_table)
    policy.compiled = False  # the step-by-step path (the whole-rollout loop: tests/test_cpu_kernel.py)
    assert RolloutPlan.of(Dubins(), policy).step_out and not RolloutPlan.of(PlainDubins(), policy).step_out
    n = 64
    x0 = {"origin": torch.zeros(3), "pose": torch.tensor([1.0, -2.0, 0.7]),
          "batch": torch.randn(n, 3, generator=torch.Generator().manual_seed(3))}[start]
    got = rollout(Dubins(), policy, x0, n, horizon, torch.Generator().manual_seed(0))
    expected = rollout(PlainDubins(), policy, x0, n, horizon, torch.Generator().manual_seed(0))
    for a, b in zip(got, expected):
        assert a.shape == b.shape and a.dtype == b.dtype and torch.equal(a, b)
    if start != "batch":  # the states are a view of the time-major [T+1, d, N] buffer (what a cost reads fastest)
        assert got[0].permute(1, 2, 0).is_contiguous()
