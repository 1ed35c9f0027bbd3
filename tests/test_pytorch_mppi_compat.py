"""pytorch_mppi's convention (issue 34, items 1, 3, 4): MPPI given a dynamics function and pytorch_mppi's keywords,
the drop-in ``cuniform_torch.pytorch_mppi``, the noise default from the bounds, the automatic temperature, and the
errors that say what to do.

The cross-check against pytorch_mppi itself (same noise in, same command and costs out) runs where it is installed
(the ``[bench]`` extra) and is skipped elsewhere.
"""

from __future__ import annotations

import difflib
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from cuniform_torch import MPPI, LogMPPI, make_system
from cuniform_torch.controllers import ColoredMPPI, LowPassMPPI
from cuniform_torch.controllers.callables import covariance_to_noise
from cuniform_torch.controllers.temperature import auto_temperature
from cuniform_torch.pytorch_mppi import MPPI as DropIn
from cuniform_torch.pytorch_mppi import MPPI_Batched as DropInBatched

ROOT = Path(__file__).resolve().parents[1]


def dynamics(state, action):
    """The pendulum (gym's Pendulum-v1): ``[K, 2]``, ``[K, 1]`` -> ``[K, 2]``."""
    th, thdot = state[:, 0:1], state[:, 1:2]
    u = torch.clamp(action, -2, 2)
    newthdot = torch.clamp(thdot + (15.0 * torch.sin(th) + 3.0 * u) * 0.05, -8, 8)
    return torch.cat((th + newthdot * 0.05, newthdot), dim=1)


def running_cost(state, action):
    return ((state[:, 0] + math.pi) % (2 * math.pi) - math.pi) ** 2 + 0.1 * state[:, 1] ** 2


def trajectory_cost(states, actions):
    return running_cost(states[:, 1:].reshape(-1, 2), None).view(states.shape[0], -1).sum(dim=1)


def _make(**overrides):
    """A pytorch_mppi-style MPPI of the pendulum (float64 through noise_sigma)."""
    kw = dict(nx=2, running_cost=running_cost, noise_sigma=torch.tensor(10.0, dtype=torch.float64), u_min=-2.0,
              u_max=2.0, num_samples=64, horizon=10, lambda_=1.0, seed=0)
    kw.update(overrides)
    return MPPI(dynamics, **kw)


# ------------------------------------------------------------------------------------------ the signature

