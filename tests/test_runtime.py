"""Runtime library: the table policy, rollouts and frames, noise samplers, and the MPPI family.

Shapes: N states / samples, K proposals, T horizon, d state dimensions, q action dimensions, A actions.

Everything is seeded; statistical checks state their margins next to the draw counts. Closed-loop tests use
small sample counts (256-512 proposals) and short episodes so the whole file runs in seconds on a CPU.
"""

from __future__ import annotations

import math
import threading
import time

import numpy as np
import pytest
import torch
from scipy import stats

from cuniform_torch import CUMPPI, MPPI, CUniformMPPI, LogMPPI, TablePolicy, rollout
from cuniform_torch.common.frames import se2_to_local, se2_to_world
from cuniform_torch.controllers import COST_CAP, MPPIResult, mppi_weights
from cuniform_torch.envs import Circle, Environment, NavigationCost, simulate
from cuniform_torch.sampling import GaussianSampler, NormalLogNormalSampler, lognormal_params
from cuniform_torch.systems import wrap_angle

CUDA = torch.cuda.is_available()


# ------------------------------------------------------------------------------------------------ helpers

def _gen(seed: int, device: str | torch.device = "cpu") -> torch.Generator:
    return torch.Generator(device=device).manual_seed(seed)


def _level(table, t: int) -> tuple[int, int]:
    """Table rows ``[lo, hi)`` of level ``t``."""
    return int(table.level_offsets[t]), int(table.level_offsets[t + 1])


def _uniform(policy: TablePolicy, n: int = 1) -> torch.Tensor:
    return torch.full((n, policy.num_actions), 1.0 / policy.num_actions, dtype=policy.dtype)


def _angle_close(a: torch.Tensor, b: torch.Tensor, atol: float) -> None:
    """``a`` and ``b`` equal as angles (mod 2 pi)."""
    diff = wrap_angle(a - b)
    assert float(diff.abs().max()) <= atol, f"angles differ by up to {float(diff.abs().max())}"


def _assert_states_close(a: torch.Tensor, b: torch.Tensor, atol: float = 1e-5) -> None:
    """States ``[..., 3]`` of an SE(2) system: xy close, headings close mod 2 pi."""
    torch.testing.assert_close(a[..., :2], b[..., :2], atol=atol, rtol=0)
    _angle_close(a[..., 2], b[..., 2], atol)


def _brute_nearest(cell: torch.Tensor, level_cells: torch.Tensor, num_angle_cells: tuple[int, ...]) -> int:
    """Slow reference: index (within the level) of the level cell nearest to ``cell`` in squared grid distance
    between cell indices, angle dimensions wrapped; ties to the lowest index (``torch.argmin`` keeps the first)."""
    diff = (level_cells - cell).abs()  # [L, d]
    for dim, k in enumerate(num_angle_cells):
        if k:
            diff[:, dim] = torch.minimum(diff[:, dim], k - diff[:, dim])
    return int(torch.argmin((diff**2).sum(dim=1)))


# ------------------------------------------------------------------------------------------------ TablePolicy

@pytest.fixture(scope="module")
def dubins_policy(dubins_table):
    return TablePolicy(dubins_table)


