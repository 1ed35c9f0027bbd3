"""The policy contract of the rollout and the controllers (issue 33 item 3): what a policy declares is read once,
into :class:`PolicyCapabilities`, when the proposal is made; a command probes the policy for nothing; the start
watch is one implementation; CFU-MPPI senses once per command and the map policy takes the maps as its input;
and every controller commands what it commanded before (batched robots against the same robots alone, seeded
alike: the rollouts bit for bit)."""

from __future__ import annotations

import math

import pytest
import torch
from torch import Tensor

from cuniform_torch import CUMPPI, MPPI, CUniformMPPI, TablePolicy, load_table, make_system
from cuniform_torch.controllers.cfu import CFUMPPI
from cuniform_torch.envs import OccupancyGrid
from cuniform_torch.maps.encoder import PatchSpec
from cuniform_torch.maps.policy import MapPolicy, MapPolicyConfig
from cuniform_torch.policies.mlp import MLPPolicy
from cuniform_torch.policies.table import UniformPolicy
from cuniform_torch.sampling import PolicyCapabilities
from cuniform_torch.sampling.start_watch import WatchesStart

DUBINS = make_system("dubins")
STARTS = torch.tensor([[0.0, 0.0, 0.0], [0.5, -0.3, 1.0], [-0.2, 0.4, -2.0]])
SEEDS = [3, 11, 40]
GOAL = torch.tensor([2.0, 1.0])


def goal_cost(states: Tensor, actions: Tensor) -> Tensor:
    """``[N, T+1, d]`` -> ``[N]``: squared distance to GOAL summed over the horizon."""
    return (states[..., 1:, :2] - GOAL).square().sum(dim=-1).sum(dim=-1)


# ------------------------------------------------------------------------------------------ no probing per command

class CountingPolicy:
    """A uniform policy with the required members only (and a system and horizon): ``__getattr__`` records each
    lookup of a name it lacks (an optional capability probed for) while ``counting`` is on."""

    def __init__(self, system, horizon: int) -> None:
        self.system, self.horizon = system, horizon
        self.actions = system.action_set()  # [A, q]
        self.probes: list[str] = []
        self.counting = False

    def action_probs(self, x: Tensor, t: int) -> Tensor:
        """Uniform ``[N, A]``."""
        return x.new_full((x.shape[0], self.actions.shape[0]), 1.0 / self.actions.shape[0])

    def __getattr__(self, name: str) -> object:
        if name.startswith("__") or name in ("probes", "counting"):
            raise AttributeError(name)
        if self.counting:
            self.probes.append(name)
        raise AttributeError(name)


class PerStartPolicy(CountingPolicy):
    """A policy set per start: ``for_start`` returns one of two members (by the sign of the start's x)."""

    def __init__(self, system, horizon: int) -> None:
        super().__init__(system, horizon)
        self.members = (CountingPolicy(system, horizon), CountingPolicy(system, horizon))

    def for_start(self, x0: Tensor) -> CountingPolicy:
        return self.members[int(float(x0[0]) > 0)]


@pytest.mark.parametrize("robots", [1, 3])
@pytest.mark.parametrize("kind", ["cuniform", "cumppi"])
def test_a_command_probes_the_policy_for_nothing(kind, robots):
    policy = CountingPolicy(DUBINS, 6)
    make = CUniformMPPI if kind == "cuniform" else CUMPPI
    ctrl = make(policy, goal_cost, num_samples=16, seed=SEEDS[:robots], num_robots=robots)
    policy.counting = True
    for _ in range(3):
        ctrl.command(STARTS[:robots] if robots > 1 else STARTS[0])
    ctrl.reset()
    ctrl.command(STARTS[:robots] if robots > 1 else STARTS[0])
    assert policy.probes == [], f"probed per command: {policy.probes}"