class TestSignature:
    def test_a_dynamics_function_with_pytorch_mppis_keywords_commands(self):
        ctrl = _make()
        assert ctrl.dtype == torch.float64  # noise_sigma's dtype, as pytorch_mppi
        u = ctrl.command(torch.tensor([math.pi, 1.0], dtype=torch.float64))
        assert u.shape == (1,) and u.dtype == torch.float64 and -2 <= float(u) <= 2

    @pytest.mark.parametrize("np_dtype", [np.float64, np.float32])
    def test_a_numpy_state_gets_a_numpy_command_of_its_dtype(self, np_dtype):
        u = _make().command(np.array([math.pi, 1.0], dtype=np_dtype))
        assert isinstance(u, np.ndarray) and u.dtype == np_dtype and u.shape == (1,)

    def test_a_float64_state_on_a_float32_controller_is_converted_once_and_comes_back_float64(self):
        ctrl = _make(noise_sigma=None, noise_std=1.0)
        assert ctrl.dtype == torch.float32
        u = ctrl.command(torch.tensor([math.pi, 1.0], dtype=torch.float64))
        assert u.dtype == torch.float64
        same = _make(noise_sigma=None, noise_std=1.0).command(torch.tensor([math.pi, 1.0]))
        torch.testing.assert_close(u.float(), same)

    def test_a_batched_numpy_state(self):
        ctrl = _make(num_robots=3, seed=[1, 2, 3])
        u = ctrl.command(np.array([[math.pi, 1.0], [0.1, 0.0], [-2.0, 3.0]]))
        assert isinstance(u, np.ndarray) and u.shape == (3, 1)
        alone = [_make(seed=s).command(np.array(x)) for s, x in zip((1, 2, 3), ([math.pi, 1.0], [0.1, 0.0],
                                                                               [-2.0, 3.0]))]
        np.testing.assert_allclose(u, np.stack(alone), rtol=0, atol=1e-12)

    @pytest.mark.parametrize("cls", [LogMPPI, ColoredMPPI, LowPassMPPI])
    def test_the_other_gaussian_controllers_take_a_dynamics_function_too(self, cls):
        ctrl = cls(dynamics, nx=2, running_cost=running_cost, u_min=-2.0, u_max=2.0, num_samples=32, horizon=6,
                   seed=0)
        assert ctrl.proposal.std.tolist() == [1.0]  # the noise from the bounds
        u = ctrl.command(np.array([math.pi, 1.0]))
        assert isinstance(u, np.ndarray) and u.shape == (1,) and -2 <= float(u[0]) <= 2

    def test_a_trajectory_cost_with_a_dynamics_function(self):
        u = MPPI(dynamics, trajectory_cost, 64, 10, nx=2, u_min=-2.0, u_max=2.0, seed=0).command(np.zeros(2))
        assert u.shape == (1,)

    def test_running_cost_equals_the_trajectory_cost_it_sums(self):
        a = _make(control_cost=False).command(torch.tensor([2.0, 0.5], dtype=torch.float64))
        b = MPPI(dynamics, trajectory_cost, 64, 10, 1.0, nx=2, noise_sigma=torch.tensor(10.0, dtype=torch.float64),
                 u_min=-2.0, u_max=2.0, control_cost=False, seed=0).command(
            torch.tensor([2.0, 0.5], dtype=torch.float64))
        torch.testing.assert_close(a, b)

    def test_the_drop_in_keeps_pytorch_mppis_positional_order_and_returns_a_tensor(self):
        torch.manual_seed(0)
        ctrl = DropIn(dynamics, running_cost, 2, torch.tensor(10.0, dtype=torch.float64), 64, 10, "cpu", None, 1.0)
        u = ctrl.command(np.array([math.pi, 1.0]))  # a numpy state, as gym gives; a tensor back, as pytorch_mppi
        assert isinstance(u, torch.Tensor) and u.dtype == torch.float64 and u.shape == (1,)
        assert ctrl.cost_total.shape == (64,) and ctrl.U.shape == (10, 1)
        assert ctrl.get_rollouts(np.array([math.pi, 1.0]), 3).shape == (3, 10, 2)

    def test_torch_manual_seed_repeats_a_drop_in_run(self):
        def run():
            torch.manual_seed(7)
            ctrl = DropIn(dynamics, running_cost, 2, torch.tensor(10.0, dtype=torch.float64), 32, 8)
            return torch.stack([ctrl.command(torch.tensor([1.0, 0.0])) for _ in range(3)])

        torch.testing.assert_close(run(), run())

    def test_the_batched_drop_in_commands_what_its_robots_would_alone(self):
        sigma = torch.tensor(10.0, dtype=torch.float64)
        states = torch.tensor([[math.pi, 1.0], [0.3, -1.0]], dtype=torch.float64)
        batched = DropInBatched(dynamics, running_cost, 2, sigma, 2, 32, 8, u_min=-2.0, seed=5)
        alone = [DropIn(dynamics, running_cost, 2, sigma, 32, 8, u_min=-2.0, seed=5 + b * 1_000_003) for b in (0, 1)]
        for _ in range(3):
            u = batched.command(states)
            assert u.shape == (2, 1)
            torch.testing.assert_close(u, torch.stack([c.command(x) for c, x in zip(alone, states)]))

    def test_the_user_script_twins_differ_by_the_import_line_only(self):
        a, b = (ROOT / "eval" / "bench" / f"pendulum_user_{n}.py" for n in ("pytorch_mppi", "cuniform"))
        changed = [line for line in difflib.unified_diff(a.read_text().splitlines(), b.read_text().splitlines(),
                                                         lineterm="", n=0)
                   if line[:1] in "+-" and not line.startswith(("+++", "---"))]
        assert changed == ["-from pytorch_mppi import MPPI", "+from cuniform_torch.pytorch_mppi import MPPI"]

    def test_the_cuniform_user_script_runs(self):
        from eval.bench import pendulum_user_cuniform

        assert math.isfinite(pendulum_user_cuniform.run(0, steps=5))


