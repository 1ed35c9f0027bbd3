"""Runtime faults get one clear error (or a documented recovery), never a deep torch traceback or a NaN command.

Covers the background bank worker of ``CUniformMPPI`` surviving a failed refresh (and a small soak of it),
``lambda_`` that underflows the controller's dtype, bad states, bad cost functions, a non-generator passed as a
generator or seed, and ``MLPPolicy.action_probs`` checked as ``TablePolicy.action_probs`` is.
"""

from __future__ import annotations

import threading

import pytest
import torch

from cuniform_torch.controllers import mppi
from cuniform_torch.controllers.mppi import CUMPPI, MPPI, CUniformMPPI, LogMPPI, mppi_weights
from cuniform_torch.policies.mlp import MLPConfig, MLPPolicy
from cuniform_torch.policies.table import TablePolicy
from cuniform_torch.sampling.noise import GaussianSampler, NormalLogNormalSampler
from cuniform_torch.sampling.rollout import rollout

KINDS = ["mppi", "log_mppi", "cuniform", "cuniform_bank", "cumppi"]


@pytest.fixture(scope="module")
def policy(dubins_table) -> TablePolicy:
    return TablePolicy(dubins_table)


@pytest.fixture(scope="module")
def mlp(policy) -> MLPPolicy:
    """A small untrained MLP over the Dubins table's actions (seeded weights)."""
    torch.manual_seed(0)
    config = MLPConfig(state_dim=3, num_actions=policy.num_actions, horizon=policy.horizon,
                       periodic=[False, False, True], feature_scale=[1.0, 1.0, 1.0], hidden=16, layers=1)
    return MLPPolicy(config, policy.system, policy.actions).eval()


