"""A user system's ``step`` gets ordinary contiguous ``[N, d]`` states; column-major ones (a CPU speed trick of
``rollout``) only go to a ``step`` whose class opts in (``column_major_ok = True``, as the built-in models do)."""

from __future__ import annotations

import dataclasses
import math

import torch

from cuniform_torch import MPPI, TablePolicy, rollout
from cuniform_torch.envs import Environment, NavigationCost
from cuniform_torch.sampling.rollout import steps_column_major
from cuniform_torch.systems import Dubins


@dataclasses.dataclass(frozen=True)
class ViewingCar(Dubins):
    """Dubins dynamics written the way a newcomer might: ``x.view`` needs a contiguous tensor."""

    seen: list = dataclasses.field(default_factory=list, compare=False, repr=False)

    def step(self, x, u):
        self.seen.append(x.is_contiguous())
        flat = x.view(-1)  # raises on a column-major [N, d] tensor
        n = flat.shape[0] // 3
        theta = torch.remainder(flat[2::3] + u[:, 0] * self.dt + math.pi, 2 * math.pi) - math.pi
        return torch.stack((flat[0::3] + self.speed * self.dt * theta.cos(),
                            flat[1::3] + self.speed * self.dt * theta.sin(), theta), 1).reshape(n, 3)


def test_only_opted_in_steps_get_column_major_states():
    assert steps_column_major(Dubins()) and not steps_column_major(ViewingCar())


def test_a_users_step_gets_contiguous_states_in_every_rollout(dubins_table):
    car = ViewingCar()
    policy = TablePolicy(dubins_table)
    states, _ = rollout(car, policy, torch.tensor([0.5, -0.2, 0.3]), num_samples=64, horizon=5)
    reference, _ = rollout(Dubins(), policy, torch.tensor([0.5, -0.2, 0.3]), num_samples=64, horizon=5,
                           generator=torch.Generator().manual_seed(1))
    assert states.shape == reference.shape == (64, 6, 3)
    MPPI(car, NavigationCost(Environment([]), goal=(2.0, 0.0)), num_samples=64, horizon=5, seed=0).command(
        torch.zeros(3))  # the Gaussian proposal's open-loop rollout
    # 5 steps of each rollout, plus the 2 steps of the one construction probe (check_dynamics: cached afterwards)
    assert len(car.seen) == 12 and all(car.seen), "a step that did not opt in got a column-major state"


def test_the_same_states_whichever_layout(dubins_table):
    """The plain layout changes nothing but speed: the states equal the column-major path's, bit for bit."""
    policy = TablePolicy(dubins_table)
    x0 = torch.tensor([0.5, -0.2, 0.3])

    class PlainDubins(Dubins):  # same step, not opted in (a subclass that overrides step)
        def step(self, x, u):
            assert x.is_contiguous()
            return Dubins.step(self, x, u)

    a, ua = rollout(Dubins(), policy, x0, 128, 6, generator=torch.Generator().manual_seed(3))
    b, ub = rollout(PlainDubins(), policy, x0, 128, 6, generator=torch.Generator().manual_seed(3))
    assert torch.equal(ua, ub) and torch.equal(a, b)