class TestTablePolicy:
    @pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
    def test_rows_sum_to_one_and_equal_the_table_at_centres_and_anywhere_in_the_cell(self, dubins_table, dtype):
        policy = TablePolicy(dubins_table, dtype=dtype)
        gen = _gen(0)
        for t in range(dubins_table.horizon + 1):
            lo, hi = _level(dubins_table, t)
            cells = torch.from_numpy(dubins_table.cells[lo:hi])  # [L, d]
            expected = torch.from_numpy(dubins_table.action_probs[lo:hi]).to(dtype)  # [L, A]
            centres = policy.grid.centers(cells)  # [L, d] float64
            size = torch.tensor(policy.grid.cell_size, dtype=torch.float64)
            for x in (centres, centres + (torch.rand(centres.shape, generator=gen, dtype=torch.float64) - 0.5)
                      * 0.98 * size):  # jitter uniformly within +-0.49 of a cell
                x = x.to(dtype)
                probs = policy.action_probs(x, t)  # [L, A]
                assert probs.shape == (hi - lo, policy.num_actions) and probs.dtype == dtype
                torch.testing.assert_close(probs.sum(dim=1), torch.ones(hi - lo, dtype=dtype), atol=1e-5, rtol=0)
                torch.testing.assert_close(probs, expected, atol=0, rtol=0)
                assert torch.equal(policy.rows(x, t), torch.arange(lo, hi))
        assert int(policy.misses) == 0 and int(policy.nearest_hits) == 0

    def test_rows_agree_with_a_dictionary_lookup(self, dubins_table):
        """Fast sorted-key lookup vs a plain dict of (level, cell) -> row, on random states and on states near the
        table's cells (float64, so both sides round the same way at cell boundaries)."""
        policy = TablePolicy(dubins_table, dtype=torch.float64)
        index = {}
        for t in range(dubins_table.horizon + 1):
            lo, hi = _level(dubins_table, t)
            for row in range(lo, hi):
                index[(t, *dubins_table.cells[row].tolist())] = row
        gen = _gen(1)
        box = torch.rand(2000, 3, generator=gen, dtype=torch.float64) * torch.tensor([2.4, 2.4, 2 * math.pi]) \
            - torch.tensor([0.2, 1.2, math.pi])
        near = policy.grid.centers(torch.from_numpy(dubins_table.cells))  # [C, d]
        near = near + (torch.rand(near.shape, generator=gen, dtype=torch.float64) - 0.5) \
            * 3.0 * torch.tensor(policy.grid.cell_size)  # within +-1.5 cells: in, next to, or off the level
        x = torch.cat((box, near))
        cells = policy.grid.cells(x)
        hits = 0
        for t in range(dubins_table.horizon + 1):
            expected = torch.tensor([index.get((t, *c), -1) for c in cells.tolist()])
            assert torch.equal(policy.rows(x, t), expected)
            hits += int((expected >= 0).sum())
        assert hits > len(dubins_table.cells) // 10, "the states should land in the level sets often"

    def test_halo_state_gets_the_row_of_its_nearest_level_cell(self, dubins_table):
        """Every cell one step outside L_t (all 26 neighbour offsets) against a brute-force nearest cell."""
        policy = TablePolicy(dubins_table)
        k = policy.grid.num_angle_cells
        for t in (0, 1, 4):
            lo, hi = _level(dubins_table, t)
            level_cells = torch.from_numpy(dubins_table.cells[lo:hi])  # [L, d]
            members = {tuple(c) for c in level_cells.tolist()}
            offsets = torch.tensor([o for o in np.ndindex(3, 3, 3) if o != (1, 1, 1)]) - 1  # [26, d]
            halo = set()
            for c in level_cells:
                for o in offsets:
                    n = (c + o).clone()
                    n[2] = n[2] % k[2]
                    if tuple(n.tolist()) not in members:
                        halo.add(tuple(n.tolist()))
            halo_cells = torch.tensor(sorted(halo))  # [H, d]
            expected_rows = torch.tensor([lo + _brute_nearest(c, level_cells, k) for c in halo_cells])
            x = policy.grid.centers(halo_cells).float()
            policy.reset_counters()
            probs = policy.action_probs(x, t)
            torch.testing.assert_close(probs, torch.from_numpy(dubins_table.action_probs)[expected_rows], atol=0, rtol=0)
            assert int(policy.nearest_hits) == len(halo_cells) and int(policy.misses) == 0
            assert torch.equal(policy.rows(x, t), torch.full((len(halo_cells),), -1))  # not in L_t itself

    def test_fallbacks_and_counters_on_the_random_walk(self, walk_table):
        """Level 1 of the walk is cells -2..2 (0.5 m); cell 3 is one cell outside, cell 9 far away."""
        policy = TablePolicy(walk_table)
        lo, hi = _level(walk_table, 1)
        assert walk_table.cells[lo:hi, 0].tolist() == [-2, -1, 0, 1, 2]
        probs_table = torch.from_numpy(walk_table.action_probs)
        inside, halo_pos, halo_neg, far = 0.5, 1.5, -1.5, 4.5  # cells 1, 3, -3, 9
        x = torch.tensor([[inside], [halo_pos], [halo_neg], [far]])
        assert policy.queries == 0 and policy.miss_rate == 0.0 and policy.nearest_rate == 0.0
        probs = policy.action_probs(x, 1)
        torch.testing.assert_close(probs[0], probs_table[lo + 3])  # cell 1
        torch.testing.assert_close(probs[1], probs_table[lo + 4])  # nearest: cell 2
        torch.testing.assert_close(probs[2], probs_table[lo + 0])  # nearest: cell -2
        torch.testing.assert_close(probs[3], _uniform(policy)[0])
        assert policy.queries == 4 and int(policy.nearest_hits) == 2 and int(policy.misses) == 1
        assert policy.nearest_rate == pytest.approx(0.5) and policy.miss_rate == pytest.approx(0.25)
        policy.sample(x, 1, _gen(0))  # sampling counts the same way
        assert policy.queries == 8 and int(policy.nearest_hits) == 4 and int(policy.misses) == 2
        assert policy.nearest_rate == pytest.approx(0.5) and policy.miss_rate == pytest.approx(0.25)
        policy.reset_counters()
        assert policy.queries == 0 and int(policy.nearest_hits) == 0 and int(policy.misses) == 0
        assert policy.miss_rate == 0.0 and policy.nearest_rate == 0.0

    def test_far_state_gets_uniform_and_counts_a_miss(self, dubins_policy):
        dubins_policy.reset_counters()
        x = torch.tensor([[100.0, -100.0, 0.3], [-1e6, 1e6, -3.0]])
        for t in (0, 3, 10):
            torch.testing.assert_close(dubins_policy.action_probs(x, t), _uniform(dubins_policy, 2))
        assert int(dubins_policy.misses) == 6 and int(dubins_policy.nearest_hits) == 0
        assert dubins_policy.miss_rate == 1.0
        dubins_policy.reset_counters()

    def test_uniform_fallback_gives_uniform_one_cell_outside(self, walk_table, dubins_table):
        walk = TablePolicy(walk_table, fallback="uniform")
        probs = walk.action_probs(torch.tensor([[1.5], [-1.5], [0.5]]), 1)
        torch.testing.assert_close(probs[:2], _uniform(walk, 2))
        torch.testing.assert_close(probs[2], torch.from_numpy(walk_table.action_probs)[_level(walk_table, 1)[0] + 3])
        assert int(walk.misses) == 2 and int(walk.nearest_hits) == 0 and walk.miss_rate == pytest.approx(2 / 3)
        # Dubins: origin cell shifted by one x cell is not in L_0
        dub = TablePolicy(dubins_table, fallback="uniform")
        x = dub.grid.centers(torch.tensor([[1, 0, 0]])).float()
        torch.testing.assert_close(dub.action_probs(x, 0), _uniform(dub))
        assert dub.num_halo == 0 and dub.nearest_rate == 0.0 and dub.miss_rate == 1.0

    def test_unknown_fallback_is_a_clear_error(self, walk_table):
        with pytest.raises(ValueError, match="nearest"):
            TablePolicy(walk_table, fallback="closest")

    def test_sample_draws_actions_with_the_table_probabilities(self, dubins_table):
        """200k draws in one cell: chi-square test at p = 1e-4 and every frequency within 0.006 of its probability
        (binomial sd <= 0.0012 at n = 200k)."""
        policy = TablePolicy(dubins_table)
        t = 1
        lo, hi = _level(dubins_table, t)
        row = lo + int(dubins_table.action_probs[lo:hi].min(axis=1).argmax())  # the level-1 row with no rare action
        p = torch.from_numpy(dubins_table.action_probs[row]).double()
        assert bool((p > 0.05).all())
        n = 200_000
        x = policy.grid.centers(torch.from_numpy(dubins_table.cells[row : row + 1])).float().expand(n, 3)
        u = policy.sample(x, t, _gen(123))  # [n, q]
        assert u.shape == (n, 1)
        idx = (u[:, None, 0] == policy.actions[None, :, 0]).float().argmax(dim=1)
        assert bool((u[:, None, 0] == policy.actions[None, :, 0]).any(dim=1).all()), "drew an action not in the set"
        counts = torch.bincount(idx, minlength=policy.num_actions).double()
        chi2 = float(((counts - n * p) ** 2 / (n * p)).sum())
        assert chi2 < stats.chi2.ppf(1 - 1e-4, df=policy.num_actions - 1), f"chi2={chi2}, counts={counts.tolist()}"
        assert float((counts / n - p).abs().max()) < 0.006

    def test_sample_never_draws_a_zero_probability_action_and_is_seeded(self, walk_table):
        policy = TablePolicy(walk_table)
        lo, _ = _level(walk_table, 1)
        row = lo + 1  # cell -1: probabilities (0.111, 0.556, 0.333, 0, 0)
        p = walk_table.action_probs[row]
        assert p[3] == 0 and p[4] == 0
        x = torch.full((20_000, 1), -0.5)
        u = policy.sample(x, 1, _gen(5))
        allowed = policy.actions[torch.from_numpy(p > 0)][:, 0]
        assert bool(torch.isin(u[:, 0], allowed).all())
        assert torch.equal(u, policy.sample(x, 1, _gen(5)))
        assert not torch.equal(u, policy.sample(x, 1, _gen(6)))

    def test_bad_level_and_shapes_are_clear_errors(self, dubins_policy):
        x = torch.zeros(2, 3)
        with pytest.raises(ValueError):
            dubins_policy.action_probs(x, dubins_policy.horizon + 1)
        with pytest.raises(ValueError):
            dubins_policy.action_probs(x, -1)
        with pytest.raises(ValueError):
            dubins_policy.action_probs(torch.zeros(2, 2), 0)
        with pytest.raises(ValueError):
            dubins_policy.sample(torch.zeros(2, 3, dtype=torch.float64), 0)


