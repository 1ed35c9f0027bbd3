"""Batch invariance: a robot's commands in a batch of B are, bit for bit, its commands as a controller of one robot.

Closed loops amplify a last-bit difference into another trajectory, so lockstep evaluation (``eval.navigate
--lockstep``) and any batched deployment need equality, not closeness. Each controller of the family (MPPI,
log-MPPI, C-Uniform MPPI on a table and on a table set, CU-MPPI, CFU-MPPI) drives B = 5 robots from different
starts with different seeds for 20 commands; 5 controllers of one robot, seeded alike, must command the same bits.
The two places where a robot's arithmetic used to depend on B are tested directly too: the core's weighted average
and the rollouts' change to the world frame (compiled and torch paths).
"""

from __future__ import annotations

import math

import pytest
import torch

from cuniform_torch import CUMPPI, MPPI, CUniformMPPI, LogMPPI, TablePolicy, load_table, make_system
from cuniform_torch.common.frames import se2_to_world
from cuniform_torch.controllers.cfu import CFUMPPI
from cuniform_torch.controllers.core import weighted_average
from cuniform_torch.envs import OccupancyGrid
from cuniform_torch.maps.encoder import PatchSpec
from cuniform_torch.maps.policy import MapPolicy, MapPolicyConfig
from cuniform_torch.sampling import kernels
from cuniform_torch.tables import cpu_kernels

DUBINS = make_system("dubins")
GOAL = torch.tensor([2.0, 1.0])
STARTS = torch.tensor([[0.0, 0.0, 0.0], [0.5, -0.3, 1.0], [-0.2, 0.4, -2.0], [1.0, 1.5, 2.5], [-1.0, -0.5, 0.3]])
SEEDS = [3, 11, 40, 7, 123]
COMMANDS = 20
NUMBA = pytest.mark.skipif(not cpu_kernels.available(), reason="needs numba (the compiled frame change)")


