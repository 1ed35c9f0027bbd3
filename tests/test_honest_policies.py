"""Honest policies: a table or MLP says where it is valid (start, cells per level), counts what is outside and
answers it by the documented fallback, never silently confident (issue 17, items 3 and 5)."""

from __future__ import annotations

import math
import warnings

import pytest
import torch

from cuniform_torch import CUniformMPPI, TablePolicy, load_policy, make_system, rollout
from cuniform_torch.grid.cells import Grid
from cuniform_torch.policies import MLPConfig, MLPPolicy, MLPSupport, PolicyCheckpointError
from cuniform_torch.policies.checkpoint import policy_checkpoint
from cuniform_torch.policies.mlp import default_feature_scale
from cuniform_torch.sampling import StartMismatchWarning
from cuniform_torch.sampling.rollout import RolloutPlan
from cuniform_torch.systems import se2_invariance_gap, system_to_json
from precompute.flow.builder import BuildConfig, build_table

KS_SPEED_SMALL = dict(cell_size=(0.2, 0.2, 2 * math.pi / 18, 0.2), num_steer=3)


def _no_start_warning(fn) -> None:
    """Run ``fn`` and fail on any StartMismatchWarning it gives."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        fn()
    assert not [w for w in caught if issubclass(w.category, StartMismatchWarning)], [str(w.message) for w in caught]


def _start_warnings(fn) -> list[str]:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        fn()
    return [str(w.message) for w in caught if issubclass(w.category, StartMismatchWarning)]


def _mlp(table, support: bool = False, fallback: str = "nearest") -> MLPPolicy:
    """A small untrained MLP over ``table`` whose logits are confident (one action gets almost all the mass)."""
    system = table.make_system()
    grid = Grid.of(system)
    centres = grid.centers(torch.from_numpy(table.cells))
    config = MLPConfig(state_dim=grid.dim, num_actions=table.actions.shape[0], horizon=table.horizon,
                       periodic=list(grid.periodic), feature_scale=default_feature_scale(centres, grid),
                       hidden=8, layers=1)
    sup = MLPSupport(torch.from_numpy(table.cells), torch.from_numpy(table.level_offsets)) if support else None
    model = MLPPolicy(config, system, torch.from_numpy(table.actions), support=sup, fallback=fallback).eval()
    with torch.no_grad():
        model.net[-1].bias.zero_()
        model.net[-1].bias[0] = 20.0  # confident everywhere: what the issue saw outside the table
    return model


def _entropy(probs: torch.Tensor) -> torch.Tensor:
    return -(probs * probs.clamp_min(1e-30).log()).sum(dim=1)


# ---- a table from a start it was not built for

def test_wrong_start_table_warns_once_with_the_miss_rate(walk_table):
    policy = TablePolicy(walk_table)
    system = policy.system
    far = torch.tensor([50.0])
    messages = _start_warnings(lambda: rollout(system, policy, far, 200, 8, torch.Generator().manual_seed(0)))
    assert len(messages) == 1
    assert "1.000 (1600 of 1600 lookups)" in messages[0] and "[0.0]" in messages[0] and "[50.0]" in messages[0]
    assert "not SE(2)-invariant" in messages[0] and "Your own robot" in messages[0]
    assert policy.miss_rate == 1.0
    # once per policy object: later rollouts from other wrong starts stay silent; a new policy warns again
    _no_start_warning(lambda: [rollout(system, policy, torch.tensor([s]), 50, 8) for s in (50.0, -30.0)])
    assert len(_start_warnings(lambda: rollout(system, TablePolicy(walk_table), far, 10, 8))) == 1


def test_wrong_start_warns_through_the_controller(walk_table):
    policy = TablePolicy(walk_table)
    mppi = CUniformMPPI(policy, lambda states, actions: states[..., 0].abs().sum(dim=1), num_samples=64, seed=0)
    _no_start_warning(lambda: mppi.command(torch.tensor([0.0])))
    messages = _start_warnings(lambda: mppi.command(torch.tensor([40.0])))
    assert len(messages) == 1 and "1.000" in messages[0]


def test_no_warning_from_the_build_start_cell(walk_table):
    policy = TablePolicy(walk_table)
    system = policy.system
    _no_start_warning(lambda: [rollout(system, policy, torch.tensor([x]), 50, 8) for x in (0.0, 0.01, -0.01)])
    _no_start_warning(lambda: rollout(system, policy, torch.zeros(20, 1), 20, 8))  # one start per sample
    assert policy.miss_rate == 0.0


def test_dubins_never_warns_from_any_pose(dubins_table):
    policy = TablePolicy(dubins_table)
    system = policy.system
    poses = torch.tensor([[0.0, 0.0, 0.0], [5.0, -3.0, 2.0], [-40.0, 12.0, -3.1]])
    _no_start_warning(lambda: [rollout(system, policy, p, 100, 10) for p in poses])
    _no_start_warning(lambda: rollout(system, policy, poses[[1, 2]].repeat(50, 1), 100, 10))  # batched starts


def test_ks_speed_warns_for_another_speed_not_another_pose():
    """SE(2)-relative, the frame change moves the pose but not the speed: a start at another speed is a wrong
    start for a table built at rest."""
    table, _ = build_table(make_system("ks_speed", **KS_SPEED_SMALL), BuildConfig(horizon=3))
    policy = TablePolicy(table)
    system = policy.system
    _no_start_warning(lambda: rollout(system, policy, torch.tensor([3.0, -1.0, 2.0, 0.0]), 50, 3))
    messages = _start_warnings(lambda: rollout(system, policy, torch.tensor([3.0, -1.0, 2.0, 1.0]), 50, 3))
    assert len(messages) == 1 and "after (x, y, theta)" in messages[0]


# ---- start_relative only where it holds

def test_start_relative_only_on_se2_invariant_systems(walk_table, dubins_table):
    walk, dubins = TablePolicy(walk_table), TablePolicy(dubins_table)
    assert walk.start_relative is False and dubins.start_relative is True
    assert _mlp(walk_table).start_relative is False and _mlp(dubins_table).start_relative is True
    assert not RolloutPlan.of(walk.system, walk).relative and RolloutPlan.of(dubins.system, dubins).relative


# ---- the MLP knows its support

def test_mlp_without_support_falls_back_outside_the_table_box(walk_table):
    model = _mlp(walk_table, fallback="uniform")
    A = model.actions.shape[0]
    inside = torch.tensor([[0.0], [0.3]])
    outside = torch.tensor([[50.0], [-80.0], [float("nan")]])
    assert float(_entropy(model.action_probs(inside, 3)).max()) < 0.01  # the confident network, inside
    probs = model.action_probs(outside, 3)
    torch.testing.assert_close(_entropy(probs), torch.full((3,), math.log(A)))
    assert model.queries == 5 and int(model.misses) == 3 and model.miss_rate == pytest.approx(0.6)
    model.reset_counters()
    assert model.queries == 0 and int(model.misses) == 0


def test_mlp_rollout_from_a_wrong_start_warns_and_misses(walk_table):
    model = _mlp(walk_table)
    messages = _start_warnings(lambda: rollout(model.system, model, torch.tensor([50.0]), 100, 8))
    assert len(messages) == 1 and "MLP policy" in messages[0] and "1.000 (800 of 800 lookups)" in messages[0]


def test_mlp_exact_support_from_a_checkpoint_counts_cells_outside_the_level(walk_table):
    """Level 1 of the walk (the cells one step reaches), exact support read from a checkpoint dict: a cell three
    beyond L_1 lies in the box of all levels (the box calls it inside) but is a miss; one beyond is a nearest
    hit with ``fallback="nearest"``, a miss with ``"uniform"``."""
    system = walk_table.make_system()
    ckpt = policy_checkpoint(_mlp(walk_table, support=True), system_to_json(system, walk_table.horizon))
    assert set(ckpt["support"]) == {"cells", "level_offsets"}
    grid = Grid.of(system)
    level = torch.from_numpy(walk_table.cells[walk_table.level(1)])  # [n, 1]
    far_cell = level.max() + 3  # in the box of all levels, not within one cell of L_1
    x_far = grid.centers(far_cell.view(1, 1)).float()
    assert int(_mlp(walk_table).support_codes(x_far, 1)[0]) == 0  # the box calls it inside
    for fallback, nearest_hits in (("uniform", 0), ("nearest", 1)):
        model = load_policy(ckpt, fallback=fallback)
        near = grid.centers((level.max() + 1).view(1, 1)).float()  # one cell beyond L_1
        x = torch.cat((grid.centers(level[:1]).float(), near, x_far))  # [3, 1]
        probs = model.action_probs(x, 1)
        assert model.queries == 3 and int(model.nearest_hits) == nearest_hits
        assert int(model.misses) == 3 - 1 - nearest_hits
        torch.testing.assert_close(_entropy(probs[-1:]), torch.tensor([math.log(model.actions.shape[0])]))
        assert float(_entropy(probs[:1])) < 0.01


def test_mlp_checkpoint_with_a_bad_support_is_refused(walk_table):
    system = walk_table.make_system()
    ckpt = policy_checkpoint(_mlp(walk_table, support=True), system_to_json(system, walk_table.horizon))
    ckpt["support"] = dict(ckpt["support"], level_offsets=ckpt["support"]["level_offsets"][:-1])
    with pytest.raises(PolicyCheckpointError, match="support level_offsets must be an int64"):
        load_policy(ckpt)


# ---- se2_invariance_gap on a system without a pose

def test_se2_invariance_gap_needs_a_pose():
    with pytest.raises(ValueError, match=r"'random_walk_1d' has 1 state dimension.*\(x, y, theta, \.\.\.\)"):
        se2_invariance_gap(make_system("random_walk_1d"))
    assert se2_invariance_gap(make_system("dubins")) < 1e-9
