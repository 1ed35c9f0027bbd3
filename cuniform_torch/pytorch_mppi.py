"""pytorch_mppi's ``MPPI`` and ``MPPI_Batched``, same signatures, on this library's MPPI core: switching is the import
line.

    from pytorch_mppi import MPPI                  ->  from cuniform_torch.pytorch_mppi import MPPI
    from pytorch_mppi import mppi; mppi.MPPI(...)  ->  from cuniform_torch import pytorch_mppi as mppi

Shapes: K samples, T horizon, nx state dimensions, nu action dimensions, N environments (robots).

What is kept (pytorch_mppi 0.9.1's semantics): the positional order and names; ``dynamics(state [K, nx], action [K,
nu]) -> [K, nx]``; ``running_cost(state, action) -> [K]`` of the state each action led to; ``terminal_state_cost(
states [1, K, T, nx], actions [1, K, T, nu])``; ``noise_sigma`` a covariance (its dtype is the controller's; a full
matrix is sampled through its Cholesky factor); ``noise_mu``; ``u_min`` / ``u_max`` (one gives the other's
negative; none: unbounded); ``u_init`` appended when the nominal shifts, at the start of each command;
``U_init``; ``u_scale``; ``u_per_command``; ``sample_null_action``; ``noise_abs_cost``; the control cost ``lambda
U Sigma^-1 eps`` in each sample's cost; ``command(state)`` converting the state to the controller's dtype and device
and returning a tensor; ``reset()``, ``U``, ``get_action_sequence()``, ``get_rollouts()``, ``cost_total`` and
``omega`` after a command.

What differs, on purpose: the random numbers come from the controller's own stream (``seed=``, a keyword; without
it, a seed is drawn from torch's global generator at construction, so ``torch.manual_seed`` still makes a run
repeat), not from the global generator (the first nominal without ``U_init``, and ``reset()``'s, is a noise draw
from that stream, as pytorch_mppi's is from the global one); ``running_cost`` is called once per command on all K*T rows (it must be row-wise);
``MPPI_Batched`` draws independent noise per environment (pytorch_mppi shares one draw). Refused with one
ValueError (never ignored): ``step_dependent_dynamics``, ``rollout_samples`` > 1 (and its ``rollout_var_*``),
``specific_action_sampler``, ``change_horizon``, ``compile``, a ``[K, nx]`` batch of start states.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from cuniform_torch.common.checks import check_positive_int
from cuniform_torch.controllers.callables import (
    CallableProposal,
    DynamicsFn,
    RunningCostFn,
    TerminalStateCostFn,
    resolve,
    with_options,
)
from cuniform_torch.controllers.core import MPPICore
from cuniform_torch.controllers.result import MPPIResult
from cuniform_torch.sampling.rollout import open_loop

__all__ = ["MPPI", "MPPI_Batched"]


def _refuse(who: str, given: dict[str, tuple[object, object]]) -> None:
    """One ValueError listing every pytorch_mppi argument given that this drop-in does not do."""
    bad = [f"{name}={value!r}" for name, (value, default) in given.items() if value != default]
    if bad:
        raise ValueError(f"cuniform_torch.pytorch_mppi.{who} does not support {', '.join(bad)} (pytorch_mppi's "
                         f"stochastic rollouts, step-dependent dynamics and specific action samplers are not "
                         f"implemented here): leave them at their defaults, or keep pytorch_mppi for this controller")


class MPPI:
    """pytorch_mppi's ``MPPI`` (one robot) on :class:`~cuniform_torch.controllers.core.MPPICore`; see the module
    for what is kept and what differs.

    :param dynamics: ``(state [K, nx], action [K, nu]) -> [K, nx]``
    :param running_cost: ``(state [K, nx], action [K, nu]) -> [K]``, the state each action led to
    :param nx: the state dimension
    :param noise_sigma: ``[nu, nu]`` noise covariance (or a 0-d variance: nu = 1); its dtype is the controller's
    :param num_samples: K
    :param horizon: T
    :param device: where the controller runs
    :param terminal_state_cost: ``(states [1, K, T, nx], actions [1, K, T, nu]) -> [1, K]``
    :param lambda_: the temperature
    :param noise_mu: ``[nu]`` the noise's mean
    :param u_min: ``[nu]`` lower action bounds (default ``-u_max``; none: unbounded)
    :param u_max: ``[nu]`` upper action bounds (default ``-u_min``)
    :param u_init: ``[nu]`` appended when the nominal shifts (default zeros)
    :param U_init: ``[T, nu]`` the first nominal (default: a draw of the noise at every step)
    :param u_scale: actions are scaled by it before the dynamics and costs see them
    :param u_per_command: actions returned per command (1: ``[nu]``; more: ``[u_per_command, nu]``)
    :param step_dependent_dynamics: refused when True
    :param rollout_samples: refused unless 1
    :param rollout_var_cost: refused unless 0
    :param rollout_var_discount: refused unless 0.95
    :param sample_null_action: sample 0 is the zero action sequence
    :param specific_action_sampler: refused unless None
    :param noise_abs_cost: the control cost with ``|eps|``
    :param seed: the controller's random stream (default: drawn from torch's global generator)
    """

    _num_robots = 1

    def __init__(self, dynamics: DynamicsFn, running_cost: RunningCostFn, nx: int, noise_sigma: Tensor,
                 num_samples: int = 100, horizon: int = 15, device: torch.device | str = "cpu",
                 terminal_state_cost: TerminalStateCostFn | None = None, lambda_: float = 1.0,
                 noise_mu: Tensor | None = None, u_min: Tensor | float | None = None,
                 u_max: Tensor | float | None = None, u_init: Tensor | None = None, U_init: Tensor | None = None,
                 u_scale: float = 1, u_per_command: int = 1, step_dependent_dynamics: bool = False,
                 rollout_samples: int = 1, rollout_var_cost: float = 0, rollout_var_discount: float = 0.95,
                 sample_null_action: bool = False, specific_action_sampler: Any = None,
                 noise_abs_cost: bool = False, *, seed: int | None = None):
        who = type(self).__name__
        _refuse(who, {"step_dependent_dynamics": (step_dependent_dynamics, False),
                      "rollout_samples": (rollout_samples, 1), "rollout_var_cost": (rollout_var_cost, 0),
                      "rollout_var_discount": (rollout_var_discount, 0.95),
                      "specific_action_sampler": (specific_action_sampler, None)})
        if isinstance(u_per_command, bool) or not isinstance(u_per_command, int) or not 1 <= u_per_command <= horizon:
            raise ValueError(f"u_per_command must be an integer in [1, horizon = {horizon}], got {u_per_command!r}")
        parts = resolve(who, dynamics, None, nx=nx, running_cost=running_cost,
                        terminal_state_cost=terminal_state_cost, noise_sigma=noise_sigma, noise_mu=noise_mu,
                        u_min=u_min, u_max=u_max, u_init=0.0 if u_init is None else u_init, U_init=U_init,
                        control_cost=True, u_scale=u_scale)
        options = with_options(parts, shift_first=True, sample_null_action=bool(sample_null_action),
                               noise_abs_cost=bool(noise_abs_cost))
        if seed is None:  # torch.manual_seed(s) before construction repeats a run, as it does for pytorch_mppi
            seed = int(torch.randint(0, 2**62, (1,)).item())
        self._proposal = CallableProposal(parts.system, num_samples, horizon, parts.noise_std, options, device,
                                          parts.dtype, self._num_robots)
        self.controller = MPPICore(self._proposal, parts.cost_fn, lambda_, seed=seed)
        """the core doing the work (``controller.plan(state)``: one iteration, the nominal left as it was)"""
        self.K, self.T, self.nx, self.nu = num_samples, horizon, nx, self._proposal.low.shape[0]
        self.lambda_ = lambda_
        self.d = torch.device(device)
        self.dtype = parts.dtype
        self.u_min, self.u_max = self._proposal.low, self._proposal.high
        self.u_init = self._proposal.u_init
        self.u_scale, self.u_per_command = u_scale, u_per_command
        self.noise_mu = (self._proposal.noise_mu if self._proposal.noise_mu is not None
                         else torch.zeros(self.nu, dtype=self.dtype, device=self.d))
        self.noise_sigma = torch.as_tensor(noise_sigma, dtype=self.dtype).to(self.d).reshape(self.nu, self.nu)
        self.cost_total: Tensor | None = None
        """``[K]`` each sample's cost in the latest command (``[N, K]`` batched)"""
        self.omega: Tensor | None = None
        """``[K]`` each sample's weight in the latest command"""
        self.result: MPPIResult | None = None
        """the latest command's whole result"""
        if U_init is None:
            self._noise_nominal()

    def _noise_nominal(self) -> None:
        """pytorch_mppi's first nominal (and its reset's): a draw of the noise ``N(noise_mu, Sigma)`` at every step,
        each robot's from its own stream."""
        self._proposal.nominal = self._proposal._noise(self.controller.streams, self.T)  # [B, T, nu]

    # ------------------------------------------------------------------------------------------ pytorch_mppi's API

    def command(self, state: Any, shift_nominal_trajectory: bool = True, info: Any = None) -> Tensor:
        """The action to apply at ``state [nx]`` (a tensor, array or sequence, converted to the controller's dtype
        and device): ``[nu]`` (``[u_per_command, nu]`` for more). ``shift_nominal_trajectory=False`` refines the
        nominal without shifting it first. ``info`` is pytorch_mppi's context for a specific action sampler (which
        this drop-in refuses), unused."""
        states = self._states(state)
        if shift_nominal_trajectory:
            self._proposal.shift()
        result = self.controller.command_result(states)  # [B, ...]
        self.result, self.cost_total, self.omega = result, result.costs, result.weights
        if self._num_robots == 1:
            self.cost_total, self.omega = result.costs[0], result.weights[0]
        actions = result.nominal[:, :self.u_per_command]  # [B, n, nu]
        actions = actions[:, 0] if self.u_per_command == 1 else actions
        return actions[0] if self._num_robots == 1 else actions

    def _states(self, state: Any) -> Tensor:
        """``state`` as pytorch_mppi converts it (to the controller's dtype and device), ``[B, nx]``."""
        x = state if isinstance(state, Tensor) else torch.as_tensor(state)
        x = x.to(dtype=self.dtype, device=self.d)
        b = self._num_robots
        if b == 1 and x.shape in ((self.nx,), (1, self.nx)):
            return x.reshape(1, self.nx)
        if b > 1 and x.shape == (b, self.nx):
            return x
        want = f"[{self.nx}]" if b == 1 else f"[{b}, {self.nx}] (one state per environment)"
        more = (" (a batch of sampled start states, pytorch_mppi's state distribution, is not supported: one state "
                "per robot; MPPI_Batched runs many robots)") if b == 1 and x.ndim == 2 else ""
        raise ValueError(f"state must be {want}, got {list(x.shape)}{more}")

    @property
    def U(self) -> Tensor:
        """The nominal action sequence ``[T, nu]`` (``[N, T, nu]`` batched); assignable."""
        return self._proposal.nominal

    @U.setter
    def U(self, value: Tensor) -> None:
        self._proposal.nominal = torch.as_tensor(value).to(dtype=self.dtype, device=self.d)

    def get_action_sequence(self) -> Tensor:
        """The nominal action sequence (``U``)."""
        return self.U

    def shift_nominal_trajectory(self) -> None:
        """Shift the nominal one step, appending ``u_init``."""
        self._proposal.shift()

    def reset(self) -> None:
        """A new episode: a fresh noise draw as the nominal (pytorch_mppi's reset)."""
        self._noise_nominal()

    def get_rollouts(self, state: Any, num_rollouts: int = 1, U: Tensor | None = None) -> Tensor:
        """The states the nominal (or ``U [T, nu]``) drives from ``state [nx]``: ``[num_rollouts, T, nx]``
        (the start left out, as pytorch_mppi's)."""
        x = self._states(state)[0]
        seq = self.U if U is None else torch.as_tensor(U).to(dtype=self.dtype, device=self.d)
        if seq.ndim != 2:
            raise ValueError(f"U must be [T, nu], got {list(seq.shape)}")
        return open_loop(self._proposal.system, x, seq.expand(num_rollouts, *seq.shape))[:, 1:]

    def get_params(self) -> str:
        return (f"K={self.K} T={self.T} M=1 lambda={self.lambda_} noise_mu={self.noise_mu.cpu().numpy()} "
                f"noise_sigma={self.noise_sigma.cpu().numpy()}").replace("\n", ",")

    def change_horizon(self, horizon: int) -> None:
        raise ValueError("change_horizon is not supported: the controller's shapes are fixed at construction; make a "
                         "new controller with horizon=")

    def compile(self, **kwargs: Any) -> None:
        raise ValueError("compile is not supported; the command is one tensor program already (on CUDA, "
                         "cuniform_torch.MPPI(..., cuda_graph=True) replays it as one CUDA graph)")


