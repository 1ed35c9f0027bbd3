"""A user system's ``step`` and ``action_set`` are probed once where a controller, proposal or rollout is made
(:func:`cuniform_torch.systems.check_dynamics`): an in-place update of ``x``, a result of another dtype (int64 as
well as float64), a shape other than ``[N, d]``, ``None`` or an ndarray, and an empty or non-tensor action set are
each one clear error naming the system and the rule, never a silently different command or a raw traceback."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from cuniform_torch import MPPI, TablePolicy, rollout
from cuniform_torch.controllers.mppi import LogMPPI
from cuniform_torch.sampling.rollout import rollout_actions
from cuniform_torch.systems import Dubins, check_dynamics


def _cost(states, actions):
    return (states[..., 0] - 1).pow(2).sum(-1) + states[..., 1].pow(2).sum(-1)


@dataclasses.dataclass(frozen=True)
class InPlace(Dubins):
    """Dubins written to update ``x`` in place (as a newcomer might): the rollouts alias each other."""

    def step(self, x, u):
        x.copy_(super().step(x, u))
        return x


@dataclasses.dataclass(frozen=True)
class Nudges(Dubins):
    """Returns a new tensor but also nudges its input: the start state of every rollout moves."""

    def step(self, x, u):
        out = super().step(x, u)
        x[:, 0] += 0.01
        return out


@dataclasses.dataclass(frozen=True)
class TouchesU(Dubins):
    def step(self, x, u):
        out = super().step(x, u)
        u.mul_(0.5)
        return out


def _returns(value_of):
    @dataclasses.dataclass(frozen=True)
    class Returns(Dubins):
        def step(self, x, u):
            return value_of(super().step(x, u))
    return Returns()


def _actions(value):
    @dataclasses.dataclass(frozen=True)
    class Acts(Dubins):
        def action_set(self, dtype=torch.float32, device=None):
            return value(dtype)
    return Acts()


CASES = [
    ("in place", InPlace(), ValueError, r"'dubins' \(InPlace\): step\(x, u\).*changed its input x in place"),
    ("nudges x", Nudges(), ValueError, r"\(Nudges\).*changed its input x in place"),
    ("changes u", TouchesU(), ValueError, r"\(TouchesU\).*changed its input u in place"),
    ("int64", _returns(lambda y: y.long()), ValueError, r"returned a \[4, 3\] tensor of torch.int64.*cast silently"),
    ("float64", _returns(lambda y: y.double()), ValueError, r"returned a \[4, 3\] tensor of torch.float64"),
    ("shape", _returns(lambda y: y[:, :2]), ValueError, r"returned a \[4, 2\] tensor.*must return \[4, 3\]"),
    ("None", _returns(lambda y: None), TypeError, r"must return a torch.Tensor \[4, 3\], got None"),
    ("ndarray", _returns(lambda y: y.numpy()), TypeError, r"must return a torch.Tensor \[4, 3\], got numpy.ndarray"),
    ("no actions", _actions(lambda dt: torch.zeros((0, 1), dtype=dt)), ValueError, r"non-empty \[A, q\]"),
    ("ndarray actions", _actions(lambda dt: np.zeros((3, 1))), TypeError, r"action_set.*got numpy.ndarray"),
    ("int actions", _actions(lambda dt: torch.tensor([[-1], [0], [1]])), ValueError, r"torch.int64.*dtype=dtype"),
    ("nan actions", _actions(lambda dt: torch.tensor([[float("nan")]], dtype=dt)), ValueError, r"finite actions"),
]


@pytest.mark.parametrize("label, system, error, match", CASES, ids=[c[0] for c in CASES])
def test_a_misbehaving_step_is_refused_where_the_controller_is_made(label, system, error, match):
    for make in (lambda: MPPI(system, _cost, num_samples=16, horizon=4, seed=0),
                 lambda: LogMPPI(system, _cost, num_samples=16, horizon=4, seed=0),
                 lambda: MPPI(system, _cost, num_samples=16, horizon=4, seed=0, num_robots=3)):
        with pytest.raises(error, match=match):
            make()


@pytest.mark.parametrize("label, system, error, match", CASES[:8], ids=[c[0] for c in CASES[:8]])
def test_a_misbehaving_step_is_refused_by_the_rollouts(label, system, error, match, dubins_table):
    with pytest.raises(error, match=match):
        rollout(system, TablePolicy(dubins_table), torch.zeros(3), 8, 3)
    with pytest.raises(error, match=match):
        rollout_actions(system, torch.zeros(3), torch.zeros((8, 3, 1)))


def test_without_the_probe_an_in_place_step_changes_the_command():
    """Why the probe exists: the same seed, the same dynamics, a different command (the proposal's rollouts alias
    one another); the probe turns that into an error at construction."""
    good = MPPI(Dubins(), _cost, num_samples=64, horizon=5, seed=0).command(torch.zeros(3))
    import cuniform_torch.controllers.core as core
    import cuniform_torch.controllers.proposals as proposals
    bad = InPlace()

    def unchecked(system, dtype, device, who=None):
        return system.action_set(dtype=dtype, device=device)

    saved = core.check_dynamics, proposals.check_dynamics
    core.check_dynamics = proposals.check_dynamics = unchecked
    try:
        silent = MPPI(bad, _cost, num_samples=64, horizon=5, seed=0).command(torch.zeros(3))
    finally:
        core.check_dynamics, proposals.check_dynamics = saved
    assert not torch.equal(good, silent)


def test_the_probe_runs_once_per_system_dtype_and_device():
    calls = []

    @dataclasses.dataclass(frozen=True)
    class Counting(Dubins):
        def step(self, x, u):
            calls.append(x.shape[0])
            return super().step(x, u)

    car = Counting()
    check_dynamics(car, torch.float32, "cpu")
    check_dynamics(car, torch.float32, "cpu")
    assert calls == [4, 4]  # two probe steps (from zeros, then from where they led), then cached
    check_dynamics(car, torch.float64, "cpu")
    assert calls == [4, 4, 4, 4]
    MPPI(car, _cost, num_samples=8, horizon=2, seed=0)  # proposal and core: both cached
    assert calls == [4, 4, 4, 4]
    check_dynamics(Counting(), torch.float32, "cpu")  # another object: probed
    assert len(calls) == 6


@pytest.mark.parametrize("name", ["dubins", "random_walk_1d", "ks", "ks_speed", "double_integrator", "mountain_car"])
def test_built_in_systems_pass(name):
    from cuniform_torch.systems import make_system
    system = make_system(name)
    for dtype in (torch.float32, torch.float64):
        assert check_dynamics(system, dtype, "cpu").dtype == dtype
