"""Smooth MPPI, kernel MPPI and the mixture proposal: each proposal's statistics (the rate noise integrates to the
actions; the interpolated sequence passes through its control points; the mixture's split is exact and each share
is its proposal's draw), batched = alone, and the refusals."""

from __future__ import annotations

import pytest
import torch

from cuniform_torch import TablePolicy, make_system
from cuniform_torch.controllers.mixture import (
    CUniformMixtureMPPI,
    MixtureMPPI,
    MixtureProposal,
    split_budget,
)
from cuniform_torch.controllers.proposals import GaussianProposal, PolicyProposal
from cuniform_torch.controllers.result import MPPIResult
from cuniform_torch.controllers.smooth import (
    KernelMPPI,
    KernelProposal,
    SmoothMPPI,
    SmoothProposal,
    rbf_interpolation,
)
from cuniform_torch.controllers.streams import RobotStreams

DUBINS = make_system("dubins", max_omega=100.0)  # wide bounds: the statistics are not clipped
STARTS = torch.tensor([[0.0, 0.0, 0.0], [0.5, -0.3, 1.0]])
GOAL = torch.tensor([2.0, 1.0])


def _goal_cost(states, actions):
    return (states[:, 1:, :2] - GOAL).square().sum(dim=(1, 2))


def _streams(seed: int = 0, robots: int = 1) -> RobotStreams:
    return RobotStreams.seeded([seed + b for b in range(robots)], "cpu")


@pytest.fixture
def policy(dubins_table) -> TablePolicy:
    return TablePolicy(dubins_table)


# ------------------------------------------------------------------------------------------ smooth MPPI

def test_smooth_rate_noise_integrates_to_the_actions():
    """Actions = last action + dt * cumsum(rates); the rates are white around the nominal's rate with the std."""
    p = SmoothProposal(DUBINS, 20000, 10, noise_std=2.0, dtype=torch.float64)
    last = torch.tensor([0.3], dtype=torch.float64)
    nominal = torch.linspace(0.3, 1.2, 10, dtype=torch.float64)[:, None] + 0.05  # [T, 1]: rate 0.1 / dt + a jump
    p._last.copy_(last)
    p.nominal = nominal
    _, actions = p.propose_batch(torch.zeros(1, 3, dtype=torch.float64), _streams())
    a = actions[0, :, :, 0]  # [K, T]
    rates = torch.diff(a, dim=1, prepend=last.expand(a.shape[0], 1)) / DUBINS.dt  # [K, T]
    want_rate = torch.diff(nominal[:, 0], prepend=last) / DUBINS.dt  # [T]
    torch.testing.assert_close(rates.mean(dim=0), want_rate, atol=0.05, rtol=0)
    torch.testing.assert_close(rates.std(dim=0), torch.full((10,), 2.0, dtype=torch.float64), atol=0.05, rtol=0)
    corr = torch.corrcoef(torch.stack((rates[:, 3], rates[:, 4])))[0, 1]
    assert abs(float(corr)) < 0.03  # white in rate
    dev_std = (a - nominal[:, 0]).std(dim=0)  # a random walk: dt * std * sqrt(t + 1)
    want = DUBINS.dt * 2.0 * torch.arange(1, 11, dtype=torch.float64).sqrt()
    torch.testing.assert_close(dev_std, want, rtol=0.03, atol=0)


def test_smooth_rate_bound_and_the_warm_start():
    p = SmoothProposal(DUBINS, 500, 8, noise_std=5.0, rate_max=1.0, dtype=torch.float64)
    _, actions = p.propose_batch(torch.zeros(1, 3, dtype=torch.float64), _streams())
    rates = torch.diff(actions[0, :, :, 0], dim=1, prepend=torch.zeros(500, 1, dtype=torch.float64)) / DUBINS.dt
    assert float(rates.abs().max()) <= 1.0 + 1e-9
    nominal = torch.arange(8, dtype=torch.float64)[None, :, None] * 0.1  # [1, T, 1]
    p.update(MPPIResult(nominal[:, 0], nominal, torch.zeros(1, 2, 9, 3), actions[:, :2], torch.zeros(1, 2),
                        torch.ones(1, 2) / 2))
    torch.testing.assert_close(p.last, torch.tensor([0.0], dtype=torch.float64))
    torch.testing.assert_close(p.nominal[:, 0], torch.tensor([0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.7],
                                                             dtype=torch.float64))
    p.reset()
    assert float(p.nominal.abs().max()) == 0 and float(p.last.abs().max()) == 0


