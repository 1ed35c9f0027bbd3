"""Bad tensors, states and options at the runtime's public constructors and calls: one clear error
(or a documented recovery), never a deep torch traceback, a NaN command or a silent wrong answer.

Systems (``make_system``'s parameters, ``step``'s shapes), ``rollout`` and ``TablePolicy.rows``, ``simulate``'s
runaway limit, the controllers (the background bank worker, ``lambda_`` underflow, bad states and costs, generators
and seeds, ``MLPPolicy.action_probs``, devices) and honest policies (a table or MLP says where it is valid, counts
what is outside and answers it by the documented fallback: issue 17, items 3 and 5)."""

from __future__ import annotations

import math
import re
import threading
import warnings

import pytest
import torch
from hardening_helpers import HORIZON, _mlp

from cuniform_torch import CUniformMPPI, TablePolicy, load_policy, make_system, rollout
from cuniform_torch.controllers import mppi
from cuniform_torch.controllers.mppi import CUMPPI, MPPI, LogMPPI, mppi_weights
from cuniform_torch.grid.cells import Grid
from cuniform_torch.policies import MLPConfig, MLPPolicy
from cuniform_torch.policies.checkpoint import policy_checkpoint
from cuniform_torch.sampling import StartMismatchWarning
from cuniform_torch.sampling.noise import GaussianSampler, NormalLogNormalSampler
from cuniform_torch.sampling.rollout import RolloutPlan
from cuniform_torch.systems import Dubins, RandomWalk1D, UnknownSystemError, se2_invariance_gap, system_to_json
from precompute.flow.builder import BuildConfig, build_table

TAU = 2.0 * math.pi


BAD_PARAMS = [
    ("dubins", {"speed": 0.0}, r"dubins: speed must be a positive number, got 0\.0"),
    ("dubins", {"speed": -1.0}, r"dubins: speed must be a positive number"),
    ("dubins", {"speed": float("nan")}, r"dubins: speed must be a positive number"),
    ("dubins", {"dt": 0.0}, r"dubins: dt must be a positive number"),
    ("dubins", {"dt": -0.2}, r"dubins: dt must be a positive number"),
    ("dubins", {"dt": "0.2"}, r"dubins: dt must be a positive number, got '0\.2'"),
    ("dubins", {"max_omega": -1.0}, r"dubins: max_omega must be a non-negative number"),
    ("random_walk_1d", {"dt": 0}, r"random_walk_1d: dt must be a positive number"),
    ("random_walk_1d", {"max_speed": 0.0}, r"random_walk_1d: max_speed must be a positive number"),
    ("dubins", {"cell_size": (0.0, 0.05, TAU / 40)}, r"dubins: cell_size must be positive"),
    ("dubins", {"cell_size": (0.05, -0.05, TAU / 40)}, r"dubins: cell_size must be positive"),
    ("random_walk_1d", {"cell_size": (0.0,)}, r"random_walk_1d: cell_size must be positive"),
    ("dubins", {"cell_size": (0.05, 0.05, 0.3)}, r"dubins: the angle cell size must divide 2\*pi"),
    ("dubins", {"cell_size": (0.05, 0.05, 7.0)}, r"dubins: the angle cell size must divide 2\*pi"),
    ("dubins", {"cell_size": (0.05, 0.05, TAU / 40 * 1.01)}, r"dubins: the angle cell size must divide 2\*pi"),
    ("dubins", {"cell_offset": (0.0, 0.0, 0.5)}, r"dubins: cell_offset .*\|offset\| < 0\.5"),
    ("dubins", {"cell_offset": (-0.5, 0.0, 0.0)}, r"dubins: cell_offset .*\|offset\| < 0\.5"),
    ("random_walk_1d", {"cell_offset": (0.7,)}, r"random_walk_1d: cell_offset .*\|offset\| < 0\.5"),
    ("dubins", {"cell_offset": (0.0, 0.0, float("nan"))}, r"dubins: cell_offset must be finite"),
    ("dubins", {"cell_size": (0.05, 0.05)}, r"dubins: cell_size needs 3 value\(s\).*got 2"),
    ("dubins", {"cell_size": (0.05,) * 4}, r"dubins: cell_size needs 3 value\(s\).*got 4"),
    ("random_walk_1d", {"cell_size": (0.5, 0.5)}, r"random_walk_1d: cell_size needs 1 value\(s\).*got 2"),
    ("dubins", {"cell_offset": (0.0,)}, r"dubins: cell_offset needs 3 value\(s\)"),
    ("dubins", {"cell_size": 0.05}, r"dubins: cell_size must be a sequence of 3 numbers"),
    ("dubins", {"num_actions": 0}, r"dubins: num_actions must be a positive integer .at most 65536., got 0"),
    ("dubins", {"num_actions": -3}, r"dubins: num_actions must be a positive integer"),
    ("dubins", {"num_actions": 2.5}, r"dubins: num_actions must be a positive integer"),
    ("dubins", {"num_actions": True}, r"dubins: num_actions must be a positive integer"),
    ("random_walk_1d", {"num_actions": 0}, r"random_walk_1d: num_actions must be a positive integer"),
]