# ------------------------------------------------------------------------------------------------ rollout + frames

class TestRollout:
    @pytest.mark.parametrize("n", [1, 256])
    def test_shapes_for_table_policies_and_samplers(self, dubins_table, walk_table, n):
        dub = TablePolicy(dubins_table)
        states, actions = rollout(dub.system, dub, torch.tensor([0.3, -0.2, 1.0]), n, 10, _gen(0))
        assert states.shape == (n, 11, 3) and actions.shape == (n, 10, 1)
        assert states.dtype == torch.float32 and bool(torch.isfinite(states).all())
        walk = TablePolicy(walk_table)
        states, actions = rollout(walk.system, walk, torch.zeros(1), n, 8, _gen(0))
        assert states.shape == (n, 9, 1) and actions.shape == (n, 8, 1)
        lo, hi = dub.actions.min(0).values, dub.actions.max(0).values
        sampler = GaussianSampler(torch.zeros(7, 1), 0.3, lo, hi)
        states, actions = rollout(dub.system, sampler, torch.zeros(3), n, 7, _gen(0))
        assert states.shape == (n, 8, 3) and actions.shape == (n, 7, 1)

    def test_start_state_is_included_and_steps_follow_the_dynamics(self, dubins_policy):
        """Cross-check against the plain dynamics: states[t+1] = step(states[t], actions[t]) in the world frame."""
        pose = torch.tensor([1.3, -0.7, 2.9])
        states, actions = rollout(dubins_policy.system, dubins_policy, pose, 256, 10, _gen(2))
        torch.testing.assert_close(states[:, 0], pose.expand(256, 3))
        for t in range(10):
            _assert_states_close(dubins_policy.system.step(states[:, t], actions[:, t]), states[:, t + 1], atol=2e-5)
        assert bool(torch.isin(actions.flatten(), dubins_policy.actions[:, 0]).all())

    def test_seeded_reproducibility(self, dubins_policy):
        args = (dubins_policy.system, dubins_policy, torch.tensor([0.5, 0.5, -1.0]), 256, 10)
        s1, a1 = rollout(*args, _gen(7))
        s2, a2 = rollout(*args, _gen(7))
        s3, a3 = rollout(*args, _gen(8))
        assert torch.equal(s1, s2) and torch.equal(a1, a2)
        assert not torch.equal(a1, a3) and not torch.equal(s1, s3)

    @pytest.mark.parametrize("pose", [(0.7, -1.2, 2.5), (-3.0, 4.0, -math.pi), (10.0, 0.0, 0.5 * math.pi)])
    def test_rollout_from_a_pose_is_the_origin_rollout_moved_to_the_pose(self, dubins_policy, pose):
        P = torch.tensor(pose)
        s_pose, a_pose = rollout(dubins_policy.system, dubins_policy, P, 300, 10, _gen(11))
        s_origin, a_origin = rollout(dubins_policy.system, dubins_policy, torch.zeros(3), 300, 10, _gen(11))
        assert torch.equal(a_pose, a_origin)
        expected = se2_to_world(s_origin, P)
        torch.testing.assert_close(s_pose[..., :2], expected[..., :2], atol=1e-5, rtol=1e-5)
        _angle_close(s_pose[..., 2], expected[..., 2], 1e-5)

    def test_batch_of_start_poses(self, dubins_policy):
        """``x0 [N, d]``: each row is rolled out from its own pose (same draws as the origin rollout)."""
        n = 64
        poses = torch.rand(n, 3, generator=_gen(3)) * torch.tensor([4.0, 4.0, 2 * math.pi]) - torch.tensor([2.0, 2.0, math.pi])
        s, a = rollout(dubins_policy.system, dubins_policy, poses, n, 10, _gen(4))
        s0, a0 = rollout(dubins_policy.system, dubins_policy, torch.zeros(3), n, 10, _gen(4))
        assert torch.equal(a, a0)
        _assert_states_close(s, se2_to_world(s0, poses[:, None, :]), atol=1e-5)

    def test_se2_to_local_inverts_se2_to_world(self):
        gen = _gen(9)
        local = torch.randn(5, 7, 4, generator=gen, dtype=torch.float64) * 3  # a 4th dimension passes through
        local[..., 2] = wrap_angle(local[..., 2])
        pose = torch.randn(5, 1, 4, generator=gen, dtype=torch.float64) * 3
        world = se2_to_world(local, pose)
        assert torch.equal(world[..., 3], local[..., 3])
        back = se2_to_local(world, pose)
        torch.testing.assert_close(back[..., :2], local[..., :2], atol=1e-12, rtol=0)
        _angle_close(back[..., 2], local[..., 2], 1e-12)
        torch.testing.assert_close(back[..., 3], local[..., 3])
        # and the other way round
        _assert_states_close(se2_to_world(se2_to_local(world, pose), pose)[..., :3], world[..., :3], atol=1e-12)
        # a known value: (1, 0, 0) seen from (2, 3, pi/2) is (2, 4, pi/2)
        torch.testing.assert_close(se2_to_world(torch.tensor([1.0, 0.0, 0.0]), torch.tensor([2.0, 3.0, math.pi / 2])),
                                   torch.tensor([2.0, 4.0, math.pi / 2]))

    def test_horizon_beyond_the_table_is_a_value_error(self, dubins_policy):
        with pytest.raises(ValueError, match="horizon"):
            rollout(dubins_policy.system, dubins_policy, torch.zeros(3), 4, dubins_policy.horizon + 1)

    @pytest.mark.parametrize("bad", [float("nan"), float("inf")])
    def test_non_finite_start_is_a_value_error(self, dubins_policy, bad):
        with pytest.raises(ValueError):
            rollout(dubins_policy.system, dubins_policy, torch.tensor([0.0, bad, 0.0]), 4, 5)
        with pytest.raises(ValueError):
            rollout(dubins_policy.system, dubins_policy, torch.tensor([[0.0, 0.0, 0.0], [bad, 0.0, 0.0]]), 2, 5)

    def test_wrong_start_shape_is_a_value_error(self, dubins_policy):
        with pytest.raises(ValueError):
            rollout(dubins_policy.system, dubins_policy, torch.zeros(2), 4, 5)
        with pytest.raises(ValueError):
            rollout(dubins_policy.system, dubins_policy, torch.zeros(3, 3), 4, 5)

    def test_policy_on_another_device_is_a_value_error(self, dubins_table):
        """A policy on the ``meta`` device stands in for one on a GPU."""
        try:
            meta = TablePolicy(dubins_table, device="meta")
        except Exception as exc:  # pragma: no cover - depends on the torch build
            pytest.skip(f"cannot build a policy on the meta device: {exc}")
        with pytest.raises(ValueError, match="device|meta"):
            rollout(meta.system, meta, torch.zeros(3), 4, 5)

    def test_discrete_policy_without_sample_uses_categorical_draws(self, dubins_policy):
        """A Policy with only ``actions`` / ``action_probs`` (an MLP's interface) goes through the categorical path."""

        class ProbsOnly:
            start_relative = True

            def __init__(self, inner):
                self.inner, self.actions, self.horizon = inner, inner.actions, inner.horizon

            def action_probs(self, x, t):
                return self.inner.action_probs(x, t)

        policy = ProbsOnly(dubins_policy)
        pose = torch.tensor([0.4, 0.9, -2.0])
        s, a = rollout(dubins_policy.system, policy, pose, 256, 10, _gen(0))
        assert s.shape == (256, 11, 3) and a.shape == (256, 10, 1)
        assert bool(torch.isin(a.flatten(), dubins_policy.actions[:, 0]).all())
        s2, a2 = rollout(dubins_policy.system, policy, pose, 256, 10, _gen(0))
        assert torch.equal(s, s2) and torch.equal(a, a2)
        s0, a0 = rollout(dubins_policy.system, policy, torch.zeros(3), 256, 10, _gen(0))
        assert torch.equal(a, a0)
        _assert_states_close(s, se2_to_world(s0, pose), atol=1e-5)
        with pytest.raises(ValueError, match="horizon"):
            rollout(dubins_policy.system, policy, pose, 4, 11)

    def test_an_object_that_is_no_policy_is_a_value_error(self, dubins_policy):
        with pytest.raises(ValueError):
            rollout(dubins_policy.system, object(), torch.zeros(3), 4, 3)

    @pytest.mark.parametrize("source", [
        "gaussian",
        "table",
    ])
    def test_zero_horizon_keeps_the_action_dimension(self, dubins_policy, source):
        lo, hi = dubins_policy.actions.min(0).values, dubins_policy.actions.max(0).values
        src = dubins_policy if source == "table" else GaussianSampler(torch.zeros(5, 1), 0.3, lo, hi)
        states, actions = rollout(dubins_policy.system, src, torch.tensor([1.0, 2.0, 0.5]), 4, 0, _gen(0))
        torch.testing.assert_close(states, torch.tensor([1.0, 2.0, 0.5]).expand(4, 1, 3))
        assert actions.shape == (4, 0, 1)

    def test_horizon_beyond_the_sampler_nominal_is_a_value_error(self, dubins_policy):
        lo, hi = dubins_policy.actions.min(0).values, dubins_policy.actions.max(0).values
        sampler = GaussianSampler(torch.zeros(5, 1), 0.3, lo, hi)
        with pytest.raises(ValueError):
            rollout(dubins_policy.system, sampler, torch.zeros(3), 4, 10, _gen(0))

    def test_sampler_of_another_dtype_is_a_value_error(self, dubins_policy):
        lo, hi = dubins_policy.actions.min(0).values, dubins_policy.actions.max(0).values
        sampler = GaussianSampler(torch.zeros(5, 1), 0.3, lo, hi)  # float32
        with pytest.raises(ValueError, match=r"states are torch\.float64 but the sampler is torch\.float32"):
            rollout(dubins_policy.system, sampler, torch.zeros(3, dtype=torch.float64), 4, 5, _gen(0))
        states, actions = rollout(dubins_policy.system, sampler, torch.zeros(3), 4, 5, _gen(0))  # its own dtype works
        assert states.dtype == actions.dtype == torch.float32

    @pytest.mark.parametrize("sampler_cls", [GaussianSampler, NormalLogNormalSampler])
    def test_sampler_actions_are_clipped_to_the_system_bounds(self, dubins_policy, sampler_cls):
        system = dubins_policy.system
        acts = system.action_set()
        lo, hi = acts.min(0).values, acts.max(0).values  # [-pi/4, pi/4]
        nominal = torch.full((10, 1), 0.6)  # near the upper bound, so clipping happens often
        sampler = sampler_cls(nominal, 2.0, lo, hi)
        states, actions = rollout(system, sampler, torch.zeros(3), 500, 10, _gen(0))
        assert states.shape == (500, 11, 3) and actions.shape == (500, 10, 1)
        assert bool((actions >= lo).all()) and bool((actions <= hi).all())
        assert bool((actions == hi).any()) and bool((actions == lo).any()), "std 2 should hit both bounds"
        inner = actions[(actions > lo) & (actions < hi)]
        assert inner.numel() > 100, "some actions should be strictly inside the bounds (continuous noise)"