# ------------------------------------------------------------------------------------------ pytorch_mppi itself

class TestAgainstPytorchMppi:
    """Same noise in, same command and costs out: the semantics (the next state's running cost, the terminal cost
    of the states after each step, the control cost lambda U Sigma^-1 eps, u_scale, the shift before the command
    that appends u_init, the clamp to the bounds) are pytorch_mppi's."""

    @pytest.mark.parametrize("case", ["diagonal", "full", "bounded"])
    def test_one_command_equals_pytorch_mppis_with_the_same_noise(self, case):
        pytorch_mppi = pytest.importorskip("pytorch_mppi")
        k, t = 48, 7
        dyn = lambda x, u: torch.cat((x[:, :2] + 0.1 * x[:, 2:], x[:, 2:] + 0.1 * u), 1)  # noqa: E731
        cost = lambda x, u: (x[:, :2] ** 2).sum(1) + 0.01 * (u**2).sum(1)  # noqa: E731
        terminal = lambda s, a: 10 * (s[..., -1, :2] ** 2).sum(-1)  # noqa: E731  # [1, K, T, d] -> [1, K]
        sigma = (torch.tensor([[0.5, 0.2], [0.2, 0.3]]) if case == "full" else torch.diag(torch.tensor([0.5, 0.3])))
        sigma = sigma.double()
        kw = dict(num_samples=k, horizon=t, lambda_=0.7, terminal_state_cost=terminal, u_scale=1.5,
                  u_init=torch.tensor([0.1, -0.2], dtype=torch.float64),
                  U_init=torch.linspace(-1, 1, t * 2, dtype=torch.float64).view(t, 2))
        if case == "bounded":
            kw.update(u_min=torch.tensor([-0.4, -0.6], dtype=torch.float64), u_max=torch.tensor([0.5, 0.6],
                                                                                                dtype=torch.float64))
        ours = DropIn(dyn, cost, 4, sigma, seed=3, **kw)
        state = torch.tensor([1.0, -0.5, 0.2, 0.3], dtype=torch.float64)
        u = ours.command(state)
        noise = ours.result.actions[0] - _shifted(kw["U_init"], kw["u_init"])  # [K, T, nu]: clipped, so theirs is too
        theirs = pytorch_mppi.MPPI(dyn, cost, 4, sigma, **kw)
        theirs._sample_noise = lambda shape: noise.clone()  # the noise our command drew
        torch.testing.assert_close(theirs.command(state), u, rtol=1e-10, atol=1e-10)
        torch.testing.assert_close(theirs.cost_total, ours.cost_total, rtol=1e-10, atol=1e-10)
        torch.testing.assert_close(theirs.U, ours.U, rtol=1e-10, atol=1e-10)


def _shifted(U, u_init):
    return torch.cat((U[1:], u_init.view(1, -1)))


# ------------------------------------------------------------------------------------------ the noise