def goal_cost(states: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
    """``[K, T+1, d]`` -> ``[K]`` squared distance to (1, 0) summed over the horizon."""
    return ((states[:, :, 0] - 1.0) ** 2 + states[:, :, 1] ** 2).sum(dim=1)


def _make(kind: str, policy: TablePolicy, cost=goal_cost, **kw):
    """One small controller of each kind."""
    if kind == "mppi":
        return MPPI(policy.system, cost, num_samples=32, horizon=5, **kw)
    if kind == "log_mppi":
        return LogMPPI(policy.system, cost, num_samples=32, horizon=5, **kw)
    if kind == "cuniform":
        return CUniformMPPI(policy, cost, num_samples=32, **kw)
    if kind == "cuniform_bank":
        return CUniformMPPI(policy, cost, num_samples=32, bank_size=64, **kw)
    if kind == "cumppi":
        return CUMPPI(policy, cost, num_samples=32, **kw)
    raise AssertionError(kind)


def _fail_first_refresh(ctrl: CUniformMPPI, monkeypatch: pytest.MonkeyPatch) -> None:
    """The controller's first bank draw after this raises RuntimeError; later ones draw as usual."""
    draw, calls = ctrl._draw_bank, []

    def failing(generator: torch.Generator):
        calls.append(1)
        if len(calls) == 1:
            raise RuntimeError("injected failure")
        return draw(generator)

    monkeypatch.setattr(ctrl, "_draw_bank", failing)


def _bank_threads() -> set[threading.Thread]:
    return {t for t in threading.enumerate() if t.name.startswith("cuniform-bank") and t.is_alive()}


# ------------------------------------------------------------------------------------------ background bank

class TestBankWorker:
    def _controller(self, policy) -> CUniformMPPI:
        return CUniformMPPI(policy, goal_cost, num_samples=32, bank_size=64, bank_refresh=1, bank_background=True,
                            seed=0)

    def test_a_failed_refresh_is_reported_once_and_the_old_bank_stays(self, policy, monkeypatch):
        before = _bank_threads()
        ctrl = self._controller(policy)
        _fail_first_refresh(ctrl, monkeypatch)
        first = ctrl.bank_states.clone()
        x = torch.tensor([0.1, -0.2, 0.3])
        try:
            ctrl.command(x)  # submits the refresh that fails
            with pytest.warns(mppi.BankRefreshWarning, match="RuntimeError: injected failure"):
                assert ctrl.wait_for_bank() is False
            assert ctrl.bank_failures == 1 and isinstance(ctrl.last_bank_error, RuntimeError)
            assert torch.equal(ctrl.bank_states, first), "the old bank stays in use"
            u = ctrl.command(x)  # works with the old bank, and submits the next refresh
            assert u.shape == (1,) and bool(torch.isfinite(u).all())
            assert ctrl.wait_for_bank() is True  # the next refresh succeeds
            assert ctrl.banks_swapped == 1 and ctrl.bank_failures == 1
            assert not torch.equal(ctrl.bank_states, first)
            assert bool(torch.isfinite(ctrl.command(x)).all())
        finally:
            ctrl.close()
        assert _bank_threads() <= before, "close() leaves no worker thread"
        ctrl.close()  # idempotent

    def test_close_stops_the_worker_after_an_unseen_failure(self, policy, monkeypatch):
        before = _bank_threads()
        ctrl = self._controller(policy)
        _fail_first_refresh(ctrl, monkeypatch)
        ctrl.command(torch.zeros(3))  # the failing refresh is pending (or done) and not yet looked at
        with pytest.warns(mppi.BankRefreshWarning):
            ctrl.close()
        assert _bank_threads() <= before and ctrl.bank_failures == 1
        ctrl.close()
        assert bool(torch.isfinite(ctrl.command(torch.zeros(3))).all()), "after close() the refresh runs in the loop"

    def test_small_soak_with_a_failure(self, policy):
        from eval.bench.soak_bank import soak  # the script's own loop, at 300 commands

        result = soak(policy, commands=300, num_samples=32, bank_size=256, refresh=5, fail_once=True)
        assert result.finite and result.bank_failures == 1 and result.warnings == 1
        assert result.max_worker_threads <= 1 and result.worker_threads_after_close == 0


# ------------------------------------------------------------------------------------------ lambda_

class TestLambda:
    @pytest.mark.parametrize("kind", KINDS)
    @pytest.mark.parametrize("lambda_", [1e-46, 1e-40, 1e39])
    def test_lambda_outside_float32_is_refused_at_construction(self, policy, kind, lambda_):
        with pytest.raises(ValueError, match=r"lambda_=.*torch\.float32"):
            _make(kind, policy, lambda_=lambda_)

    def test_lambda_that_float64_holds_is_fine_there(self, dubins_table):
        with pytest.raises(ValueError, match="lambda_"):
            mppi_weights(torch.tensor([1.0, 2.0]), 1e-46)
        torch.testing.assert_close(mppi_weights(torch.tensor([1.0, 2.0], dtype=torch.float64), 1e-46),
                                   torch.tensor([1.0, 0.0], dtype=torch.float64))
        policy64 = TablePolicy(dubins_table, dtype=torch.float64)
        u = CUniformMPPI(policy64, goal_cost, num_samples=32, lambda_=1e-46, seed=0).command(
            torch.zeros(3, dtype=torch.float64))
        assert bool(torch.isfinite(u).all())


# ------------------------------------------------------------------------------------------ states and costs

class TestStatesAndCosts:
    @pytest.mark.parametrize("kind", KINDS)
    def test_a_state_that_requires_grad_is_detached(self, policy, kind):
        u = _make(kind, policy, seed=0).command(torch.tensor([0.1, 0.2, 0.3], requires_grad=True))
        assert bool(torch.isfinite(u).all()) and not u.requires_grad

    def test_a_float64_state_for_a_float32_controller_names_the_fix(self, policy):
        with pytest.raises(ValueError, match=r"state is torch\.float64 .* pass state\.to\(torch\.float32\)"):
            _make("mppi", policy).command(torch.zeros(3, dtype=torch.float64))

    @pytest.mark.parametrize("kind", ["mppi", "cuniform", "cuniform_bank", "cumppi"])
    @pytest.mark.parametrize("bad, got", [
        (lambda c: c.double(), r"\[\d+\] tensor of torch\.float64"),
        (lambda c: c.long(), r"\[\d+\] tensor of torch\.int64"),
        (lambda c: c[:, None], r"\[\d+, 1\] tensor of torch\.float32"),
        (lambda c: c[:-1], r"\[\d+\] tensor of torch\.float32"),
        (lambda c: 1.5, r"returned float 1\.5"),
        (lambda c: torch.full_like(c, float("nan")), r"returned NaN for all"),
    ])
    def test_a_bad_cost_names_the_function_and_the_expected_tensor(self, policy, kind, bad, got):
        def broken_cost(states, actions):
            return bad(goal_cost(states, actions))

        with pytest.raises(ValueError, match=r"cost_fn .*broken_cost.* " + got + ".*expected a \\[\\d+\\] tensor"):
            _make(kind, policy, broken_cost, seed=0).command(torch.zeros(3))

    def test_a_bad_terminal_cost_and_a_cost_object_are_named(self, policy):
        class Float64Cost:
            def __call__(self, states, actions):
                return goal_cost(states, actions).double()

        with pytest.raises(ValueError, match=r"terminal_cost .*<lambda>.* torch\.float64.*expected"):
            MPPI(policy.system, goal_cost, 16, 4, terminal_cost=lambda s: s[:, 0].double()).command(torch.zeros(3))
        with pytest.raises(ValueError, match=r"cost_fn .*Float64Cost.*torch\.float64"):
            MPPI(policy.system, Float64Cost(), 16, 4).command(torch.zeros(3))


# ------------------------------------------------------------------------------------------ generators and seeds

class TestGenerators:
    def test_rollout_refuses_an_int_generator(self, policy, mlp):
        for source in (policy, mlp):
            with pytest.raises(TypeError, match="generator must be a torch.Generator or None, got int"):
                rollout(policy.system, source, torch.zeros(3), 8, 3, 0)

    @pytest.mark.parametrize("cls", [GaussianSampler, NormalLogNormalSampler])
    def test_samplers_refuse_an_int_generator(self, cls):
        sampler = cls(torch.zeros(5, 1), 0.3, torch.tensor([-1.0]), torch.tensor([1.0]))
        for draw in (lambda: sampler.sample(torch.zeros(4, 3), 0, 0), lambda: sampler.sample_sequences(4, 3, 0),
                     lambda: sampler.noise(4, 0)):
            with pytest.raises(TypeError, match="generator must be a torch.Generator or None, got int"):
                draw()

    @pytest.mark.parametrize("kind", KINDS)
    @pytest.mark.parametrize("seed", [torch.Generator(), "1", 1.5, True])
    def test_controllers_refuse_a_seed_that_is_not_an_int(self, policy, kind, seed):
        with pytest.raises(TypeError, match="seed must be an int or None"):
            _make(kind, policy, seed=seed)

    def test_rollout_names_a_policy_that_returns_misshaped_probabilities(self, policy):
        class WidePolicy:
            actions = policy.actions

            def action_probs(self, x, t):
                return torch.full((x.shape[0], self.actions.shape[0] + 1), 1.0)

        with pytest.raises(ValueError, match=r"WidePolicy\.action_probs returned \[8, 6\] at step 0; expected \[8, 5\]"):
            rollout(policy.system, WidePolicy(), torch.zeros(3), 8, 3)


# ------------------------------------------------------------------------------------------ MLPPolicy.action_probs

class TestMLPActionProbs:
    @pytest.mark.parametrize("t", [-1, "horizon+1", 2.0, True, None])
    def test_levels_outside_the_table_are_refused_like_a_table(self, policy, mlp, t):
        t = mlp.horizon + 1 if t == "horizon+1" else t
        x = torch.zeros(2, 3)
        for source in (policy, mlp):
            with pytest.raises(ValueError, match=rf"level t={t!r} is outside the .* levels 0\.\.{mlp.horizon}"):
                source.action_probs(x, t)
        for t in (0, mlp.horizon):  # both ends are levels of a table too
            assert mlp.action_probs(x, t).shape == policy.action_probs(x, t).shape == (2, policy.num_actions)

    def test_float64_states_are_refused_like_a_table(self, policy, mlp):
        x = torch.zeros(2, 3, dtype=torch.float64)
        for source in (policy, mlp):
            with pytest.raises(ValueError, match=r"states are torch\.float64 but the policy is torch\.float32"):
                source.action_probs(x, 0)

    def test_nan_and_inf_states_get_the_uniform_row_and_are_counted(self, policy, mlp):
        nan, inf = float("nan"), float("inf")
        x = torch.tensor([[nan, 0.0, 0.0], [0.0, 0.0, inf], [-inf, 0.0, 0.0], [0.1, 0.2, 0.3]])
        misses, queries = int(mlp.misses), mlp.queries
        probs = mlp.action_probs(x, 1)
        A = policy.num_actions
        torch.testing.assert_close(probs[:3], torch.full((3, A), 1.0 / A))
        with torch.no_grad():
            torch.testing.assert_close(probs[3], torch.softmax(mlp(x[3:], 1), dim=1)[0])
        assert int(mlp.misses) - misses == 3 and mlp.queries - queries == 4
        table_row = policy.action_probs(x[:1], 1)  # a table's NaN state: its uniform "not found" row
        torch.testing.assert_close(table_row, probs[:1])


# ------------------------------------------------------------------------------------------ devices

def test_an_unindexed_cuda_device_is_the_current_one(monkeypatch):
    """``TablePolicy(table, "cuda")`` keeps ``cuda`` while its tensors say ``cuda:0``: the checks must agree."""
    from cuniform_torch.sampling.rollout import same_device

    monkeypatch.setattr(torch.cuda, "current_device", lambda: 0)  # no GPU needed
    assert same_device("cuda", torch.device("cuda", 0)) and same_device(torch.device("cuda", 0), "cuda")
    assert not same_device("cuda", "cuda:1") and not same_device("cuda", "cpu")
    assert same_device("cpu", torch.device("cpu")) and not same_device("cpu", "meta")
