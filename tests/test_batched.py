"""Batched control: a controller of B robots commands what B controllers of one robot command, seeded the same.

Every controller of the MPPI family, over several commands (so the warm starts carry), with robots at different
states: MPPI, log-MPPI, C-Uniform MPPI on a table, CU-MPPI, C-Uniform MPPI on a table set whose robots choose
different members, CFU-MPPI sensing a different local map around each robot. Plus per-robot resets, a cost per
robot, the errors of a wrong batch, and the per-command host syncs of a plan.
"""

from __future__ import annotations

import math

import pytest
import torch

from cuniform_torch import CUMPPI, MPPI, CUniformMPPI, LogMPPI, TablePolicy, load_table, make_system
from cuniform_torch.controllers.cfu import CFUMPPI
from cuniform_torch.envs import OccupancyGrid
from cuniform_torch.maps.encoder import PatchSpec
from cuniform_torch.maps.policy import MapPolicy, MapPolicyConfig

DUBINS = make_system("dubins")
GOAL = torch.tensor([2.0, 1.0])
STARTS = torch.tensor([[0.0, 0.0, 0.0], [0.5, -0.3, 1.0], [-0.2, 0.4, -2.0]])
SEEDS = [3, 11, 40]


def goal_cost(states: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
    """Squared distance to GOAL summed over the horizon: ``[N, T+1, d]`` -> ``[N]``."""
    return (states[..., 1:, :2] - GOAL).square().sum(dim=-1).sum(dim=-1)


def _drive(controller, states: torch.Tensor, steps: int = 4) -> list[torch.Tensor]:
    """Commands of ``steps`` cycles from ``states`` (``[B, d]`` or ``[d]``), each state stepped by its command."""
    out = []
    system = controller.system
    for _ in range(steps):
        u = controller.command(states)
        out.append(u)
        x, a = (states, u) if states.ndim == 2 else (states[None], u[None])
        nxt = system.step(x, a)
        states = nxt if states.ndim == 2 else nxt[0]
    return out


def _same_as_alone(make, starts: torch.Tensor = STARTS, seeds: list[int] = SEEDS, steps: int = 4,
                   atol: float | None = None) -> None:
    """``make(seed, num_robots)`` batched over the starts = one controller per start, seeded alike: bit for bit
    (``atol`` None; the CPU arithmetic of a robot does not depend on B), or to ``atol``."""
    batched = _drive(make(seeds, len(seeds)), starts, steps)
    for b, seed in enumerate(seeds):
        alone = _drive(make(seed, 1), starts[b], steps)
        for t in range(steps):
            if atol is None:
                assert torch.equal(batched[t][b], alone[t]), f"robot {b}, command {t}: {batched[t][b]} != {alone[t]}"
            else:
                torch.testing.assert_close(batched[t][b], alone[t], atol=atol, rtol=0)


@pytest.fixture(scope="module")
def table(dubins_table):
    return TablePolicy(dubins_table)


@pytest.mark.parametrize("cls", [MPPI, LogMPPI])
def test_gaussian_controllers_batched_equal_alone(cls):
    _same_as_alone(lambda seed, n: cls(DUBINS, goal_cost, num_samples=64, horizon=8, noise_std=0.5, seed=seed,
                                       num_robots=n))


def test_cuniform_on_a_table_batched_equals_alone(table):
    _same_as_alone(lambda seed, n: CUniformMPPI(table, goal_cost, num_samples=64, seed=seed, num_robots=n))


@pytest.mark.parametrize("local", ["mppi", "log_mppi"])
def test_cumppi_batched_equals_alone(table, local):
    _same_as_alone(lambda seed, n: CUMPPI(table, goal_cost, num_samples=64, local=local, seed=seed, num_robots=n))


def test_cumppi_in_one_pass_batched_equals_alone(table):
    _same_as_alone(lambda seed, n: CUMPPI(table, goal_cost, num_samples=64, seed=seed, num_robots=n, pipelined=True))


def test_cumppi_in_one_pass_seeds_the_next_local_pass_with_this_commands_best_cuniform_sequence(table):
    """One pass: K1 C-Uniform rollouts and K2 local ones side by side; after a command the local nominal is each
    robot's lowest-cost C-Uniform sequence of that command, shifted one step."""
    ctrl = CUMPPI(table, goal_cost, num_samples=64, seed=[1, 2], num_robots=2, pipelined=True)
    k1 = ctrl.cuniform.num_samples
    result = ctrl.plan(STARTS[:2])
    assert result.actions.shape[1] == 64 and ctrl.num_samples == 64
    ctrl.proposal.update(result)
    best = result.costs[:, :k1].argmin(dim=1)
    for b in range(2):
        seq = result.actions[b, best[b]]
        torch.testing.assert_close(ctrl.local.nominal[b], torch.cat((seq[1:], seq[-1:])))


def test_an_int_seed_gives_robot_zero_that_seed_and_the_others_their_own_streams():
    batched = MPPI(DUBINS, goal_cost, num_samples=32, horizon=6, seed=5, num_robots=3)
    alone = MPPI(DUBINS, goal_cost, num_samples=32, horizon=6, seed=5)
    same = STARTS[0].expand(3, 3).contiguous()
    u = batched.command(same)
    torch.testing.assert_close(u[0], alone.command(STARTS[0]))
    assert not torch.equal(u[0], u[1]) and not torch.equal(u[1], u[2])  # same state, different streams


def test_reset_of_some_robots_forgets_only_their_warm_start():
    make = lambda seed, n: MPPI(DUBINS, goal_cost, num_samples=64, horizon=8, noise_std=0.5, seed=seed,  # noqa: E731
                                num_robots=n)
    batched = make(SEEDS, 3)
    alone = [make(s, 1) for s in SEEDS]
    for _ in range(3):
        batched.command(STARTS)
        for b in range(3):
            alone[b].command(STARTS[b])
    batched.reset([1])
    alone[1].reset()
    assert batched.proposal.nominal[1].abs().sum() == 0 and batched.proposal.nominal[0].abs().sum() > 0
    u = batched.command(STARTS)
    for b in range(3):
        torch.testing.assert_close(u[b], alone[b].command(STARTS[b]))
    with pytest.raises(ValueError, match="robots must be indices in 0..2"):
        batched.reset([3])


def test_a_cost_per_robot_sees_the_batch_and_steers_each_robot_to_its_goal():
    goals = torch.tensor([[2.0, 0.0], [-2.0, 0.0]])

    def per_robot(states: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:  # [B, K, T+1, d] -> [B, K]
        assert states.ndim == 4
        return (states[:, :, 1:, :2] - goals[:, None, None]).square().sum(dim=-1).sum(dim=-1)

    per_robot.batched = True  # type: ignore[attr-defined]
    ctrl = MPPI(DUBINS, per_robot, num_samples=256, horizon=10, noise_std=1.0, seed=0, num_robots=2)
    x = torch.zeros(2, 3)
    for _ in range(40):
        x = DUBINS.step(x, ctrl.command(x))
    assert float(x[0, 0]) > 0.5 and float(x[1, 0]) < -0.5  # each went its own way


def test_a_batch_of_the_wrong_size_and_a_shared_generator_are_clear_errors():
    ctrl = MPPI(DUBINS, goal_cost, num_samples=16, horizon=4, num_robots=3)
    with pytest.raises(ValueError, match=r"state must be a tensor of shape \[3, 3\], got \[2, 3\]"):
        ctrl.command(torch.zeros(2, 3))
    with pytest.raises(ValueError, match=r"shape \[3, 3\], got \[3\]"):
        ctrl.command(torch.zeros(3))  # one state for three robots
    with pytest.raises(ValueError, match="needs one stream each"):
        from cuniform_torch.controllers.core import MPPICore
        from cuniform_torch.controllers.proposals import GaussianProposal
        MPPICore(GaussianProposal(DUBINS, 8, 4, num_robots=2), goal_cost, generator=torch.Generator())
    with pytest.raises(ValueError, match="2 ints"):
        MPPI(DUBINS, goal_cost, num_samples=16, horizon=4, seed=[1, 2, 3], num_robots=2)
    with pytest.raises(TypeError, match="seed must be an int or None"):
        MPPI(DUBINS, goal_cost, num_samples=16, horizon=4, seed="7", num_robots=2)


def test_a_batched_cost_of_the_wrong_shape_names_the_shape():
    def flat(states, actions):
        return states[..., -1, 0].reshape(-1)

    flat.batched = True  # type: ignore[attr-defined]
    with pytest.raises(ValueError, match=r"expected a \[2, 16\] tensor"):
        MPPI(DUBINS, flat, num_samples=16, horizon=4, num_robots=2).command(torch.zeros(2, 3))


# ------------------------------------------------------------------------------------------ a table set

def test_a_table_set_gives_each_robot_its_nearest_member(tmp_path):
    """ks_speed members at 0, 0.5 and 1 m/s; three robots at 0.1, 0.9 and 0.45 m/s choose three members."""
    from precompute.build import main

    assert main(["--system", "ks_speed", "--horizon", "3", "--quiet", "--starts", "3=0:1:3",
                 "--out", str(tmp_path / "set")]) == 0
    many = load_table(tmp_path / "set")
    starts = torch.tensor([[0.0, 0.0, 0.0, 0.1], [1.0, 0.5, 0.3, 0.9], [-1.0, 0.0, 2.0, 0.45]])
    assert many.nearest(starts)[0].tolist() == [0, 2, 1]

    def cost(states, actions):
        return states[:, -1, 0].square() + states[:, -1, 1].square()

    _same_as_alone(lambda seed, n: CUniformMPPI(many, cost, num_samples=32, seed=seed, num_robots=n), starts,
                   steps=2)


# ------------------------------------------------------------------------------------------ a map policy

MAP_SYSTEM = make_system("dubins", speed=1.0, dt=0.2, num_actions=5, max_omega=math.pi / 2,
                         cell_size=[0.1, 0.1, 2 * math.pi / 16])
SPEC = PatchSpec((24, 24), 0.1, (-1.2, -1.2))


def _map_policy() -> MapPolicy:
    torch.manual_seed(0)
    config = MapPolicyConfig(state_dim=3, num_actions=5, horizon=4, periodic=[False, False, True],
                             feature_scale=[0.8, 0.6, 1.0], patch=SPEC.to_dict(), hidden=32, layers=2, embed=8,
                             channels=4)
    return MapPolicy(config, MAP_SYSTEM, MAP_SYSTEM.action_set()).eval()


def test_cfu_mppi_batched_senses_a_map_per_robot_and_equals_alone():
    occ = torch.zeros((60, 60), dtype=torch.bool)
    occ[25:35, 30:34] = True  # a wall one robot sees and the others do not
    world = OccupancyGrid(occ, (-3.0, -3.0), 0.1)
    policy = _map_policy()

    def cost(states, actions):
        hit = world.contains(states[:, 1:, :2]).any(dim=1)
        return (states[:, -1, :2] - torch.tensor([3.0, 0.0])).square().sum(dim=1) + 1e3 * hit

    starts = torch.tensor([[0.0, 0.0, 0.0], [-2.0, 2.0, 1.0], [1.5, -2.0, -0.5]])
    encodes = policy.encodes
    _same_as_alone(lambda seed, n: CFUMPPI(policy, world, cost, num_samples=32, seed=seed, num_robots=n), starts,
                   steps=2)
    assert policy.encodes - encodes == 2 + 3 * 2  # one encoding per command: of all 3 patches, or of its own


# ------------------------------------------------------------------------------------------ host syncs

class _SyncCounter:
    """Counts the Tensor methods that read a value to the host (on CUDA each waits for the device)."""

    NAMES = ("item", "tolist", "__bool__", "__int__", "__float__", "__index__", "numpy")

    def __init__(self, monkeypatch):
        self.calls: list[str] = []
        self.originals = {name: getattr(torch.Tensor, name) for name in self.NAMES}
        for name, original in self.originals.items():
            monkeypatch.setattr(torch.Tensor, name, self._counting(name, original))

    def _counting(self, name, original):
        def counted(tensor, *args, **kwargs):
            self.calls.append(name)
            return original(tensor, *args, **kwargs)
        return counted


@pytest.mark.parametrize("kind", ["mppi", "log_mppi", "cuniform_torch_kernel", "cumppi_torch_kernel"])
def test_a_plan_reads_nothing_back_to_the_host_when_debug_is_off(dubins_table, monkeypatch, kind):
    """With ``debug=False`` (the default on CUDA) a command is a tensor program: no value read back per command,
    for one robot and for a batch. The table's torch kernel is the device path (the numba kernel is CPU-only)."""
    from cuniform_torch.policies.table import Kernel
    from cuniform_torch.sampling import kernels as frame_kernels

    table = TablePolicy(dubins_table, kernel=Kernel.TORCH)
    # the compiled frame change is a CPU loop over numpy views (never taken on a device): the torch ops instead
    monkeypatch.setattr(frame_kernels, "usable", lambda x: False)
    make = {
        "mppi": lambda n: MPPI(DUBINS, goal_cost, num_samples=32, horizon=6, seed=0, num_robots=n, debug=False),
        "log_mppi": lambda n: LogMPPI(DUBINS, goal_cost, num_samples=32, horizon=6, seed=0, num_robots=n,
                                      debug=False),
        "cuniform_torch_kernel": lambda n: CUniformMPPI(table, goal_cost, num_samples=32, seed=0, num_robots=n,
                                                        debug=False),
        "cumppi_torch_kernel": lambda n: CUMPPI(table, goal_cost, num_samples=32, seed=0, num_robots=n,
                                                debug=False),
    }[kind]
    for n, states in ((1, STARTS[1]), (3, STARTS)):
        ctrl = make(n)
        ctrl.command(states)  # warm: anything done once (a first lookup, a cache) is not per command
        counter = _SyncCounter(monkeypatch)
        ctrl.command(states)
        ctrl.plan(states)
        for name in counter.NAMES:
            monkeypatch.setattr(torch.Tensor, name, counter.originals[name])
        assert counter.calls == [], f"{kind} with {n} robots read {counter.calls} back per command"


# ------------------------------------------------------------------------------------------ on a CUDA device

CUDA = torch.cuda.is_available()


@pytest.mark.gpu
@pytest.mark.skipif(not CUDA, reason="needs a CUDA device")
@pytest.mark.parametrize("kind", ["mppi", "log_mppi", "cuniform", "cumppi"])
def test_on_cuda_a_batched_command_never_waits_for_the_device(dubins_table, kind):
    """``torch.cuda.set_sync_debug_mode("error")`` raises on any synchronizing call: a command (default debug off
    on CUDA) makes none, for 1 robot and for 64; and batched = alone there too."""
    table = TablePolicy(dubins_table, device="cuda")
    make = {
        "mppi": lambda seed, n: MPPI(DUBINS, goal_cost_cuda, num_samples=256, horizon=10, device="cuda", seed=seed,
                                     num_robots=n),
        "log_mppi": lambda seed, n: LogMPPI(DUBINS, goal_cost_cuda, num_samples=256, horizon=10, device="cuda",
                                            seed=seed, num_robots=n),
        "cuniform": lambda seed, n: CUniformMPPI(table, goal_cost_cuda, num_samples=256, seed=seed, num_robots=n),
        "cumppi": lambda seed, n: CUMPPI(table, goal_cost_cuda, num_samples=256, seed=seed, num_robots=n),
    }[kind]
    starts = STARTS.cuda()
    for n, states in ((1, starts[0]), (64, starts[torch.arange(64) % 3])):
        ctrl = make(list(range(n)) if n > 1 else 0, n)
        ctrl.command(states)  # the first command may set things up
        torch.cuda.synchronize()
        torch.cuda.set_sync_debug_mode("error")
        try:
            for _ in range(3):
                ctrl.command(states)
        finally:
            torch.cuda.set_sync_debug_mode("default")
    _same_as_alone(make, starts, SEEDS, steps=3, atol=1e-4)


GOAL_CUDA = GOAL.cuda() if CUDA else GOAL


def goal_cost_cuda(states: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
    return (states[..., 1:, :2] - GOAL_CUDA).square().sum(dim=-1).sum(dim=-1)  # no copy to the device per call


def test_cuda_graph_needs_a_cuda_device_and_no_bank(table):
    with pytest.raises(ValueError, match="cuda_graph=True needs a CUDA device"):
        MPPI(DUBINS, goal_cost, num_samples=16, horizon=4, cuda_graph=True)
    with pytest.raises(ValueError, match="cuda_graph: a proposal bank"):
        CUniformMPPI(table, goal_cost, num_samples=16, bank_size=32, cuda_graph=True)


@pytest.mark.gpu
@pytest.mark.skipif(not CUDA, reason="needs a CUDA device")
@pytest.mark.parametrize("kind", ["mppi", "log_mppi", "cuniform", "cumppi", "cumppi_pipe", "mppi_navigation"])
def test_on_cuda_a_graphed_command_is_the_eager_command(dubins_table, kind):
    """``cuda_graph=True``: the first command is captured and every later one replayed; seeded alike, the replays
    command what eager commands do (the registered streams advance as eager draws do), for 1 and for 8 robots."""
    from cuniform_torch.envs import Circle, Environment, NavigationCost

    table = TablePolicy(dubins_table, device="cuda")
    nav = NavigationCost(Environment([Circle((1.0, 0.5), 0.3), Circle((0.5, -0.5), 0.2)]), (2.0, 1.0))
    make = {
        "mppi": lambda seed, n, g: MPPI(DUBINS, goal_cost_cuda, num_samples=256, horizon=10, device="cuda",
                                        seed=seed, num_robots=n, cuda_graph=g),
        "log_mppi": lambda seed, n, g: LogMPPI(DUBINS, goal_cost_cuda, num_samples=256, horizon=10, device="cuda",
                                               seed=seed, num_robots=n, cuda_graph=g),
        "cuniform": lambda seed, n, g: CUniformMPPI(table, goal_cost_cuda, num_samples=256, seed=seed, num_robots=n,
                                                    cuda_graph=g),
        "cumppi": lambda seed, n, g: CUMPPI(table, goal_cost_cuda, num_samples=256, seed=seed, num_robots=n,
                                            cuda_graph=g),
        "cumppi_pipe": lambda seed, n, g: CUMPPI(table, goal_cost_cuda, num_samples=256, seed=seed, num_robots=n,
                                                 cuda_graph=g, pipelined=True),
        "mppi_navigation": lambda seed, n, g: MPPI(DUBINS, nav, num_samples=256, horizon=10, device="cuda",
                                                   seed=seed, num_robots=n, cuda_graph=g),
    }[kind]
    starts = STARTS.cuda()
    for n, states in ((1, starts[0]), (8, starts[torch.arange(8) % 3])):
        seed = 0 if n == 1 else list(range(n))
        eager = _drive(make(seed, n, False), states, 5)
        graphed = _drive(make(seed, n, True), states, 5)
        for e, g in zip(eager, graphed):
            torch.testing.assert_close(g, e, atol=1e-4, rtol=0)