def test_smooth_mppi_adds_the_action_sequence_cost():
    ctrl = SmoothMPPI(DUBINS, _goal_cost, num_samples=32, horizon=6, noise_std=3.0, smoothness=2.5, seed=0)
    res = ctrl.plan(STARTS[0])
    jumps = torch.diff(res.actions, dim=1, prepend=torch.zeros(32, 1, 1))
    want = _goal_cost(res.states, res.actions) + 2.5 * jumps.square().sum(dim=(1, 2))
    torch.testing.assert_close(res.costs, want)


def test_kernel_sequences_pass_through_their_control_points():
    """Every sampled sequence is the RBF interpolation of its values at the support steps (integers here), and those
    values are the control points: Gaussian around the nominal's, independent."""
    p = KernelProposal(DUBINS, 20000, 13, noise_std=0.7, num_points=7, sigma=1.5, dtype=torch.float64)
    torch.testing.assert_close(p.support, torch.arange(0, 13, 2, dtype=torch.float64))
    nominal = torch.sin(torch.arange(13, dtype=torch.float64))[:, None]
    p.nominal = nominal
    _, actions = p.propose_batch(torch.zeros(1, 3, dtype=torch.float64), _streams())
    a = actions[0, :, :, 0]  # [K, T]
    points = a[:, ::2]  # [K, 7] the sequence at the support steps
    torch.testing.assert_close(a, points @ p.interp[:, :].T.to(a.dtype), atol=1e-9, rtol=0)
    centre = p.fit @ nominal[:, 0]
    torch.testing.assert_close(points.mean(dim=0), centre, atol=0.02, rtol=0)
    torch.testing.assert_close(points.std(dim=0), torch.full((7,), 0.7, dtype=torch.float64), atol=0.02, rtol=0)
    assert float(torch.corrcoef(points[:, 2:4].T)[0, 1].abs()) < 0.03
    # the control points of an interpolated nominal are recovered exactly (the warm start keeps them)
    theta = torch.randn(7, 1, dtype=torch.float64)
    torch.testing.assert_close(p.fit @ (p.interp @ theta), theta)


def test_rbf_interpolation_is_identity_at_the_support_and_refuses_ill_conditioning():
    support = torch.tensor([0.0, 2.5, 6.0, 9.0])
    torch.testing.assert_close(rbf_interpolation(support, support, 1.0), torch.eye(4, dtype=torch.float64))
    with pytest.raises(ValueError, match="ill-conditioned"):
        rbf_interpolation(torch.arange(15.0), torch.linspace(0, 14, 15), 20.0)
    with pytest.raises(ValueError, match="num_points"):
        KernelProposal(DUBINS, 8, 6, num_points=7)


# ------------------------------------------------------------------------------------------ the mixture

@pytest.mark.parametrize("total, shares, want", [(10, (1, 1, 1), [4, 3, 3]), (65, (0.5, 0.5), [33, 32]),
                                                 (3, (100, 1, 1), [1, 1, 1]), (1000, (0.25, 0.75), [250, 750]),
                                                 (7, (0.3, 0.3, 0.4), [2, 2, 3])])
def test_split_is_exact(total, shares, want):
    parts = split_budget(total, shares)
    assert parts == want and sum(parts) == total


def test_split_is_exact_for_every_budget():
    for total in range(3, 300):
        for shares in ((1, 2, 3), (0.01, 0.99, 0.5), (0.5,)):
            parts = split_budget(total, shares)
            assert sum(parts) == total and min(parts) >= 1
            exact = [total * s / sum(shares) for s in shares]
            assert all(abs(p - e) < 1 for p, e in zip(parts, exact)) or min(exact) < 1