class MPPI_Batched(MPPI):
    """pytorch_mppi's ``MPPI_Batched``: N environments (robots) in one call, ``command(states [N, nx]) -> [N, nu]``
    (each robot its own nominal, weights and noise stream: robot ``b`` of ``seed`` s draws from ``s + b *
    1_000_003``). Parameters as :class:`MPPI`'s, with ``num_envs`` (N) fifth.

    :param num_envs: N, robots per call
    """

    def __init__(self, dynamics: DynamicsFn, running_cost: RunningCostFn, nx: int, noise_sigma: Tensor,
                 num_envs: int, num_samples: int = 100, horizon: int = 15, device: torch.device | str = "cpu",
                 lambda_: float = 1.0, noise_mu: Tensor | None = None, u_min: Tensor | float | None = None,
                 u_max: Tensor | float | None = None, u_init: Tensor | None = None, u_scale: float = 1,
                 u_per_command: int = 1, step_dependent_dynamics: bool = False, noise_abs_cost: bool = False, *,
                 seed: int | None = None):
        check_positive_int("num_envs", num_envs, integral=False)
        self._num_robots = num_envs
        self.N = num_envs
        super().__init__(dynamics, running_cost, nx, noise_sigma, num_samples, horizon, device, lambda_=lambda_,
                         noise_mu=noise_mu, u_min=u_min, u_max=u_max, u_init=u_init, u_scale=u_scale,
                         u_per_command=u_per_command, step_dependent_dynamics=step_dependent_dynamics,
                         noise_abs_cost=noise_abs_cost, seed=seed)

    def command(self, states: Any, shift_nominal_trajectory: bool = True,  # type: ignore[override]
                info: Any = None) -> Tensor:
        """The actions at ``states [N, nx]``: ``[N, nu]`` (``[N, u_per_command, nu]``)."""
        return super().command(states, shift_nominal_trajectory, info)

