"""Colored and low-pass noise proposals: their statistics (the spectrum's slope, the lag-1 correlation, the
per-step variance) and the batched = alone property of every proposal."""

from __future__ import annotations

import math

import pytest
import torch

from cuniform_torch import make_system
from cuniform_torch.controllers.filtered import (
    ColoredMPPI,
    ColoredNoiseProposal,
    LowPassMPPI,
    LowPassProposal,
    colored_filter,
    low_pass_filter,
)
from cuniform_torch.controllers.streams import RobotStreams

DUBINS = make_system("dubins", max_omega=10.0)  # wide bounds: the statistics are not clipped
STARTS = torch.tensor([[0.0, 0.0, 0.0], [0.5, -0.3, 1.0]])


def _noise(proposal, n_robots=1, seed=0) -> torch.Tensor:
    """``[B, K, T]`` the proposal's noise (nominal zero), one action dimension."""
    streams = RobotStreams.seeded([seed + b for b in range(n_robots)], "cpu")
    return proposal._sequences(streams, proposal.num_samples, proposal.horizon)[..., 0]


@pytest.mark.parametrize("beta", [0.0, 1.0, 2.0])
def test_colored_noise_has_the_power_law_spectrum_and_the_std_at_every_step(beta):
    proposal = ColoredNoiseProposal(DUBINS, 4000, 64, noise_std=0.5, beta=beta, dtype=torch.float64)
    e = _noise(proposal)[0]  # [K, T]
    torch.testing.assert_close(e.std(dim=0), torch.full((64,), 0.5, dtype=torch.float64), atol=0.03, rtol=0)
    power = torch.fft.rfft(e, dim=1).abs().square().mean(dim=0)[1:-1]  # [T/2 - 1] without DC and Nyquist
    freqs = torch.fft.rfftfreq(64, dtype=torch.float64)[1:-1]
    slope = torch.linalg.lstsq(torch.stack((freqs.log(), torch.ones_like(freqs)), 1), power.log()[:, None]).solution
    assert abs(float(slope[0]) + beta) < 0.15, f"spectrum slope {float(slope[0]):.3f}, expected {-beta}"


@pytest.mark.parametrize("a", [0.0, 0.5, 0.9])
def test_low_pass_noise_has_its_lag_one_correlation_and_the_std_at_every_step(a):
    proposal = LowPassProposal(DUBINS, 20000, 12, noise_std=0.3, a=a, dtype=torch.float64)
    e = _noise(proposal)[0]
    torch.testing.assert_close(e.std(dim=0), torch.full((12,), 0.3, dtype=torch.float64), atol=0.01, rtol=0)
    corr = torch.corrcoef(torch.stack((e[:, 4], e[:, 5])))[0, 1]
    assert abs(float(corr) - a) < 0.02


def test_the_filters_refuse_what_they_cannot_be():
    with pytest.raises(ValueError, match="beta must be"):
        colored_filter(10, -1.0)
    with pytest.raises(ValueError, match="in \\[0, 1\\)"):
        low_pass_filter(10, 1.0)
    with pytest.raises(ValueError, match="a cutoff \\(Hz\\) or the coefficient a"):
        LowPassMPPI(DUBINS, lambda s, a: s[:, -1, 0], cutoff=1.0, a=0.5)
    ctrl = LowPassMPPI(DUBINS, lambda s, a: s[:, -1, 0], num_samples=8, horizon=4, cutoff=1.0)
    assert ctrl.a == pytest.approx(math.exp(-2 * math.pi * 1.0 * DUBINS.dt))


@pytest.mark.parametrize("cls, kw", [(ColoredMPPI, dict(beta=1.0)), (LowPassMPPI, dict(a=0.8))])
def test_batched_equals_alone(cls, kw):
    goal = torch.tensor([2.0, 1.0])

    def cost(states, actions):
        return (states[:, 1:, :2] - goal).square().sum(dim=(1, 2))

    batched = cls(DUBINS, cost, num_samples=64, horizon=10, noise_std=0.5, seed=[3, 8], num_robots=2, **kw)
    alone = [cls(DUBINS, cost, num_samples=64, horizon=10, noise_std=0.5, seed=s, **kw) for s in (3, 8)]
    x = STARTS.clone()
    for _ in range(3):
        u = batched.command(x)
        for b in range(2):
            torch.testing.assert_close(u[b], alone[b].command(x[b]), atol=1e-5, rtol=0)
        x = DUBINS.step(x, u)
