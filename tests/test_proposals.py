"""Proposals and the one MPPI core: the protocol, each built-in proposal's own behaviour, and a user-written
proposal that drops into the core unchanged and drives a closed loop to the goal.

Shapes: K proposals, T horizon, d state dimensions, q action dimensions, M bank rollouts.
"""

from __future__ import annotations

import pytest
import torch

from cuniform_torch import CUMPPI, MPPI, CUniformMPPI, Dubins, LogMPPI, MPPICore, Proposal, TablePolicy, rollout
from cuniform_torch.common.frames import se2_to_local, se2_to_world
from cuniform_torch.controllers import (
    BankProposal,
    CompositeProposal,
    GaussianProposal,
    MPPIResult,
    NormalLogNormalProposal,
    PolicyProposal,
)
from cuniform_torch.envs import Circle, Environment, NavigationCost, simulate
from cuniform_torch.sampling import rollout_actions


def _gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def goal_cost(states: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
    """``[K, T+1, d]`` -> ``[K]`` squared distance to (1, 0) summed over the horizon."""
    return ((states[:, :, 0] - 1.0) ** 2 + states[:, :, 1] ** 2).sum(dim=1)


@pytest.fixture(scope="module")
def policy(dubins_table) -> TablePolicy:
    return TablePolicy(dubins_table)


class ArcFan:
    """The README's user-written proposal: K constant turn rates spread over the action range, each step jittered
    by Gaussian noise, rolled out open-loop. It knows nothing of the core but the Proposal protocol."""

    def __init__(self, system, num_samples: int = 256, horizon: int = 15, jitter: float = 0.1):
        self.system, self.num_samples, self.horizon = system, num_samples, horizon
        self.device, self.dtype = torch.device("cpu"), torch.float32
        actions = system.action_set()  # [A, q]
        self.low, self.high = actions.min(0).values, actions.max(0).values  # [q]
        self.rates = torch.linspace(0, 1, num_samples)[:, None] * (self.high - self.low) + self.low  # [K, q]
        self.jitter = jitter
        self.updates: list[MPPIResult] = []
        self.resets = 0

    def propose(self, state, generator):  # [d] -> [K, T+1, d], [K, T, q]
        noise = self.jitter * torch.randn(self.num_samples, self.horizon, self.low.shape[0], generator=generator)
        actions = (self.rates[:, None, :] + noise).clamp(self.low, self.high)  # [K, T, q]
        return rollout_actions(self.system, state, actions), actions

    def update(self, result):
        self.updates.append(result)

    def reset(self):
        self.resets += 1


# ------------------------------------------------------------------------------------------ a user's proposal

class TestUserProposal:
    @pytest.mark.parametrize("seed", [0, 1, 2, 3])
    def test_an_arc_fan_drives_the_core_around_an_obstacle_to_the_goal(self, seed):
        env = Environment([Circle(center=(2.0, 0.0), radius=0.5)])  # on the straight line to the goal
        cost = NavigationCost(env, goal=(4.0, 0.0), goal_tolerance=0.2)
        ctrl = MPPICore(ArcFan(Dubins()), cost, lambda_=0.567, seed=seed)
        result = simulate(ctrl.system, ctrl, torch.zeros(3), env, goal=(4.0, 0.0), goal_tolerance=0.2,
                          time_limit=10.0, cost=cost)
        assert result.outcome == "goal", (seed, result.outcome, result.path[-1].tolist())
        # it went around: the path leaves the straight line by more than the obstacle's radius
        assert float(result.path[:, 1].abs().max()) > 0.5
        assert ctrl.proposal.resets == 1, "simulate resets the controller, which resets its proposal"
        assert len(ctrl.proposal.updates) == len(result.controls), "one update per command"

    def test_command_updates_the_proposal_with_its_own_result_and_plan_does_not(self):
        ctrl = MPPICore(ArcFan(Dubins(), num_samples=32, horizon=5), goal_cost, seed=0)
        state = torch.tensor([0.1, 0.2, 0.3])
        ctrl.plan(state)
        assert ctrl.proposal.updates == [], "plan must leave the proposal as it was"
        gen_state = ctrl.generator.get_state()
        expected = ctrl.plan(state)
        ctrl.generator.set_state(gen_state)
        u = ctrl.command(state)
        assert len(ctrl.proposal.updates) == 1
        got = ctrl.proposal.updates[0]
        assert isinstance(got, MPPIResult) and torch.equal(got.command, u)
        assert torch.equal(got.nominal, expected.nominal) and torch.equal(got.weights, expected.weights)

    def test_seeded_cores_repeat_and_the_proposal_draws_from_the_controllers_generator(self):
        a = MPPICore(ArcFan(Dubins(), 32, 5), goal_cost, seed=7).plan(torch.zeros(3))
        b = MPPICore(ArcFan(Dubins(), 32, 5), goal_cost, seed=7).plan(torch.zeros(3))
        c = MPPICore(ArcFan(Dubins(), 32, 5), goal_cost, seed=8).plan(torch.zeros(3))
        assert torch.equal(a.actions, b.actions) and torch.equal(a.command, b.command)
        assert not torch.equal(a.actions, c.actions)

    def test_an_object_that_is_no_proposal_is_named_with_what_it_lacks(self):
        class Half:
            system, num_samples, horizon = Dubins(), 8, 3

            def propose(self, state, generator):
                raise AssertionError("never called")

        with pytest.raises(TypeError, match=r"Half is not a Proposal: it lacks device, dtype, update, reset"):
            MPPICore(Half(), goal_cost)

    @pytest.mark.parametrize("bad", ["short_horizon", "few_samples", "float64", "actions_only_2d"])
    def test_misshapen_proposals_are_value_errors_naming_the_proposal(self, bad):
        class Broken(ArcFan):
            def propose(self, state, generator):
                states, actions = super().propose(state, generator)
                if bad == "short_horizon":
                    return states[:, :-1], actions[:, :-1]
                if bad == "few_samples":
                    return states[1:], actions[1:]
                if bad == "float64":
                    return states.double(), actions.double()
                return states, actions[:, :, 0]

        ctrl = MPPICore(Broken(Dubins(), 8, 3), goal_cost, seed=0)
        with pytest.raises(ValueError, match=r"Broken\.propose returned states .* expected \[8, 4, 3\] and \[8, 3, 1\] "
                                             r"of torch\.float32"):
            ctrl.command(torch.zeros(3))


# ------------------------------------------------------------------------------------------ built-in proposals

def _proposals(policy) -> dict[str, object]:
    system = policy.system
    first = CUniformMPPI(policy, goal_cost, num_samples=16, lambda_=0.0, seed=0)
    return {
        "gaussian": GaussianProposal(system, 16, 5),
        "log_normal": NormalLogNormalProposal(system, 16, 5),
        "policy": PolicyProposal(policy, 16),
        "bank": BankProposal(PolicyProposal(policy, 16), 64, _gen(0)),
        "composite": CompositeProposal(first, GaussianProposal(system, 16, first.horizon)),
    }


class TestBuiltInProposals:
    @pytest.mark.parametrize("kind", ["gaussian", "log_normal", "policy", "bank", "composite"])
    def test_each_is_a_proposal_of_the_declared_shapes(self, policy, kind):
        proposal = _proposals(policy)[kind]
        assert isinstance(proposal, Proposal)
        pose = torch.tensor([0.5, -0.4, 1.1])
        states, actions = proposal.propose(pose, _gen(0))
        K, T = proposal.num_samples, proposal.horizon
        assert states.shape == (K, T + 1, 3) and actions.shape == (K, T, 1)
        assert states.dtype == actions.dtype == proposal.dtype
        torch.testing.assert_close(states[:, 0], pose.expand(K, 3))
        for t in range(T):  # every proposal follows the dynamics from the pose
            step = proposal.system.step(states[:, t], actions[:, t])
            torch.testing.assert_close(step[:, :2], states[:, t + 1, :2], atol=2e-5, rtol=0)

    def test_gaussian_warm_start_is_the_weighted_sequence_shifted_one_step(self, policy):
        proposal = GaussianProposal(policy.system, 8, 4, noise_std=0.0)
        weighted = torch.tensor([[0.1], [0.2], [-0.3], [0.4]])
        result = MPPIResult(weighted[0], weighted, torch.zeros(8, 5, 3), torch.zeros(8, 4, 1), torch.zeros(8),
                            torch.full((8,), 1 / 8))
        proposal.update(result)
        torch.testing.assert_close(proposal.nominal, torch.tensor([[0.2], [-0.3], [0.4], [0.4]]))
        # the next proposals are drawn around it (no noise: every one is the shifted sequence)
        _, actions = proposal.propose(torch.zeros(3), _gen(0))
        torch.testing.assert_close(actions, proposal.nominal.expand(8, 4, 1))
        proposal.reset()
        assert torch.equal(proposal.nominal, torch.zeros(4, 1))

    def test_mppi_command_warm_starts_its_proposal(self, policy):
        ctrl = MPPI(policy.system, goal_cost, num_samples=64, horizon=6, seed=0)
        result = ctrl.plan(torch.zeros(3))
        assert torch.equal(ctrl.nominal, torch.zeros(6, 1)), "plan leaves the nominal as it was"
        again = MPPI(policy.system, goal_cost, num_samples=64, horizon=6, seed=0)
        u = again.command(torch.zeros(3))
        torch.testing.assert_close(u, result.command)
        torch.testing.assert_close(again.proposal.nominal, torch.cat((result.nominal[1:], result.nominal[-1:])))

    def test_nominal_of_the_wrong_shape_is_a_value_error(self, policy):
        proposal = GaussianProposal(policy.system, 8, 4)
        with pytest.raises(ValueError, match=r"nominal must be a \[4, 1\] tensor of torch\.float32"):
            proposal.nominal = torch.zeros(5, 1)

    def test_log_mppi_proposes_normal_times_log_normal_noise(self, policy):
        """Around a zero nominal, far inside the bounds (+-0.785), the actions are the noise itself: variance
        std^2 (v + m^2) = 0.0009 * (1 + 1) = 0.0018. Its kurtosis is 3 e^(4 sigma^2) = 48, so the variance estimate
        of 40k draws has sd sqrt(47 / 40k) = 3.4%: margin 12%. Heavier tails than a Gaussian (kurtosis 3)."""
        ctrl = LogMPPI(policy.system, goal_cost, num_samples=4000, horizon=10, noise_std=0.03, seed=0)
        assert isinstance(ctrl.proposal, NormalLogNormalProposal)
        _, actions = ctrl.proposal.propose(torch.zeros(3), _gen(0))
        a = actions.flatten().double()
        assert float(a.var()) == pytest.approx(0.0018, rel=0.12)
        assert float(((a - a.mean()) ** 4).mean() / a.var() ** 2) > 4.0
        gauss = MPPI(policy.system, goal_cost, num_samples=4000, horizon=10, noise_std=0.03, seed=0)
        g = gauss.proposal.propose(torch.zeros(3), _gen(0))[1].flatten().double()
        assert float(((g - g.mean()) ** 4).mean() / g.var() ** 2) < 3.3

    def test_policy_proposal_is_a_rollout_of_the_policy_from_the_pose(self, policy):
        proposal = PolicyProposal(policy, 128)
        pose = torch.tensor([1.0, 2.0, -0.5])
        states, actions = proposal.propose(pose, _gen(3))
        s, a = rollout(policy.system, policy, pose, 128, policy.horizon, _gen(3))
        assert torch.equal(states, s) and torch.equal(actions, a)

    def test_policy_proposal_horizon_and_system_are_checked(self, policy):
        with pytest.raises(ValueError, match="horizon 11 is longer"):
            PolicyProposal(policy, 8, horizon=11)

        class NoSystem:
            actions = policy.actions
            horizon = 10

            def action_probs(self, x, t):
                return policy.action_probs(x, t)

        with pytest.raises(ValueError, match="NoSystem has no system"):
            PolicyProposal(NoSystem(), 8)

    @pytest.mark.parametrize("kernel", [True, False])
    def test_bank_proposals_are_distinct_bank_rows_moved_rigidly_to_the_pose(self, policy, kernel, monkeypatch):
        from cuniform_torch.sampling import kernels as rollout_kernels

        if not kernel:  # the torch frame change (a GPU, or no numba)
            monkeypatch.setattr(rollout_kernels, "usable", lambda x: False)
        bank = BankProposal(PolicyProposal(policy, 64), 256, _gen(0))
        pose = torch.tensor([-1.5, 0.7, 2.6])
        states, actions = bank.propose(pose, _gen(1))
        torch.testing.assert_close(states[:, 0], pose.expand(64, 3))
        # the same draw again, with the subset's rows known: each proposal is its bank row moved to the pose
        idx = torch.randperm(256, generator=_gen(1))[:64]
        assert len(set(idx.tolist())) == 64
        assert torch.equal(actions, bank.bank_actions[idx])
        torch.testing.assert_close(states, se2_to_world(bank.bank_states[idx], pose), atol=1e-6, rtol=0)
        back = se2_to_local(states, pose)  # and back in the bank's frame: the origin rollouts themselves
        torch.testing.assert_close(back[..., :2], bank.bank_states[idx][..., :2], atol=1e-5, rtol=0)

    def test_bank_refreshes_every_refresh_commands_from_its_seeded_stream(self, policy):
        ctrls = [CUniformMPPI(policy, goal_cost, num_samples=16, bank_size=32, bank_refresh=3, seed=5)
                 for _ in range(2)]
        banks = []
        for ctrl in ctrls:
            seen = [ctrl.bank_states.clone()]
            for _ in range(6):
                ctrl.command(torch.zeros(3))
                seen.append(ctrl.bank_states.clone())
            banks.append(seen)
        for seen in banks:  # a new bank after commands 3 and 6, none in between
            changed = [not torch.equal(a, b) for a, b in zip(seen, seen[1:])]
            assert changed == [False, False, True, False, False, True]
        assert all(torch.equal(a, b) for a, b in zip(*banks)), "seeded controllers draw the same banks"
        ctrls[0].reset()
        assert ctrls[0].bank.commands == 0

    def test_composite_seeds_the_local_pass_with_the_best_first_stage_trajectory(self, policy):
        first = CUniformMPPI(policy, goal_cost, num_samples=64, lambda_=0.0, seed=0)
        local = GaussianProposal(policy.system, 32, first.horizon, noise_std=0.0)
        composite = CompositeProposal(first, local)
        gen_state = first.generator.get_state()
        seed = first.plan(torch.zeros(3))
        first.generator.set_state(gen_state)
        _, actions = composite.propose(torch.zeros(3), _gen(0))
        best = seed.actions[int(torch.argmin(seed.costs))]
        assert float(goal_cost(seed.states, seed.actions).min()) < float(goal_cost(seed.states, seed.actions).max())
        torch.testing.assert_close(local.nominal, best)
        torch.testing.assert_close(actions, best.expand(32, *best.shape))

    def test_cumppi_is_the_core_around_a_composite(self, policy):
        ctrl = CUMPPI(policy, goal_cost, num_samples=64, seed=0)
        assert isinstance(ctrl, MPPICore) and isinstance(ctrl.proposal, CompositeProposal)
        assert ctrl.proposal.first is ctrl.cuniform and ctrl.proposal.local is ctrl.local
        assert ctrl.num_samples == 32 and ctrl.cuniform.num_samples == 32


class TestClose:
    def test_close_stops_a_bank_worker_and_is_a_no_op_otherwise(self, policy):
        ctrl = CUniformMPPI(policy, goal_cost, num_samples=16, bank_size=32, bank_refresh=1, bank_background=True,
                            seed=0)
        with ctrl:
            ctrl.command(torch.zeros(3))
            assert ctrl.bank.worker_running
        assert not ctrl.bank.worker_running
        plain = MPPICore(ArcFan(Dubins(), 8, 3), goal_cost, seed=0)
        plain.close()  # nothing to release
        assert bool(torch.isfinite(plain.command(torch.zeros(3))).all())


# ------------------------------------------------------------------------------------------ rollout's frame change

class TestFrameChangeKernel:
    """The compiled frame change of a start-relative rollout against :func:`se2_to_world` (the torch reference)."""

    @pytest.mark.parametrize("dtype, atol", [(torch.float32, 4e-6), (torch.float64, 1e-13)])
    @pytest.mark.parametrize("d", [3, 4])
    def test_it_matches_se2_to_world(self, dtype, atol, d):
        from cuniform_torch.sampling import kernels as rollout_kernels

        if not rollout_kernels.usable(torch.zeros(1, dtype=dtype)):
            pytest.skip("numba is not installed")
        gen = torch.Generator().manual_seed(0)
        local = torch.randn(11, d, 500, generator=gen, dtype=dtype) * 3  # [T+1, d, N], time-major
        local[:, 2] = torch.remainder(local[:, 2] + torch.pi, 2 * torch.pi) - torch.pi
        for pose in ([0.3, -2.0, 0.7], [10.0, 1.0, -3.1], [0.0, 0.0, 3.14159], [-4.0, 2.0, -torch.pi],
                     [1.0, 2.0, 7.0], [0.0, 0.0, -9.5]):  # headings outside [-pi, pi) too (a state need not wrap)
            pose = torch.tensor(pose + [0.5] * (d - 3), dtype=dtype)
            expected = se2_to_world(local.permute(2, 0, 1), pose)  # [N, T+1, d]
            got = rollout_kernels.to_world(local, pose)
            assert got.shape == expected.shape and got.is_contiguous() and got.dtype == dtype
            torch.testing.assert_close(got[..., :2], expected[..., :2], atol=atol, rtol=0)
            heading = torch.remainder(got[..., 2] - expected[..., 2] + torch.pi, 2 * torch.pi) - torch.pi
            assert float(heading.abs().max()) <= atol
            assert float(got[..., 2].min()) >= -torch.pi and float(got[..., 2].max()) < torch.pi
            assert torch.equal(got[..., 3:], expected[..., 3:])

    def test_rollouts_from_a_pose_agree_with_and_without_it(self, policy, monkeypatch):
        from cuniform_torch.sampling import kernels as rollout_kernels

        pose = torch.tensor([1.2, -0.4, 2.2])
        fast, fast_actions = rollout(policy.system, policy, pose, 300, 10, _gen(4))
        monkeypatch.setattr(rollout_kernels, "usable", lambda x: False)
        slow, slow_actions = rollout(policy.system, policy, pose, 300, 10, _gen(4))
        assert torch.equal(fast_actions, slow_actions)
        torch.testing.assert_close(fast[..., :2], slow[..., :2], atol=4e-6, rtol=0)
        heading = torch.remainder(fast[..., 2] - slow[..., 2] + torch.pi, 2 * torch.pi) - torch.pi
        assert float(heading.abs().max()) <= 4e-6