def test_split_refuses():
    with pytest.raises(ValueError, match="at least one sample per part"):
        split_budget(2, (1, 1, 1))
    with pytest.raises(ValueError, match="finite numbers > 0"):
        split_budget(10, (1, 0))


def test_each_share_is_drawn_from_its_proposal(policy):
    """The mixture's rows are its parts' draws, in order, from the robot's one stream; the C-Uniform rows are the
    table's actions, the Gaussian rows noise around the nominal."""
    cu = PolicyProposal(policy, 30, num_robots=2)
    gauss = GaussianProposal(policy.system, 70, cu.horizon, noise_std=0.2, num_robots=2)
    mix = MixtureProposal([cu, gauss])
    assert mix.num_samples == 100 and mix.offsets == [0, 30, 100]
    states, actions = mix.propose_batch(STARTS, _streams(5, 2))
    streams = _streams(5, 2)
    cu_x, cu_u = cu.propose_batch(STARTS, streams)
    g_x, g_u = gauss.propose_batch(STARTS, streams)
    torch.testing.assert_close(actions, torch.cat((cu_u, g_u), dim=1))
    torch.testing.assert_close(states, torch.cat((cu_x, g_x), dim=1))
    table_actions = policy.system.action_set(dtype=torch.float32, device="cpu")[:, 0]
    assert bool(torch.isin(actions[:, :30], table_actions).all())
    assert not bool(torch.isin(actions[:, 30:], table_actions).all())


def test_mixture_weighs_all_rows_together_and_warm_starts_the_gaussian_share(policy):
    ctrl = CUniformMixtureMPPI(policy, _goal_cost, num_samples=64, cuniform_fraction=0.25, noise_std=0.3, seed=1)
    assert ctrl.mixture.sizes == [16, 48]
    res = ctrl.plan(STARTS[0])
    assert res.weights.shape == (64,)
    torch.testing.assert_close(res.weights.sum(), torch.tensor(1.0))
    want = torch.softmax(-(res.costs - res.costs.min()) / ctrl.lambda_, dim=0)
    torch.testing.assert_close(res.weights, want)
    ctrl.command(STARTS[0])
    gauss = ctrl.mixture.parts[1]
    assert float(gauss.nominal.abs().max()) > 0  # the warm start is the whole mixture's weighted sequence


def test_mixture_refuses_parts_that_differ(policy):
    cu = PolicyProposal(policy, 8)
    with pytest.raises(ValueError, match="mixture part 1"):
        MixtureProposal([cu, GaussianProposal(policy.system, 8, cu.horizon - 1)])
    with pytest.raises(TypeError, match="not a batched Proposal"):
        MixtureProposal([cu, object()])  # type: ignore[list-item]
    with pytest.raises(ValueError, match="cuniform_fraction"):
        CUniformMixtureMPPI(policy, _goal_cost, num_samples=8, cuniform_fraction=1.0)


# ------------------------------------------------------------------------------------------ batched = alone

def _controllers(name: str, policy, seed, robots: int = 1):
    if name == "smooth":
        return SmoothMPPI(DUBINS, _goal_cost, num_samples=64, horizon=10, noise_std=3.0, seed=seed, num_robots=robots)
    if name == "kernel":
        return KernelMPPI(DUBINS, _goal_cost, num_samples=64, horizon=10, noise_std=0.8, seed=seed,
                          num_robots=robots)
    if name == "mixture":
        return CUniformMixtureMPPI(policy, _goal_cost, num_samples=64, noise_std=0.5, seed=seed, num_robots=robots)
    parts = [GaussianProposal(DUBINS, 20, 10, 0.3, num_robots=robots),
             KernelProposal(DUBINS, 20, 10, 1.0, num_robots=robots),
             SmoothProposal(DUBINS, 24, 10, 2.0, num_robots=robots)]
    return MixtureMPPI(parts, _goal_cost, seed=seed)


