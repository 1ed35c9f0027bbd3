"""CU-MPPI's lean first stage: ``CUniformMPPI._best_actions`` is ``_plan(...).best_actions()`` without the weights.

Side by side with the whole plan it replaces (the same streams, so the same draws), for one robot and a batch,
with infinite and NaN costs (capped, so ties are broken as the plan breaks them), and CU-MPPI's command no longer
runs the first stage's whole plan.
"""

from __future__ import annotations

import pytest
import torch

from cuniform_torch import CUMPPI, CUniformMPPI, TablePolicy


def _cost(states: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
    """Squared distance to (1, 0) over the horizon; inf for rollouts that end left of x = 0.05, NaN above
    y = 0.15 (non-finite costs the plan caps)."""
    c = ((states[:, :, 0] - 1.0) ** 2 + states[:, :, 1] ** 2).sum(dim=1)
    c = torch.where(states[:, -1, 0] < 0.05, torch.inf, c)
    return torch.where(states[:, -1, 1] > 0.15, torch.nan, c)


@pytest.mark.parametrize("robots", [1, 3])
@pytest.mark.parametrize("terminal", [False, True])
def test_best_actions_are_the_plans(dubins_table, robots, terminal):
    policy = TablePolicy(dubins_table)
    terminal_cost = (lambda x: x[:, 1].abs()) if terminal else None
    ctrl = CUniformMPPI(policy, _cost, num_samples=48, lambda_=0.0, terminal_cost=terminal_cost, seed=5,
                        num_robots=robots)
    states = torch.tensor([[0.0, 0.0, 0.0], [0.1, -0.1, 0.5], [-0.2, 0.1, -1.0]])[:robots]
    for _ in range(3):
        saved = [g.get_state() for g in ctrl.streams.generators]
        plan = ctrl._plan(states)
        for g, s in zip(ctrl.streams.generators, saved):
            g.set_state(s)
        lean = ctrl._best_actions(states)
        assert lean.shape == (robots, ctrl.horizon, 1)
        assert torch.equal(lean, plan.best_actions())
        assert bool((plan.costs == 1e10).any()), "the costs include capped ones (ties broken the plan's way)"


def test_cumppi_does_not_plan_its_first_stage(dubins_table):
    ctrl = CUMPPI(TablePolicy(dubins_table), _cost, num_samples=64, seed=0)

    def whole_plan(state):
        raise AssertionError("CU-MPPI's first stage ran a whole plan (weights, weighted sequence, result)")

    ctrl.cuniform._plan = whole_plan  # type: ignore[method-assign]
    u = ctrl.command(torch.zeros(3))
    assert u.shape == (1,) and bool(torch.isfinite(u).all())


def test_the_parts_benchmark_times_the_parts_it_names(dubins_table):
    """``python -m eval.bench.first_stage --parts``: each closure runs the part of its name, at its stage's K
    (K / 2 C-Uniform rollouts in stage 1, the rest in stage 2, all K for MPPI)."""
    from eval.bench.first_stage import _PARTS, _part_fns

    policy = TablePolicy(dubins_table)
    fns = _part_fns(10, policy, lambda x, u: x[:, :, 0].square().sum(dim=1), torch.zeros(3))
    assert tuple(fns) == _PARTS
    out = {name: fn() for name, fn in fns.items()}
    t = policy.horizon
    assert out["mppi proposals"][1].shape == (1, 10, t, 1) and out["mppi evaluate"][0].shape == (1, 10)
    assert out["stage 1 rollouts"][1].shape == (1, 5, t, 1) and out["stage 1 cost"].shape == (1, 5)
    assert out["stage 1"].shape == (1, t, 1)
    assert out["stage 2 proposals"][1].shape == (1, 5, t, 1) and out["stage 2 evaluate"][0].shape == (1, 5)
    assert out["mppi command"].shape == out["cumppi command"].shape == (1,)


def test_the_parts_benchmark_times_cfu_mppis_parts():
    """``--parts``' CFU-MPPI closures: a command, the sensing (one map set per call), K / 2 map-policy rollouts and
    their cost call."""
    from cuniform_torch.envs import Circle, Environment, NavigationCost
    from eval.bench.first_stage import _CFU_PARTS, _cfu_fns

    cost = NavigationCost(Environment([Circle((1.0, 0.5), 0.3)]), goal=(3.0, 0.0))
    fns = _cfu_fns(8, cost, torch.zeros(3))
    assert tuple(fns) == _CFU_PARTS
    out = {name: fn() for name, fn in fns.items()}
    assert out["cfu command"].shape == (1,) and out["cfu sense"] is None
    states, actions = out["cfu stage 1 rollouts"]
    assert states.shape[:2] == (1, 4) and actions.shape[:2] == (1, 4) and out["cfu stage 1 cost"].shape == (1, 4)
    assert actions.unique().numel() <= 7  # the map policy's discrete turn rates, not the local Gaussian pass
