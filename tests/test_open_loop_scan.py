"""The Dubins closed-form scan equals the step loop, and open_loop uses it only where the step is the class's own."""

import math

import pytest
import torch

from cuniform_torch.sampling.rollout import open_loop
from cuniform_torch.systems.models import Dubins


def _step_loop(system, start, actions):
    """The reference: ``system.step`` applied T times, states stacked ``[N, T+1, d]``."""
    x, states = start, [start]
    for t in range(actions.shape[1]):
        x = system.step(x, actions[:, t])
        states.append(x)
    return torch.stack(states, dim=1)


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-11), (torch.float32, 5e-5)])
@pytest.mark.parametrize("horizon", [1, 15, 100])
def test_the_scan_equals_the_step_loop(dtype, tol, horizon):
    system = Dubins(speed=0.5, dt=0.2, max_omega=1.5, num_actions=7)
    g = torch.Generator().manual_seed(horizon)
    n = 257
    start = torch.stack((torch.randn(n, generator=g) * 5, torch.randn(n, generator=g) * 5,
                         (torch.rand(n, generator=g) * 2 - 1) * math.pi), dim=1).to(dtype)
    actions = (torch.randn(n, horizon, 1, generator=g, dtype=dtype) * 1.5).clamp(-1.5, 1.5)
    ref = _step_loop(system, start, actions)
    got = system.scan(start, actions)
    assert got.shape == (n, horizon + 1, 3)
    assert torch.equal(got[:, 0], start)
    assert (got - ref).abs().max() < tol
    assert got[..., 2].abs().max() <= math.pi  # headings wrapped as the step wraps them


def test_open_loop_takes_the_scan_of_a_dubins_and_steps_a_subclass_that_changes_step():
    class Slower(Dubins):
        def step(self, x, u, out=None):
            y = super().step(x, u, out=out)
            y[:, :2] = x[:, :2] + 0.5 * (y[:, :2] - x[:, :2])
            return y

    start = torch.zeros(8, 3)
    actions = torch.full((8, 5, 1), 0.3)
    plain, slower = Dubins(), Slower()
    assert torch.allclose(open_loop(plain, start, actions), plain.scan(start, actions))
    assert torch.allclose(open_loop(slower, start, actions), _step_loop(slower, start, actions))
    assert not torch.allclose(open_loop(slower, start, actions), plain.scan(start, actions))