@pytest.mark.parametrize("name", ["smooth", "kernel", "mixture", "three_part_mixture"])
def test_batched_equals_alone(name, policy):
    batched = _controllers(name, policy, [3, 8], robots=2)
    alone = [_controllers(name, policy, s) for s in (3, 8)]
    x = STARTS.clone()
    for step in range(4):
        u = batched.command(x)
        for b in range(2):
            torch.testing.assert_close(u[b], alone[b].command(x[b]), atol=1e-5, rtol=0)
        if step == 1:
            batched.reset(torch.tensor([1]))
            alone[1].reset()
        x = batched.system.step(x, u)


# ------------------------------------------------------------------------------------------ no host sync

@pytest.mark.parametrize("name", ["smooth", "kernel", "three_part_mixture"])
def test_a_command_reads_nothing_back_to_the_host_when_debug_is_off(name, policy, monkeypatch):
    """A command of each new proposal is a tensor program: no ``.item()`` / ``bool(t)`` / ``.tolist()`` per command
    (what would wait for a CUDA device)."""
    names = ("item", "tolist", "__bool__", "__int__", "__float__", "__index__", "numpy")
    ctrl = _controllers(name, policy, [0, 1], robots=2)
    ctrl.debug = False
    ctrl.command(STARTS)
    calls: list[str] = []
    originals = {n: getattr(torch.Tensor, n) for n in names}

    def counting(n, original):
        def counted(tensor, *args, **kwargs):
            calls.append(n)
            return original(tensor, *args, **kwargs)
        return counted

    for n, original in originals.items():
        monkeypatch.setattr(torch.Tensor, n, counting(n, original))
    ctrl.command(STARTS)
    ctrl.plan(STARTS)
    for n, original in originals.items():
        monkeypatch.setattr(torch.Tensor, n, original)
    assert calls == [], f"{name} read {calls} back per command"


# ------------------------------------------------------------------------------------------ on a CUDA device

CUDA = torch.cuda.is_available()


@pytest.mark.gpu
@pytest.mark.skipif(not CUDA, reason="needs a CUDA device")
@pytest.mark.parametrize("name", ["smooth", "kernel", "mixture"])
def test_on_cuda_batched_equals_alone_and_a_graphed_command_is_the_eager_command(name, dubins_table):
    """On CUDA: a batch commands what its robots would alone, and ``cuda_graph=True`` replays what eager commands
    command (the smoothness cost reads the proposal's last actions in place; the mixture's parts share the streams)."""
    goal = GOAL.cuda()

    def cost(states, actions):
        return (states[:, 1:, :2] - goal).square().sum(dim=(1, 2))

    table = TablePolicy(dubins_table, device="cuda")
    make = {
        "smooth": lambda seed, n, g: SmoothMPPI(DUBINS, cost, num_samples=256, horizon=10, noise_std=3.0,
                                                device="cuda", seed=seed, num_robots=n, cuda_graph=g),
        "kernel": lambda seed, n, g: KernelMPPI(DUBINS, cost, num_samples=256, horizon=10, noise_std=0.8,
                                                device="cuda", seed=seed, num_robots=n, cuda_graph=g),
        "mixture": lambda seed, n, g: CUniformMixtureMPPI(table, cost, num_samples=256, noise_std=0.5, seed=seed,
                                                          num_robots=n, cuda_graph=g),
    }[name]
    starts = STARTS.cuda()
    batched, graphed = make([3, 8], 2, False), make([3, 8], 2, True)
    alone = [make(s, 1, False) for s in (3, 8)]
    x = starts.clone()
    for _ in range(4):
        u = batched.command(x)
        torch.testing.assert_close(graphed.command(x), u, atol=1e-4, rtol=0)
        for b in range(2):
            torch.testing.assert_close(alone[b].command(x[b]), u[b], atol=1e-4, rtol=0)
        x = DUBINS.step(x, u)