class TestNoise:
    def test_a_scalar_variance_and_a_diagonal_covariance_are_a_std(self):
        std, chol, inv = covariance_to_noise(torch.tensor(10.0))
        assert chol is None and torch.allclose(std, torch.tensor([math.sqrt(10)], dtype=torch.float64))
        std, chol, inv = covariance_to_noise(torch.diag(torch.tensor([4.0, 0.25])))
        assert chol is None and std.tolist() == [2.0, 0.5]
        torch.testing.assert_close(inv, torch.diag(torch.tensor([0.25, 4.0], dtype=torch.float64)))

    def test_a_full_covariance_is_sampled_with_its_correlation(self):
        sigma = torch.tensor([[1.0, 0.8], [0.8, 2.0]], dtype=torch.float64)
        ctrl = MPPI(lambda x, u: x + u.sum(1, keepdim=True), nx=1, running_cost=lambda x, u: x[:, 0] ** 2,
                    noise_sigma=sigma, num_samples=20000, horizon=2, seed=0)
        result = ctrl.plan(torch.zeros(1, dtype=torch.float64))  # unbounded, nominal 0: the actions are the noise
        eps = result.actions.reshape(-1, 2)
        torch.testing.assert_close(torch.cov(eps.T), sigma, rtol=0, atol=0.06)

    def test_the_default_noise_is_a_quarter_of_the_action_range(self):
        ctrl = MPPI(dynamics, nx=2, running_cost=running_cost, u_min=-2.0, u_max=2.0)
        assert ctrl.proposal.std.tolist() == [1.0]
        dubins = make_system("dubins")
        ctrl = MPPI(dubins, lambda s, a: s[:, -1, 0], num_samples=8, horizon=4)
        torch.testing.assert_close(ctrl.proposal.std, torch.tensor([math.pi / 8]))
        assert MPPI(dubins, lambda s, a: s[:, -1, 0], 8, 4, noise_std=0.3).proposal.std.tolist() == [
            pytest.approx(0.3)]  # a noise given is kept

    def test_noise_mu_shifts_the_noise(self):
        ctrl = MPPI(lambda x, u: x + u, nx=1, running_cost=lambda x, u: x[:, 0] ** 2, noise_std=0.1,
                    noise_mu=2.0, num_samples=4000, horizon=2, seed=0)
        assert abs(float(ctrl.plan(torch.zeros(1)).actions.mean()) - 2.0) < 0.01


# ------------------------------------------------------------------------------------------ the temperature