def goal_cost(states: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
    """Squared distance to GOAL summed over the horizon: ``[N, T+1, d]`` -> ``[N]``."""
    return (states[..., 1:, :2] - GOAL).square().sum(dim=-1).sum(dim=-1)


def _drive(controller, states: torch.Tensor) -> torch.Tensor:
    """``COMMANDS`` commands in closed loop from ``states [B, d]`` (or ``[d]``): ``[COMMANDS, B, q]`` (or
    ``[COMMANDS, q]``); each state is stepped by its own command."""
    out = []
    for _ in range(COMMANDS):
        u = controller.command(states)
        out.append(u)
        x, a = (states, u) if states.ndim == 2 else (states[None], u[None])
        nxt = controller.system.step(x, a)
        states = nxt if states.ndim == 2 else nxt[0]
    return torch.stack(out)


def _assert_batch_invariant(make, starts: torch.Tensor = STARTS) -> None:
    """``make(seeds, B)`` over the starts commands, bit for bit, what ``make(seed, 1)`` commands per start."""
    batched = _drive(make(SEEDS, len(SEEDS)), starts)  # [C, B, q]
    for b, seed in enumerate(SEEDS):
        alone = _drive(make(seed, 1), starts[b])  # [C, q]
        differ = (batched[:, b] != alone).any(dim=-1).nonzero()
        assert differ.numel() == 0, (f"robot {b}: its commands in a batch of {len(SEEDS)} differ from its commands "
                                     f"alone from command {differ[0].item()} on (max abs diff "
                                     f"{(batched[:, b] - alone).abs().max().item():.3g})")


@pytest.fixture(scope="module")
def table():
    """A 15-level Dubins table: T*q = 15, where a float32 bmm rounds a robot's average by B."""
    from precompute.flow.builder import BuildConfig, build_table

    return TablePolicy(build_table(DUBINS, BuildConfig(horizon=15))[0])


@pytest.fixture(scope="module")
def table_set(tmp_path_factory):
    """ks_speed members at 0, 0.5 and 1 m/s (3 steps)."""
    from precompute.build import main

    folder = tmp_path_factory.mktemp("set") / "set"
    assert main(["--system", "ks_speed", "--horizon", "3", "--quiet", "--starts", "3=0:1:3", "--out", str(folder)]) == 0
    return load_table(folder)


@pytest.mark.parametrize("cls", [MPPI, LogMPPI])
def test_gaussian_controllers(cls):
    # T*q = 30, where a float32 bmm rounds a robot's average by B (BLAS blocking; seen at K = 32..1024)
    _assert_batch_invariant(lambda seed, n: cls(DUBINS, goal_cost, num_samples=64, horizon=15, noise_std=0.5,
                                                seed=seed, num_robots=n))


@pytest.mark.parametrize("frame", ["compiled", "torch"])
def test_cuniform_on_a_table(table, frame, monkeypatch):
    if frame == "compiled" and not cpu_kernels.available():
        pytest.skip("needs numba (the compiled frame change)")
    if frame == "torch":  # the device path (no numba, or not a CPU): torch ops, the same for one start and many
        monkeypatch.setattr(kernels, "usable", lambda x: False)
    _assert_batch_invariant(lambda seed, n: CUniformMPPI(table, goal_cost, num_samples=64, seed=seed, num_robots=n))


def test_cuniform_on_a_table_set_whose_robots_use_different_members(table_set):
    starts = torch.tensor([[0.0, 0.0, 0.0, 0.1], [1.0, 0.5, 0.3, 0.9], [-1.0, 0.0, 2.0, 0.45],
                           [0.3, -0.8, -1.0, 0.0], [-0.5, 1.0, 1.5, 0.7]])
    assert len(set(table_set.nearest(starts)[0].tolist())) == 3

    def cost(states, actions):
        return states[:, -1, 0].square() + states[:, -1, 1].square()

    _assert_batch_invariant(lambda seed, n: CUniformMPPI(table_set, cost, num_samples=32, seed=seed, num_robots=n),
                            starts)


@pytest.mark.parametrize("pipelined", [False, True])
def test_cumppi(table, pipelined):
    _assert_batch_invariant(lambda seed, n: CUMPPI(table, goal_cost, num_samples=64, seed=seed, num_robots=n,
                                                   pipelined=pipelined))


def test_cfu_mppi_sensing_a_map_per_robot():
    system = make_system("dubins", speed=1.0, dt=0.2, num_actions=5, max_omega=math.pi / 2,
                         cell_size=[0.1, 0.1, 2 * math.pi / 16])
    torch.manual_seed(0)
    config = MapPolicyConfig(state_dim=3, num_actions=5, horizon=15, periodic=[False, False, True],
                             feature_scale=[0.8, 0.6, 1.0], patch=PatchSpec((24, 24), 0.1, (-1.2, -1.2)).to_dict(),
                             hidden=32, layers=2, embed=8, channels=4)
    policy = MapPolicy(config, system, system.action_set()).eval()
    occ = torch.zeros((60, 60), dtype=torch.bool)
    occ[25:35, 30:34] = True  # a wall some robots see and others do not
    world = OccupancyGrid(occ, (-3.0, -3.0), 0.1)

    def cost(states, actions):
        hit = world.contains(states[:, 1:, :2]).any(dim=1)
        return (states[:, -1, :2] - torch.tensor([3.0, 0.0])).square().sum(dim=1) + 1e3 * hit

    # a high temperature: many samples weigh in a robot's average (with one weight near 1 any order of sums agrees)
    _assert_batch_invariant(lambda seed, n: CFUMPPI(policy, world, cost, num_samples=64, lambda_=100.0, seed=seed,
                                                    num_robots=n))


# ------------------------------------------------------------------------------------------ the two sources

@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_weighted_average_of_a_robot_does_not_depend_on_the_batch(dtype):
    """The core's average of K sequences by the weights: robot i's nominal in a batch of B = 3, 40, 64 is the
    bits of robot i alone (T*q = 15: a float32 bmm rounds robots 1, 2, 3, ... of a batch unlike one robot)."""
    make = lambda seed, n: MPPI(DUBINS, goal_cost, num_samples=256, horizon=15, seed=seed,  # noqa: E731
                                num_robots=n, dtype=dtype)
    starts = torch.randn(64, 3, generator=torch.Generator().manual_seed(0), dtype=dtype)
    alone = {i: make(i, 1).plan(starts[i]).nominal for i in (0, 1, 2, 39, 63)}  # [T, q] each
    for b in (3, 40, 64):
        nominal = make(list(range(b)), b).plan(starts[:b]).nominal  # [B, T, q]
        for i in (i for i in alone if i < b):
            assert torch.equal(nominal[i], alone[i]), f"robot {i}'s average differs in a batch of {b} from alone"


@pytest.mark.parametrize("threads", [1, 4])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_weighted_average_gives_each_robot_its_bits_alone_for_any_batch(dtype, threads):
    """``weighted_average`` over a grid: B = 3, 40, 64, K = 16..4096, T*q = 1..60 (float32 T*q = 15 and 30 are where
    a bmm rounds by B), with 1 and 4 torch threads (a reduction split across threads could change the order)."""
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        for k, (t, q) in ((16, (15, 1)), (256, (15, 2)), (1024, (1, 1)), (1024, (30, 2)), (4096, (15, 1))):
            g = torch.Generator().manual_seed(k * t * q)
            weights = torch.softmax(torch.randn(64, k, generator=g, dtype=dtype), dim=1)  # [64, K]
            actions = torch.randn(64, k, t, q, generator=g, dtype=dtype)  # [64, K, T, q]
            alone = torch.cat([weighted_average(weights[i:i + 1], actions[i:i + 1]) for i in range(64)])
            for b in (3, 40, 64):
                assert torch.equal(weighted_average(weights[:b], actions[:b]), alone[:b]), (k, t, q, b)
    finally:
        torch.set_num_threads(before)


@NUMBA
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_compiled_frame_change_moves_each_robots_samples_as_it_moves_them_alone(dtype):
    """Per-robot poses ``[B, d]`` (or the ``[B*K, d]`` start rows) move robot b's K samples to the bits that its
    pose alone gives them, in both output layouts; within float rounding of the torch path."""
    g = torch.Generator().manual_seed(1)
    b, k, steps, d = 7, 33, 6, 4
    local = torch.randn(b * k, steps, d, generator=g, dtype=dtype).permute(1, 2, 0)  # [T+1, d, N]
    poses = torch.randn(b, d, generator=g, dtype=dtype) * 3
    world = kernels.to_world(local, poses)  # [N, T+1, d]
    alone = torch.cat([kernels.to_world(local[..., i * k:(i + 1) * k], poses[i]) for i in range(b)])
    assert torch.equal(world, alone)
    assert torch.equal(world, kernels.to_world(local, poses.repeat_interleave(k, dim=0)))
    assert torch.equal(world, kernels.to_world_time_major(local.contiguous(), poses).permute(2, 0, 1))
    torch.testing.assert_close(world, se2_to_world(local.permute(2, 0, 1), poses.repeat_interleave(k, 0)[:, None]))
    with pytest.raises(ValueError, match="the number of poses must divide the samples"):
        kernels.to_world(local, poses[:5])


def test_a_bank_moves_each_robots_subset_as_it_moves_it_alone(table):
    """A proposal bank's batch: robot b's subset of the origin rollouts (drawn from its stream) moved to its pose
    is the bits of that robot alone (the bank's proposals are compared: a batch shares one bank, drawn from robot
    0's stream, so a controller of robot b alone draws another bank)."""
    from cuniform_torch.controllers.streams import RobotStreams

    bank = CUniformMPPI(table, goal_cost, num_samples=64, bank_size=256, seed=0).proposal
    states, actions = bank.propose_batch(STARTS, RobotStreams.seeded(SEEDS, "cpu"))  # [B, K, T+1, d], [B, K, T, q]
    for b, seed in enumerate(SEEDS):
        alone = bank.propose_batch(STARTS[b:b + 1], RobotStreams.seeded([seed], "cpu"))
        assert torch.equal(alone[1][0], actions[b]), f"robot {b}: another subset"
        assert torch.equal(alone[0][0], states[b]), f"robot {b}: its subset is moved to its pose with other bits"