@pytest.fixture(scope="module")
def policy(dubins_table) -> TablePolicy:
    return TablePolicy(dubins_table)


def goal_cost(states: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
    """``[K, T+1, d]`` -> ``[K]`` squared distance to (1, 0) summed over the horizon."""
    return ((states[:, :, 0] - 1.0) ** 2 + states[:, :, 1] ** 2).sum(dim=1)


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


KINDS = ["mppi", "log_mppi", "cuniform", "cuniform_bank", "cumppi"]


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


@pytest.fixture(scope="module")
def mlp(policy) -> MLPPolicy:
    """A small untrained MLP over the Dubins table's actions (seeded weights)."""
    torch.manual_seed(0)
    config = MLPConfig(state_dim=3, num_actions=policy.num_actions, horizon=policy.horizon,
                       periodic=[False, False, True], feature_scale=[1.0, 1.0, 1.0], hidden=16, layers=1)
    return MLPPolicy(config, policy.system, policy.actions).eval()


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


KS_SPEED_SMALL = dict(cell_size=(0.2, 0.2, 2 * math.pi / 18, 0.2), num_steer=3)




def _entropy(probs: torch.Tensor) -> torch.Tensor:
    return -(probs * probs.clamp_min(1e-30).log()).sum(dim=1)


# ------------------------------------------------------------------------------------------------------------- systems

def test_unknown_system_lists_known_names():
    with pytest.raises(UnknownSystemError, match=r"unknown system 'nope'") as info:
        make_system("nope")
    assert isinstance(info.value, ValueError)
    assert "dubins" in str(info.value) and "random_walk_1d" in str(info.value)


@pytest.mark.parametrize("name, params, bad", [
    ("dubins", {"speeed": 1.0}, "speeed"),
    ("dubins", {"max_speed": 1.0}, "max_speed"),
    ("random_walk_1d", {"speed": 2.0}, "speed"),
    ("random_walk_1d", {"horizon": 3, "v": 1}, "horizon, v"),
])
def test_unknown_parameter_names(name, params, bad):
    with pytest.raises(ValueError, match=rf"system '{name}' has no parameter\(s\) {bad}; its parameters: .*cell_size"):
        make_system(name, **params)


@pytest.mark.parametrize("name, params, match", BAD_PARAMS,
                         ids=[f"{n}-{'-'.join(f'{k}={v!r}' for k, v in p.items())}" for n, p, _ in BAD_PARAMS])
def test_bad_system_parameters(name, params, match):
    with pytest.raises(ValueError, match=match):
        make_system(name, **params)


def test_non_numeric_cell_size_names_the_field():
    with pytest.raises(ValueError, match=r"dubins: cell_size"):
        make_system("dubins", cell_size=("a", "b", "c"))


@pytest.mark.parametrize("x_shape, u_shape, match", [
    ((4, 2), (4, 1), r"dubins\.step: x must have shape \[N, 3\], got \[4, 2\]"),
    ((3,), (1,), r"dubins\.step: x must have shape \[N, 3\], got \[3\]"),
    ((4, 3, 1), (4, 1), r"dubins\.step: x must have shape \[N, 3\], got \[4, 3, 1\]"),
    ((4, 3), (4,), r"dubins\.step: u must have shape \[4, 1\], got \[4\]"),
    ((4, 3), (4, 2), r"dubins\.step: u must have shape \[4, 1\], got \[4, 2\]"),
    ((4, 3), (5, 1), r"dubins\.step: u must have shape \[4, 1\], got \[5, 1\]"),
])
def test_dubins_step_bad_shapes(x_shape, u_shape, match):
    with pytest.raises(ValueError, match=match):
        Dubins().step(torch.zeros(x_shape), torch.zeros(u_shape))


def test_random_walk_step_bad_shapes():
    with pytest.raises(ValueError, match=r"random_walk_1d\.step: x must have shape \[N, 1\], got \[4, 3\]"):
        RandomWalk1D().step(torch.zeros(4, 3), torch.zeros(4, 1))
    with pytest.raises(ValueError, match=r"random_walk_1d\.step: u must have shape \[4, 1\], got \[4, 5\]"):
        RandomWalk1D().step(torch.zeros(4, 1), torch.zeros(4, 5))


# -------------------------------------------------------------------------------------------------- rollout and policy

def test_rollout_valid_control(small_policy):
    states, actions = rollout(small_policy.system, small_policy, torch.zeros(3), 8, HORIZON,
                              generator=torch.Generator().manual_seed(0))
    assert states.shape == (8, HORIZON + 1, 3) and actions.shape == (8, HORIZON, 1)


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_rollout_non_finite_x0(small_policy, bad):
    x0 = torch.tensor([0.0, bad, 0.0])
    with pytest.raises(ValueError, match=r"x0 contains NaN or infinite values"):
        rollout(small_policy.system, small_policy, x0, 4, 2)
    x0 = torch.zeros(4, 3)
    x0[2, 0] = bad
    with pytest.raises(ValueError, match=r"x0 contains NaN or infinite values"):
        rollout(small_policy.system, small_policy, x0, 4, 2)


def test_rollout_names_a_system_whose_step_returns_a_wrong_shape(small_policy):
    class Truncating(Dubins):
        def step(self, x, u):
            return super().step(x, u)[:, :2]

    # probed once, before the rollout (check_dynamics): the shape of the probe's batch, then what it must be
    with pytest.raises(ValueError, match=r"'dubins' \(Truncating\): step\(x, u\).* returned a \[4, 2\] tensor.*must "
                                         r"return \[4, 3\]"):
        rollout(Truncating(), small_policy, torch.zeros(3), 4, 2)


@pytest.mark.parametrize("shape", [(2,), (4,), (5, 3), (4, 2), (4, 3, 1), ()])
def test_rollout_wrong_x0_shape(small_policy, shape):
    with pytest.raises(ValueError, match=rf"x0 must have shape \[3\] or \[4, 3\], got {re.escape(str(list(shape)))}"):
        rollout(small_policy.system, small_policy, torch.zeros(shape), 4, 2)


def test_rollout_horizon_longer_than_table(small_policy):
    with pytest.raises(ValueError, match=rf"horizon {HORIZON + 1} is longer than the policy's table \({HORIZON} steps\)"):
        rollout(small_policy.system, small_policy, torch.zeros(3), 4, HORIZON + 1)


def test_rollout_negative_horizon(small_policy):
    with pytest.raises(ValueError, match=r"horizon"):
        rollout(small_policy.system, small_policy, torch.zeros(3), 4, -1)


def test_rollout_non_integer_horizon(small_policy):
    with pytest.raises((ValueError, TypeError), match=r"horizon"):
        rollout(small_policy.system, small_policy, torch.zeros(3), 4, 2.5)


def test_rollout_negative_num_samples(small_policy):
    with pytest.raises(ValueError, match=r"num_samples"):
        rollout(small_policy.system, small_policy, torch.zeros(3), -2, 2)


def test_rollout_integer_x0(small_policy):
    with pytest.raises(ValueError, match=r"dtype|floating"):
        rollout(small_policy.system, small_policy, torch.zeros(3, dtype=torch.int64), 4, 2)


def test_rows_valid_control(small_policy):
    assert small_policy.rows(torch.zeros(2, 3), 0).tolist() == [0, 0]


@pytest.mark.parametrize("shape", [(4, 2), (3,), (4, 3, 1), (4, 1)])
def test_rows_wrong_state_shape(small_policy, shape):
    with pytest.raises(ValueError, match=rf"states must have shape \[N, 3\], got {re.escape(str(list(shape)))}"):
        small_policy.rows(torch.zeros(shape), 0)


@pytest.mark.parametrize("t", [-1, HORIZON + 1, 100])
def test_rows_level_outside_table(small_policy, t):
    with pytest.raises(ValueError, match=rf"level t={t} is outside the table's levels 0\.\.{HORIZON}"):
        small_policy.rows(torch.zeros(2, 3), t)
    with pytest.raises(ValueError, match=rf"level t={t} is outside"):
        small_policy.action_probs(torch.zeros(2, 3), t)


def test_rows_non_integer_level(small_policy):
    with pytest.raises(ValueError, match=r"level"):
        small_policy.rows(torch.zeros(2, 3), 1.5)


def test_rows_integer_states(small_policy):
    with pytest.raises(ValueError, match=r"dtype|floating"):
        small_policy.rows(torch.zeros(2, 3, dtype=torch.int64), 0)


def test_table_policy_sample_names_a_generator_that_is_not_one(small_policy):
    with pytest.raises(TypeError, match=r"generator must be a torch.Generator or None, got int"):
        small_policy.sample(torch.zeros(4, 3), 0, generator=0)


# -------------------------------------------------------------------------------------------- simulate's runaway limit

def test_simulate_refuses_a_time_limit_of_runaway_steps_before_the_first_step():
    import time

    import torch

    from cuniform_torch.envs.environment import Environment
    from cuniform_torch.envs.sim import simulate
    from cuniform_torch.systems import make_system

    class Counting:
        commands = 0

        def command(self, state):
            Counting.commands += 1
            assert Counting.commands <= 1000, "simulate ran the runaway limit"  # a regression fails, never hangs
            return state.new_zeros(1)

    args = dict(system=make_system("dubins"), controller=Counting(), x0=torch.zeros(3), env=Environment([]),
                goal=(50.0, 50.0), goal_tolerance=0.1)  # unreachable: only the time limit ends the run
    begin = time.perf_counter()
    with pytest.raises(ValueError, match=r"time_limit 1000000000.0 s at dt 0.2 s is 5,000,000,000 steps, more than "
                                         r"the limit of 100,000; .*step_limit=5000000000"):
        simulate(**args, time_limit=1e9)
    assert time.perf_counter() - begin < 2.0 and Counting.commands == 0
    assert simulate(**args, time_limit=0.4, step_limit=2).steps == 2  # within a given limit: runs
    with pytest.raises(ValueError, match="step_limit must be a positive integer"):
        simulate(**args, time_limit=0.4, step_limit=0)


# ----------------------------------------------------------------------------------------------------- background bank

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


# ------------------------------------------------------------------------------------------------------------- lambda_

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


# ---------------------------------------------------------------------------------------------------- states and costs

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


# ------------------------------------------------------------------------------------------------ generators and seeds

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


# ---------------------------------------------------------------------------------------------- MLPPolicy.action_probs

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


# ------------------------------------------------------------------------------------------------------------- devices

def test_an_unindexed_cuda_device_is_the_current_one(monkeypatch):
    """``TablePolicy(table, "cuda")`` keeps ``cuda`` while its tensors say ``cuda:0``: the checks must agree."""
    from cuniform_torch.sampling.rollout import same_device

    monkeypatch.setattr(torch.cuda, "current_device", lambda: 0)  # no GPU needed
    assert same_device("cuda", torch.device("cuda", 0)) and same_device(torch.device("cuda", 0), "cuda")
    assert not same_device("cuda", "cuda:1") and not same_device("cuda", "cpu")
    assert same_device("cpu", torch.device("cpu")) and not same_device("cpu", "meta")


# --------------------------------------------------------------------------- a table from a start it was not built for

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


# ---------------------------------------------------------------------------------- start_relative only where it holds

def test_start_relative_only_on_se2_invariant_systems(walk_table, dubins_table):
    walk, dubins = TablePolicy(walk_table), TablePolicy(dubins_table)
    assert walk.start_relative is False and dubins.start_relative is True
    assert _mlp(walk_table).start_relative is False and _mlp(dubins_table).start_relative is True
    assert not RolloutPlan.of(walk.system, walk).relative and RolloutPlan.of(dubins.system, dubins).relative


# ------------------------------------------------------------------------------------------- the MLP knows its support

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


# ----------------------------------------------------------------------- se2_invariance_gap on a system without a pose

def test_se2_invariance_gap_needs_a_pose():
    with pytest.raises(ValueError, match=r"'random_walk_1d' has 1 state dimension.*\(x, y, theta, \.\.\.\)"):
        se2_invariance_gap(make_system("random_walk_1d"))
    assert se2_invariance_gap(make_system("dubins")) < 1e-9