# ------------------------------------------------------------------------------------------------ samplers

class TestSamplers:
    @pytest.mark.parametrize("mean,var", [(1.0, 1.0), (2.0, 0.5), (0.5, 0.1)])
    def test_lognormal_params_give_the_documented_mean_and_variance(self, mean, var):
        """200k draws; sample-variance sd is < 1.5% of var for these laws; margins: 1.5% mean, 6% variance."""
        mu, sigma = lognormal_params(mean, var)
        assert sigma == pytest.approx(math.sqrt(math.log1p(var / mean**2)))
        z = torch.randn(200_000, generator=_gen(0), dtype=torch.float64)
        draws = torch.exp(mu + sigma * z)
        assert float(draws.mean()) == pytest.approx(mean, rel=0.015)
        assert float(draws.var()) == pytest.approx(var, rel=0.06)

    @pytest.mark.parametrize("mean,var", [(0.0, 1.0), (-1.0, 1.0), (1.0, -0.1), (float("nan"), 1.0), (1.0, float("inf"))])
    def test_lognormal_params_reject_bad_moments(self, mean, var):
        with pytest.raises(ValueError):
            lognormal_params(mean, var)

    def test_normal_lognormal_noise_has_mean_zero_and_variance_std2_v_plus_m2(self):
        """var = std^2 (v + m^2) = 0.09 * 2 = 0.18; at n = 200k the sd of the sample variance is ~1.5%, of the
        mean ~0.001. Margins: 6% on the variance, 0.005 on the mean."""
        std, m, v = 0.3, 1.0, 1.0
        low, high = torch.full((2,), -1e9), torch.full((2,), 1e9)
        sampler = NormalLogNormalSampler(torch.zeros(5, 2), std, low, high, lognormal_mean=m, lognormal_var=v)
        noise = sampler.noise(200_000, _gen(1)).double()  # [n, q]
        assert noise.shape == (200_000, 2)
        assert float(noise.mean(0).abs().max()) < 0.005
        torch.testing.assert_close(noise.var(0), torch.full((2,), std**2 * (v + m**2), dtype=torch.float64),
                                   rtol=0.06, atol=0)
        # heavier tails than a Gaussian of the same variance (kurtosis > 3)
        kurt = float(((noise - noise.mean(0)) ** 4).mean() / noise.var(0).mean() ** 2)
        assert kurt > 4.0

    def test_gaussian_noise_has_the_noise_std(self):
        low, high = torch.full((2,), -1e9), torch.full((2,), 1e9)
        sampler = GaussianSampler(torch.zeros(5, 2), torch.tensor([0.1, 0.5]), low, high)
        noise = sampler.noise(200_000, _gen(2)).double()
        assert float(noise.mean(0).abs().max()) < 0.005
        torch.testing.assert_close(noise.std(0), torch.tensor([0.1, 0.5], dtype=torch.float64), rtol=0.01, atol=0)
        scalar = GaussianSampler(torch.zeros(5, 1), 0.3, low[:1], high[:1]).noise(200_000, _gen(3)).double()
        assert float(scalar.std()) == pytest.approx(0.3, rel=0.01)

    def test_sample_adds_noise_to_the_nominal_of_step_t(self):
        nominal = torch.tensor([[0.0], [0.5], [-0.5]])
        low, high = torch.tensor([-1.0]), torch.tensor([1.0])
        sampler = GaussianSampler(nominal, 0.0, low, high)
        x = torch.zeros(4, 3)
        for t in range(3):
            assert torch.equal(sampler.sample(x, t, None), nominal[t].expand(4, 1))

    @pytest.mark.parametrize("sampler_cls", [GaussianSampler, NormalLogNormalSampler])
    def test_sample_sequences_shapes_clipping_and_zero_noise(self, sampler_cls):
        nominal = torch.linspace(-0.9, 0.9, 6)[:, None]  # [T, 1]
        low, high = torch.tensor([-0.5]), torch.tensor([0.5])
        seqs = sampler_cls(nominal, 0.0, low, high).sample_sequences(3, 4, _gen(0))
        assert seqs.shape == (3, 4, 1)
        torch.testing.assert_close(seqs, nominal[:4].clamp(-0.5, 0.5).expand(3, 4, 1))
        noisy = sampler_cls(nominal, 1.0, low, high).sample_sequences(500, 6, _gen(0))
        assert bool((noisy >= -0.5).all() and (noisy <= 0.5).all())
        assert bool((noisy == 0.5).any() and (noisy == -0.5).any())

    @pytest.mark.parametrize("std", [-0.1, float("nan"), [0.1, 0.2, 0.3]])
    def test_bad_noise_std_is_a_value_error(self, std):
        with pytest.raises(ValueError):
            GaussianSampler(torch.zeros(5, 2), std if not isinstance(std, list) else torch.tensor(std),
                            torch.full((2,), -1.0), torch.full((2,), 1.0))