def test_a_member_chosen_per_start_is_read_once_the_set_never():
    """The set is read when the controller is made; each member the first time it serves, then never again."""
    policy = PerStartPolicy(DUBINS, 6)
    ctrl = CUniformMPPI(policy, goal_cost, num_samples=16, seed=SEEDS, num_robots=3)
    for p in (policy, *policy.members):
        p.counting = True
    ctrl.command(STARTS)  # robots at x = 0, 0.5, -0.2: both members serve
    assert policy.probes == []
    first = [list(m.probes) for m in policy.members]
    assert all(first), "each member's capabilities are read the first time it serves"
    for m in policy.members:
        m.probes.clear()
    for _ in range(2):
        ctrl.command(STARTS)
    assert policy.probes == [] and all(m.probes == [] for m in policy.members), \
        f"probed again: {[m.probes for m in policy.members]}"


# ------------------------------------------------------------------------------------------ the declared record

@pytest.fixture(scope="module")
def speed_set(tmp_path_factory):
    """A ks_speed table set, members at 0, 0.5 and 1 m/s (horizon 3)."""
    from precompute.build import main

    out = tmp_path_factory.mktemp("set") / "set"
    assert main(["--system", "ks_speed", "--horizon", "3", "--quiet", "--starts", "3=0:1:3", "--out", str(out)]) == 0
    return load_table(out)


def test_the_capabilities_of_the_built_in_policies(dubins_table, speed_set):
    table = TablePolicy(dubins_table)
    caps = PolicyCapabilities.of(table)
    assert caps.probs and caps.sampler and caps.draw is not None and caps.action_dim == table.actions.shape[1] == 1
    assert caps.watch_start is not None and caps.new_episode is not None and caps.fused_rollout is not None
    assert not caps.table_set and caps.member_starts is None and caps.traits.horizon == table.horizon
    uniform = PolicyCapabilities.of(UniformPolicy(DUBINS, 5))
    assert uniform.watch_start is None and uniform.new_episode is None and uniform.for_start is None
    many = PolicyCapabilities.of(speed_set)
    assert many.table_set and many.member_starts is not None and many.member_starts.shape == (3, 4)
    with pytest.raises(ValueError, match="neither a Policy"):
        PolicyCapabilities.of(object()).check(object())


def test_the_start_watch_is_written_once():
    """Tables, MLPs and map policies answer ``watch_start``, ``new_episode``, ``start_misses`` and ``build_start``
    through the one :class:`WatchesStart`; none keeps a copy of its own."""
    for cls in (TablePolicy, MLPPolicy, MapPolicy):
        assert issubclass(cls, WatchesStart)
        for name in ("watch_start", "new_episode", "start_misses", "build_start"):
            assert name not in vars(cls), f"{cls.__name__} writes its own {name}"


# ------------------------------------------------------------------------------------------ the same commands

MAP_SYSTEM = make_system("dubins", speed=1.0, dt=0.2, num_actions=5, max_omega=math.pi / 2,
                         cell_size=[0.1, 0.1, 2 * math.pi / 16])
SPEC = PatchSpec((24, 24), 0.1, (-1.2, -1.2))
MAP_STARTS = torch.tensor([[0.0, 0.0, 0.0], [-2.0, 2.0, 1.0], [1.5, -2.0, -0.5]])


def _map_policy() -> MapPolicy:
    torch.manual_seed(0)
    config = MapPolicyConfig(state_dim=3, num_actions=5, horizon=4, periodic=[False, False, True],
                             feature_scale=[0.8, 0.6, 1.0], patch=SPEC.to_dict(), hidden=32, layers=2, embed=8,
                             channels=4)
    return MapPolicy(config, MAP_SYSTEM, MAP_SYSTEM.action_set()).eval()


def _world() -> OccupancyGrid:
    occ = torch.zeros((60, 60), dtype=torch.bool)
    occ[25:35, 30:34] = True  # a wall one robot sees and the others do not
    return OccupancyGrid(occ, (-3.0, -3.0), 0.1)