class TestAutoTemperature:
    @pytest.mark.parametrize("target", [2.0, 10.0, 40.0])
    def test_the_command_reaches_its_target_ess_for_every_robot(self, target):
        ctrl = _make(lambda_="auto", target_ess=target, num_robots=4, seed=[0, 1, 2, 3])
        states = torch.tensor([[math.pi, 1.0], [0.1, 0.0], [-2.0, 3.0], [1.0, -4.0]], dtype=torch.float64)
        for _ in range(3):
            result = ctrl.command_result(states)
            assert result.lambda_.shape == (4,) and bool((result.lambda_ > 0).all())
            assert torch.allclose(result.ess, torch.full((4,), target, dtype=torch.float64), rtol=0.02), result.ess

    def test_it_is_the_smallest_lambda_at_the_target_and_scales_with_the_costs(self):
        costs = torch.rand(5, 200, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 50
        lam = auto_temperature(costs, 20.0)

        def ess(c, lam):
            w = torch.softmax(-(c - c.amin(1, keepdim=True)) / lam[:, None], dim=1)
            return 1 / (w**2).sum(1)

        assert bool((ess(costs, lam) >= 20).all()) and bool((ess(costs, lam * 0.995) < 20).all())
        torch.testing.assert_close(auto_temperature(costs * 10, 20.0), lam * 10, rtol=1e-3, atol=0)

    def test_a_fixed_lambda_is_reported_too(self):
        result = _make(lambda_=0.5).command_result(np.array([1.0, 0.0]))
        assert float(result.lambda_) == 0.5 and 1 <= float(result.ess) <= 64


# ------------------------------------------------------------------------------------------ errors

class TestErrors:
    def test_a_function_where_a_system_was_expected_names_the_two_ways(self):
        with pytest.raises(ValueError, match=r"got the function dynamics where a System was expected.*a System .*"
                                             r"trajectory cost.*or the function itself.*nx=d, running_cost="):
            MPPI(dynamics, trajectory_cost)

    def test_a_numpy_state_for_a_system_controller_names_the_fixes(self):
        ctrl = MPPI(make_system("dubins"), lambda s, a: s[:, -1, 0], 8, 4)
        with pytest.raises(ValueError, match=r"got ndarray: pass torch\.as_tensor\(state, dtype=torch\.float32.*"
                                             r"convert_states=True"):
            ctrl.command(np.zeros(3))
        assert isinstance(MPPI(make_system("dubins"), lambda s, a: s[:, -1, 0], 8, 4, convert_states=True).command(
            np.zeros(3)), np.ndarray)

    def test_a_float64_state_names_dtype_and_convert_states(self):
        ctrl = MPPI(make_system("dubins"), lambda s, a: s[:, -1, 0], 8, 4)
        with pytest.raises(ValueError, match=r"pass state\.to\(torch\.float32\), or build the controller with "
                                             r"dtype=torch\.float64 \(or convert_states=True"):
            ctrl.command(torch.zeros(3, dtype=torch.float64))

    @pytest.mark.parametrize("steps", ["T", "T+1"])
    def test_a_per_step_cost_given_as_the_trajectory_cost(self, steps):
        def per_step(states, actions):  # [N, T+1, d] -> [N, T(+1)]: forgot the sum
            s = states[:, 1:] if steps == "T" else states
            return s[..., 0] ** 2

        with pytest.raises(ValueError, match=r"cost_fn .*per_step.* returned a \[8, \d+\] tensor.*is a cost per step: "
                                             r"sum it over the steps.*running_cost="):
            MPPI(make_system("dubins"), per_step, 8, 4).command(torch.zeros(3))

    def test_a_running_cost_of_the_wrong_shape_names_it(self):
        with pytest.raises(ValueError, match=r"running_cost .*<lambda>.* returned a \[640, 2\] tensor.*expected "
                                             r"\[640\] \(one cost per row"):
            _make(running_cost=lambda x, u: x ** 2).command(np.zeros(2))

    def test_the_drop_in_refuses_what_it_does_not_do_in_one_error(self):
        with pytest.raises(ValueError, match=r"does not support step_dependent_dynamics=True, rollout_samples=4"):
            DropIn(dynamics, running_cost, 2, torch.tensor(1.0), step_dependent_dynamics=True, rollout_samples=4)
        ctrl = DropIn(dynamics, running_cost, 2, torch.tensor(1.0), 8, 4, seed=0)
        with pytest.raises(ValueError, match="change_horizon is not supported"):
            ctrl.change_horizon(8)
        with pytest.raises(ValueError, match=r"a batch of sampled start states.*is not supported"):
            ctrl.command(torch.zeros(5, 2))

    @pytest.mark.parametrize("kw, match", [
        (dict(noise_sigma=torch.tensor([1.0, 2.0])), r"covariance matrix \[nu, nu\].*torch\.diag\(v\).*noise_std="),
        (dict(noise_sigma=torch.tensor([[1.0, 0.5], [0.0, 1.0]])), r"must be symmetric"),
        (dict(noise_sigma=torch.tensor([[1.0, 2.0], [2.0, 1.0]])), r"positive definite"),
        (dict(noise_std=1.0), r"noise_std .* or noise_sigma .*, not both"),
        (dict(noise_sigma=None, u_min=None, u_max=None), r"no noise scale was given and the action bounds.*give "
                                                          r"noise_std .* or noise_sigma"),
        (dict(nx=None), r"where a System was expected"),
        (dict(target_ess=5), r"target_ess=5 sets the automatic temperature: pass lambda_=\"auto\""),
        (dict(lambda_="auto", target_ess=500), r"target_ess must be a number of samples between 1 and num_samples"),
        (dict(u_min=torch.tensor([-1.0, -1.0])), r"the action dimension differs between arguments"),
    ])
    def test_bad_pytorch_style_arguments(self, kw, match):
        with pytest.raises(ValueError, match=match):
            _make(**kw)

    def test_u_min_with_a_system_and_a_full_covariance_for_log_mppi(self):
        with pytest.raises(ValueError, match=r"u_min / u_max bound a dynamics function's actions; a System's"):
            MPPI(make_system("dubins"), lambda s, a: s[:, -1, 0], u_min=-1.0)
        with pytest.raises(ValueError, match=r"LogMPPI draws its own noise.*use MPPI"):
            LogMPPI(dynamics, nx=2, running_cost=running_cost, u_min=-2.0,
                    noise_sigma=torch.tensor([[1.0, 0.5], [0.5, 1.0]]))