# ------------------------------------------------------------------------------------------------ MPPI core

def _all_inf_cost(states: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
    return torch.full((states.shape[0],), float("inf"), dtype=states.dtype)


def _controller(kind: str, policy: TablePolicy, cost, seed: int = 0, **kw):
    """One line per controller; the sample counts the closed-loop tests use."""
    system = policy.system
    if kind == "mppi":
        return MPPI(system, cost, num_samples=256, horizon=15, noise_std=0.3, seed=seed, **kw)
    if kind == "log_mppi":
        return LogMPPI(system, cost, num_samples=256, horizon=15, noise_std=0.3, seed=seed, **kw)
    if kind == "cuniform":
        return CUniformMPPI(policy, cost, num_samples=256, seed=seed, **kw)
    if kind == "cuniform_bank":
        return CUniformMPPI(policy, cost, num_samples=256, bank_size=1024, seed=seed, **kw)
    if kind == "cumppi":
        return CUMPPI(policy, cost, num_samples=512, seed=seed, **kw)
    if kind == "cumppi_log":
        return CUMPPI(policy, cost, num_samples=512, local="log_mppi", seed=seed, **kw)
    raise AssertionError(kind)


KINDS = ["mppi", "log_mppi", "cuniform", "cuniform_bank", "cumppi", "cumppi_log"]


class TestWeights:
    def test_weights_sum_to_one_and_prefer_low_costs(self):
        costs = torch.tensor([3.0, 1.0, 2.0, 10.0])
        w = mppi_weights(costs, 1.0)
        torch.testing.assert_close(w.sum(), torch.tensor(1.0))
        assert int(torch.argmax(w)) == 1 and bool((w[[1, 2, 0, 3]].diff() < 0).all())
        torch.testing.assert_close(w, torch.softmax(-costs, 0))

    @pytest.mark.parametrize("lambda_", [0.0, 0.01, 1.0, 100.0])
    def test_weights_are_finite_with_inf_and_nan_costs(self, lambda_):
        costs = torch.tensor([float("inf"), 2.0, float("nan"), 1.0, float("-inf"), 5.0])
        w = mppi_weights(costs, lambda_)
        assert bool(torch.isfinite(w).all()) and float(w.sum()) == pytest.approx(1.0)
        costs = torch.tensor([float("inf"), 2.0, float("nan"), 1.0])
        w = mppi_weights(costs, lambda_)
        assert bool(torch.isfinite(w).all()) and float(w.sum()) == pytest.approx(1.0)
        assert int(torch.argmax(w)) == 3 and float(w[0]) == 0.0 and float(w[2]) == 0.0

    @pytest.mark.parametrize("lambda_", [0.0, 1.0])
    @pytest.mark.parametrize("bad", [float("inf"), float("nan")])
    def test_weights_are_finite_when_every_cost_is_bad(self, lambda_, bad):
        w = mppi_weights(torch.full((8,), bad), lambda_)
        assert bool(torch.isfinite(w).all()) and float(w.sum()) == pytest.approx(1.0)
        if lambda_ > 0:
            torch.testing.assert_close(w, torch.full((8,), 1 / 8))

    def test_lambda_zero_is_one_hot_at_the_argmin(self):
        costs = torch.tensor([3.0, 1.0, 2.0, float("inf"), 1.5])
        w = mppi_weights(costs, 0.0)
        assert torch.equal(w, torch.tensor([0.0, 1.0, 0.0, 0.0, 0.0]))
        assert bool(torch.isfinite(mppi_weights(torch.tensor([5.0, float("nan")]), 0)).all())

    def test_cost_cap_is_finite(self):
        assert math.isfinite(COST_CAP) and COST_CAP > 1e6


class TestControllers:
    @pytest.mark.parametrize("kind", KINDS)
    @pytest.mark.parametrize("goal", [(2.5, 1.0), (2.0, -1.5)])
    def test_reaches_a_goal_in_free_space(self, dubins_policy, kind, goal):
        env = Environment([])
        cost = NavigationCost(env, goal, goal_tolerance=0.2)
        ctrl = _controller(kind, dubins_policy, cost, seed=0)
        result = simulate(dubins_policy.system, ctrl, torch.zeros(3), env, goal, 0.3, 8.0, cost=cost)
        assert result.outcome == "goal", (kind, result.outcome, result.path[-1].tolist())
        assert bool(torch.isfinite(result.controls).all())

    @pytest.mark.parametrize("kind", KINDS)
    def test_avoids_a_circle_on_the_straight_line_to_the_goal(self, dubins_policy, kind):
        obstacle = Circle((1.5, 0.0), 0.3)
        env = Environment([obstacle])
        goal = (3.0, 0.0)
        start = torch.zeros(3)
        # the obstacle is really in the way: driving straight collides
        class Straight:
            def command(self, state):
                return torch.zeros(1)
        assert simulate(dubins_policy.system, Straight(), start, env, goal, 0.3, 8.0).outcome == "collision"
        cost = NavigationCost(env, goal, goal_tolerance=0.2)
        ctrl = _controller(kind, dubins_policy, cost, seed=0)
        result = simulate(dubins_policy.system, ctrl, start, env, goal, 0.3, 8.0, cost=cost)
        assert result.outcome == "goal", (kind, result.outcome, result.path[-1].tolist())
        assert float(obstacle.signed_distance(result.path[:, :2]).min()) > 0

    @pytest.mark.parametrize("kind", KINDS)
    def test_command_is_finite_when_every_proposal_collides(self, dubins_policy, kind):
        ctrl = _controller(kind, dubins_policy, _all_inf_cost)
        state = torch.tensor([0.4, -0.3, 1.0])
        for _ in range(3):
            u = ctrl.command(state)
            assert u.shape == (1,) and bool(torch.isfinite(u).all())
        result = ctrl.plan(state)
        assert bool(torch.isfinite(result.weights).all()) and float(result.weights.sum()) == pytest.approx(1.0, abs=1e-5)
        assert bool(torch.isfinite(result.costs).all())

    def test_nan_costs_give_a_finite_command(self, dubins_policy):
        def nan_cost(states, actions):
            c = states[:, -1, 0].clone()
            c[::2] = float("nan")
            return c
        for kind in ("mppi", "cuniform"):
            u = _controller(kind, dubins_policy, nan_cost).command(torch.zeros(3))
            assert bool(torch.isfinite(u).all())

    def test_mppi_warm_start_shifts_the_nominal(self, dubins_policy):
        cost = NavigationCost(Environment([]), (2.0, 1.0))
        ctrl = _controller("mppi", dubins_policy, cost, seed=3)
        state = torch.tensor([0.1, 0.2, 0.3])
        gen_state = ctrl.generator.get_state()
        result = ctrl.plan(state)
        assert torch.equal(ctrl.nominal, torch.zeros(15, 1)), "plan must not change the nominal"
        ctrl.generator.set_state(gen_state)
        u = ctrl.command(state)
        torch.testing.assert_close(u, result.command)
        torch.testing.assert_close(ctrl.nominal, torch.cat((result.nominal[1:], result.nominal[-1:])))
        assert not torch.equal(ctrl.nominal, torch.zeros(15, 1))
        ctrl.reset()
        assert torch.equal(ctrl.nominal, torch.zeros(15, 1))

    def test_command_is_the_weighted_first_action(self, dubins_policy):
        cost = NavigationCost(Environment([]), (2.0, 1.0))
        for kind in ("mppi", "cuniform"):
            result = _controller(kind, dubins_policy, cost, seed=1).plan(torch.zeros(3))
            torch.testing.assert_close(result.nominal, torch.einsum("k,ktq->tq", result.weights, result.actions))
            torch.testing.assert_close(result.command, result.nominal[0])

    def test_cuniform_lambda_zero_commands_the_best_proposal(self, dubins_policy):
        cost = NavigationCost(Environment([]), (2.0, 1.0))
        ctrl = CUniformMPPI(dubins_policy, cost, num_samples=256, lambda_=0.0, seed=0)
        result = ctrl.plan(torch.zeros(3))
        torch.testing.assert_close(result.command, result.actions[result.best, 0])

    def test_cuniform_seeded_controllers_repeat(self, dubins_policy):
        cost = NavigationCost(Environment([]), (2.0, 1.0))
        for kind in ("cuniform", "cuniform_bank", "mppi"):
            a = _controller(kind, dubins_policy, cost, seed=4).plan(torch.zeros(3))
            b = _controller(kind, dubins_policy, cost, seed=4).plan(torch.zeros(3))
            assert torch.equal(a.states, b.states) and torch.equal(a.command, b.command)

    def test_bank_proposals_are_bank_rollouts_moved_to_the_pose(self, dubins_policy):
        cost = NavigationCost(Environment([]), (2.0, 1.0))
        ctrl = CUniformMPPI(dubins_policy, cost, num_samples=256, bank_size=512, seed=0)
        assert ctrl.bank_states.shape == (512, 11, 3) and ctrl.bank_actions.shape == (512, 10, 1)
        pose = torch.tensor([1.0, -2.0, 0.7])
        states, actions = ctrl.propose(pose)
        assert states.shape == (256, 11, 3) and actions.shape == (256, 10, 1)
        local = se2_to_local(states, pose)
        # every proposal is one of the bank's rollouts
        dist = (local[:, None, :, :2] - ctrl.bank_states[None, :, :, :2]).abs().amax(dim=(2, 3))  # [K, M]
        assert float(dist.min(dim=1).values.max()) < 1e-5
        # and they are distinct bank rows (a subset, not draws with replacement): no action sequence appears
        # more often among the proposals than in the bank (C-Uniform banks can repeat a sequence)
        def counts(a):
            rows, n = torch.unique(a.reshape(a.shape[0], -1), dim=0, return_counts=True)
            return {tuple(r.tolist()): int(c) for r, c in zip(rows, n)}

        in_bank, proposed = counts(ctrl.bank_actions), counts(actions)
        assert all(c <= in_bank[seq] for seq, c in proposed.items())
        assert sum(proposed.values()) == 256

    def test_bank_refresh_draws_a_new_bank(self, dubins_policy):
        cost = NavigationCost(Environment([]), (2.0, 1.0))
        ctrl = CUniformMPPI(dubins_policy, cost, num_samples=64, bank_size=128, bank_refresh=2, seed=0)
        bank = ctrl.bank_states.clone()
        ctrl.command(torch.zeros(3))
        assert torch.equal(ctrl.bank_states, bank)
        ctrl.command(torch.zeros(3))
        assert not torch.equal(ctrl.bank_states, bank)

    @pytest.mark.parametrize("kind", KINDS)
    def test_result_fields_have_the_documented_shapes(self, dubins_policy, kind):
        cost = NavigationCost(Environment([]), (2.0, 1.0))
        ctrl = _controller(kind, dubins_policy, cost, seed=0)
        result = ctrl.plan(torch.zeros(3))
        assert isinstance(result, MPPIResult)
        T = 15 if kind in ("mppi", "log_mppi") else 10
        K = 256  # CU-MPPI returns its local pass: the other half of its 512 samples
        assert result.command.shape == (1,)
        assert result.nominal.shape == (T, 1)
        assert result.states.shape == (K, T + 1, 3)
        assert result.actions.shape == (K, T, 1)
        assert result.costs.shape == (K,) and bool(torch.isfinite(result.costs).all())
        assert result.weights.shape == (K,) and float(result.weights.sum()) == pytest.approx(1.0, abs=1e-5)
        assert result.best.shape == () and 0 <= int(result.best) < K
        assert float(result.costs[result.best]) == float(result.costs.min())
        for tensor in (result.command, result.nominal, result.states, result.actions, result.costs, result.weights):
            assert tensor.dtype == torch.float32
        torch.testing.assert_close(result.states[:, 0], torch.zeros(K, 3))

    def test_cumppi_local_pass_starts_from_the_best_cuniform_rollout(self, dubins_policy):
        cost = NavigationCost(Environment([]), (2.0, 1.0))
        ctrl = CUMPPI(dubins_policy, cost, num_samples=512, noise_std=0.0, seed=0)
        state = torch.zeros(3)
        gen_state = ctrl.cuniform.generator.get_state()
        seed_result = ctrl.cuniform.plan(state)
        ctrl.cuniform.generator.set_state(gen_state)
        result = ctrl.plan(state)
        # no noise: every local sample is the best C-Uniform sequence
        best = seed_result.actions[seed_result.best]
        torch.testing.assert_close(result.nominal, best)
        torch.testing.assert_close(result.command, best[0])

    # -------------------------------------------------------------------------------------------- bad input

    @pytest.mark.parametrize("kind", KINDS)
    def test_bad_states_are_value_errors(self, dubins_policy, kind):
        ctrl = _controller(kind, dubins_policy, NavigationCost(Environment([]), (2.0, 1.0)))
        for bad in (torch.zeros(2), torch.zeros(2, 3), torch.zeros(4), torch.tensor([0.0, float("nan"), 0.0]),
                    torch.tensor([float("inf"), 0.0, 0.0])):
            with pytest.raises(ValueError):
                ctrl.command(bad)
        assert ctrl.command(torch.zeros(1, 3)).shape == (1, 1)  # a batch of one robot keeps its robot dimension

    @pytest.mark.parametrize("kind", KINDS)
    @pytest.mark.parametrize("lambda_", [-1.0, float("nan"), float("inf")])
    def test_bad_lambda_is_a_value_error(self, dubins_policy, kind, lambda_):
        with pytest.raises(ValueError, match="lambda"):
            _controller(kind, dubins_policy, NavigationCost(Environment([]), (2.0, 1.0)), lambda_=lambda_)

    def test_bank_smaller_than_the_samples_is_a_value_error(self, dubins_policy):
        cost = NavigationCost(Environment([]), (2.0, 1.0))
        with pytest.raises(ValueError, match="bank_size"):
            CUniformMPPI(dubins_policy, cost, num_samples=256, bank_size=100)
        with pytest.raises(ValueError, match="bank_size"):
            CUMPPI(dubins_policy, cost, num_samples=512, bank_size=100)
        with pytest.raises(ValueError, match="bank_size"):
            CUniformMPPI(dubins_policy, cost, num_samples=256, bank_size=0)

    def test_bank_on_a_system_without_se2_invariance_is_a_value_error(self, walk_table):
        walk = TablePolicy(walk_table)
        with pytest.raises(ValueError, match="SE\\(2\\)"):
            CUniformMPPI(walk, lambda s, a: s[:, -1, 0] ** 2, num_samples=16, bank_size=32)

    def test_unknown_local_pass_is_a_value_error(self, dubins_policy):
        with pytest.raises(ValueError, match="local"):
            CUMPPI(dubins_policy, NavigationCost(Environment([]), (2.0, 1.0)), local="ilqr")

    @pytest.mark.parametrize("kw", [dict(num_samples=0), dict(num_samples=1), dict(cuniform_fraction=0.0),
                                    dict(cuniform_fraction=1.0)])
    def test_bad_cumppi_split_is_a_value_error(self, dubins_policy, kw):
        with pytest.raises(ValueError):
            CUMPPI(dubins_policy, NavigationCost(Environment([]), (2.0, 1.0)), **kw)

    def test_bad_sample_counts_are_value_errors(self, dubins_policy):
        cost = NavigationCost(Environment([]), (2.0, 1.0))
        for kw in (dict(num_samples=0), dict(num_samples=2.5), dict(horizon=0)):
            with pytest.raises(ValueError):
                MPPI(dubins_policy.system, cost, **kw)
        with pytest.raises(ValueError):
            MPPI(dubins_policy.system, cost, noise_std=-0.3)
        with pytest.raises(ValueError):
            CUniformMPPI(dubins_policy, cost, num_samples=0)

    def test_horizon_beyond_the_table_is_a_value_error_at_construction(self, dubins_policy):
        with pytest.raises(ValueError, match="horizon"):
            CUniformMPPI(dubins_policy, NavigationCost(Environment([]), (2.0, 1.0)), num_samples=16, horizon=15)

    @pytest.mark.parametrize("kw", [dict(bank_size=64, bank_refresh=-1), dict(bank_size=64, bank_refresh=1.5),
                                    dict(bank_refresh=3)])
    def test_bad_bank_refresh_is_a_value_error(self, dubins_policy, kw):
        with pytest.raises(ValueError, match="bank_refresh"):
            CUniformMPPI(dubins_policy, NavigationCost(Environment([]), (2.0, 1.0)), num_samples=16, **kw)

    @pytest.mark.parametrize("dtype", [torch.int64, torch.float64])
    @pytest.mark.parametrize("kind", ["mppi", "cuniform"])
    def test_state_of_another_dtype_is_a_value_error(self, dubins_policy, kind, dtype):
        ctrl = _controller(kind, dubins_policy, NavigationCost(Environment([]), (2.0, 1.0)))
        with pytest.raises(ValueError, match="dtype|float"):
            ctrl.command(torch.zeros(3, dtype=dtype))

    def test_cost_of_the_wrong_shape_is_a_value_error(self, dubins_policy):
        ctrl = MPPI(dubins_policy.system, lambda s, a: s[:, :, 0], num_samples=16, horizon=5)
        with pytest.raises(ValueError, match="cost"):
            ctrl.command(torch.zeros(3))

    def test_checkpoint_dict_is_not_a_policy(self):
        with pytest.raises(ValueError):
            CUniformMPPI({"state_dict": {}}, lambda s, a: s[:, -1, 0])


# ------------------------------------------------------------------------------------------------ GPU

@pytest.mark.gpu
@pytest.mark.skipif(not CUDA, reason="needs a CUDA device")
class TestGPU:
    def test_policy_and_rollout_on_cuda_match_cpu_shapes(self, dubins_table):
        cpu, gpu = TablePolicy(dubins_table, "cpu"), TablePolicy(dubins_table, "cuda")
        x = torch.tensor([[0.0, 0.0, 0.0], [0.05, 0.0, 0.0], [50.0, 0.0, 0.0]])
        torch.testing.assert_close(cpu.action_probs(x, 0), gpu.action_probs(x.cuda(), 0).cpu())
        assert int(gpu.nearest_hits) == int(cpu.nearest_hits) and int(gpu.misses) == int(cpu.misses)
        u = gpu.sample(x.cuda(), 0, _gen(0, "cuda"))
        assert u.device.type == "cuda" and u.shape == (3, 1)
        s_cpu, a_cpu = rollout(cpu.system, cpu, torch.tensor([0.5, 0.5, 1.0]), 500, 10, _gen(0))
        s_gpu, a_gpu = rollout(gpu.system, gpu, torch.tensor([0.5, 0.5, 1.0], device="cuda"), 500, 10, _gen(0, "cuda"))
        assert s_gpu.shape == s_cpu.shape and a_gpu.shape == a_cpu.shape
        assert s_gpu.device.type == "cuda" and bool(torch.isfinite(s_gpu).all())
        s2, _ = rollout(gpu.system, gpu, torch.tensor([0.5, 0.5, 1.0], device="cuda"), 500, 10, _gen(0, "cuda"))
        assert torch.equal(s_gpu, s2)
        # cpu and gpu rollouts each follow the dynamics
        for t in range(10):
            _assert_states_close(gpu.system.step(s_gpu[:, t], a_gpu[:, t]), s_gpu[:, t + 1], atol=2e-5)

    @pytest.mark.parametrize("bank_size", [None, 1024])
    def test_cuniform_mppi_on_cuda_gives_finite_commands(self, dubins_table, bank_size):
        gpu = TablePolicy(dubins_table, "cuda")
        env = Environment([Circle((1.5, 0.0), 0.3)])
        cost = NavigationCost(env, (3.0, 0.0))
        ctrl = CUniformMPPI(gpu, cost, num_samples=512, bank_size=bank_size, seed=0)
        state = torch.zeros(3, device="cuda")
        result = ctrl.plan(state)
        assert result.states.shape == (512, 11, 3) and result.actions.shape == (512, 10, 1)
        assert result.command.shape == (1,) and result.command.device.type == "cuda"
        u = ctrl.command(state)
        assert bool(torch.isfinite(u).all())
        out = simulate(gpu.system, ctrl, state, env, (3.0, 0.0), 0.3, 8.0, cost=cost)
        assert out.outcome == "goal"
        all_inf = CUniformMPPI(gpu, lambda s, a: torch.full((s.shape[0],), float("inf"), device=s.device),
                               num_samples=512, bank_size=bank_size, seed=0)
        assert bool(torch.isfinite(all_inf.command(state)).all())


class TestBackgroundBank:
    def test_commands_return_while_a_refresh_is_blocked_and_the_new_bank_comes_in_after(self, dubins_policy):
        """The worker's draw waits on an Event the test holds: commands must return (with the old bank) while the
        refresh is provably still running, and the new bank is used only once it is released and done."""
        cost = lambda s, a: (s[:, :, :2] ** 2).sum(dim=(1, 2))  # noqa: E731
        ctrl = CUniformMPPI(dubins_policy, cost, num_samples=64, bank_size=256, bank_refresh=1,
                            bank_background=True, seed=0)
        started, release, finished = threading.Event(), threading.Event(), threading.Event()
        draw = ctrl.bank.draw_bank

        def blocked_draw(generator):
            started.set()
            release.wait(timeout=5)  # a command that waited for the refresh would hang here for 5 s
            bank = draw(generator)
            finished.set()
            return bank

        ctrl.bank.draw_bank = blocked_draw
        try:
            first = ctrl.bank_states.clone()
            x = torch.zeros(3)
            ctrl.command(x)  # submits the refresh
            assert started.wait(timeout=10), "the refresh never started"
            t0 = time.perf_counter()
            for _ in range(3):  # the refresh is blocked all along
                u = ctrl.command(x)
                assert u.shape == (1,) and bool(torch.isfinite(u).all())
            elapsed = time.perf_counter() - t0
            assert not finished.is_set() and not release.is_set(), "the commands ran while the refresh was blocked"
            assert elapsed < 4, f"3 commands took {elapsed:.1f} s: they waited for the refresh"
            assert torch.equal(ctrl.bank_states, first) and ctrl.banks_swapped == 0, "the old bank stays in use"
            release.set()
            assert ctrl.wait_for_bank() is True and finished.is_set()
            assert ctrl.banks_swapped == 1
            assert ctrl.bank_states.shape == first.shape and not torch.equal(ctrl.bank_states, first)
            assert ctrl.wait_for_bank() is False  # nothing pending any more
        finally:
            release.set()
            ctrl.close()
        assert not ctrl.bank.worker_running and not ctrl.bank_background

    def test_background_needs_a_refresh_period(self, dubins_policy):
        cost = lambda s, a: s[:, -1, 0]  # noqa: E731
        with pytest.raises(ValueError, match="bank_refresh"):
            CUniformMPPI(dubins_policy, cost, num_samples=64, bank_size=128, bank_background=True)