def _map_cost(world: OccupancyGrid):
    def cost(states: Tensor, actions: Tensor) -> Tensor:
        hit = world.contains(states[:, 1:, :2]).any(dim=1)
        return (states[:, -1, :2] - torch.tensor([3.0, 0.0])).square().sum(dim=1) + 1e3 * hit
    return cost


def _closed_loop(ctrl, states: Tensor, steps: int) -> tuple[list[Tensor], list]:
    """``steps`` command results from ``states [B, d]``, each state stepped by its command: the states commanded
    from and the results."""
    seen, out = [], []
    for _ in range(steps):
        result = ctrl.command_result(states)
        seen.append(states)
        out.append(result)
        states = ctrl.system.step(states, result.command)
    return seen, out


def _same_as_alone(make, starts: Tensor, steps: int = 3) -> None:
    """Batched robots (``make(seeds, B)``) propose each robot's actions bit for bit as that robot alone
    (``make(seed, 1)``, commanded from the same states: the same draws, the same choices), and the same rollouts and
    commands bit for bit too (the frame change and the core's weighted sum do one arithmetic for any B)."""
    states, batched = _closed_loop(make(SEEDS, len(SEEDS)), starts, steps)
    for b, seed in enumerate(SEEDS):
        alone_ctrl = make(seed, 1)
        for t in range(steps):
            alone = alone_ctrl.command_result(states[t][b])
            assert torch.equal(batched[t].actions[b], alone.actions), f"robot {b}, command {t}: actions differ"
            assert torch.equal(batched[t].states[b], alone.states), f"robot {b}, command {t}: states differ"
            assert torch.equal(batched[t].command[b], alone.command), f"robot {b}, command {t}: commands differ"


@pytest.fixture(scope="module")
def table(dubins_table):
    return TablePolicy(dubins_table)


def test_mppi_same_commands():
    _same_as_alone(lambda s, n: MPPI(DUBINS, goal_cost, num_samples=64, horizon=8, noise_std=0.5, seed=s,
                                     num_robots=n), STARTS)


def test_cuniform_mppi_same_commands(table):
    _same_as_alone(lambda s, n: CUniformMPPI(table, goal_cost, num_samples=64, seed=s, num_robots=n), STARTS)


def test_cumppi_same_commands(table):
    _same_as_alone(lambda s, n: CUMPPI(table, goal_cost, num_samples=64, seed=s, num_robots=n), STARTS)


def test_a_table_set_same_commands(speed_set):
    many = speed_set
    starts = torch.tensor([[0.0, 0.0, 0.0, 0.1], [1.0, 0.5, 0.3, 0.9], [-1.0, 0.0, 2.0, 0.45]])
    assert many.nearest(starts)[0].tolist() == [0, 2, 1]  # three members, one rollout

    def cost(states: Tensor, actions: Tensor) -> Tensor:
        return states[:, -1, 0].square() + states[:, -1, 1].square()

    with pytest.warns():  # robots off their members' build starts: the start check says so
        _same_as_alone(lambda s, n: CUniformMPPI(many, cost, num_samples=32, seed=s, num_robots=n), starts, 2)


def test_cfu_mppi_same_commands_and_senses_once_per_command():
    policy, world = _map_policy(), _world()
    _same_as_alone(lambda s, n: CFUMPPI(policy, world, _map_cost(world), num_samples=32, seed=s, num_robots=n),
                   MAP_STARTS)
    ctrl = CFUMPPI(policy, world, _map_cost(world), num_samples=32, seed=SEEDS, num_robots=3)
    sensed: list[list[int]] = []
    sense = ctrl.sensor.sense
    ctrl.sensor.sense = lambda states: sensed.append(list(states.shape)) or sense(states)  # type: ignore[method-assign]
    encodes = policy.encodes
    for _ in range(2):
        ctrl.command(MAP_STARTS)
    assert sensed == [[3, 3], [3, 3]] and policy.encodes - encodes == 2  # once per command, all robots at once
    assert ctrl.cuniform.policy is policy  # the map policy itself is rolled out: no sensing wrapper around it
