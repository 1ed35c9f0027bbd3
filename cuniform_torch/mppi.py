"""The MPPI family on one core: MPPI, log-MPPI, C-Uniform MPPI and CU-MPPI.

Shapes: K samples (proposals), T horizon, d state dimensions, q action dimensions.

Every controller does the same three things per command, and differs only in how it proposes trajectories:

1. propose K trajectories ``states [K, T+1, d]``, ``actions [K, T, q]`` from the current state;
2. cost each one, ``cost_fn(states, actions) -> [K]`` (+ ``terminal_cost(states[:, -1]) -> [K]``); NaN and
   +-inf (e.g. the paper's infinite collision cost) become a large finite penalty, so weights never go NaN;
3. weight them, ``w = softmax(-(cost - min cost) / lambda)`` (``lambda = 0``: all weight on the best one), and
   return the weighted average of the proposals' first actions.

* :class:`MPPI` samples Gaussian noise around a nominal sequence, updates the nominal to the weighted average
  of the sampled sequences, and warm-starts the next command by shifting it one step.
* :class:`LogMPPI` is MPPI with normal x log-normal noise (Mohamed et al.).
* :class:`CUniformMPPI` (the C-Uniform paper) proposes C-Uniform rollouts of a policy (a table or an MLP)
  from the robot's pose; optionally from a *proposal bank* of pre-sampled rollouts at the origin, so that a
  command is a random subset + a rigid transform + cost + weights.
* :class:`CUMPPI` (arXiv 2503.05819) makes the lowest-cost C-Uniform rollout the nominal of one local MPPI or
  log-MPPI pass and applies that pass's first control.

Bad input is refused with one ValueError or TypeError naming it: a ``lambda_`` that the controller's dtype
cannot hold (or whose inverse overflows it), a ``seed`` that is not an integer, a state of the wrong shape,
dtype or device or with NaN, and a cost (or terminal cost) that is not a ``[K]`` tensor of the controller's dtype
and device, or is NaN for every proposal. A state that requires grad is detached (a controller never
differentiates through its input).
"""

from __future__ import annotations

import math
import numbers
import warnings
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor

from .envs.costs import TrajectoryCost
from .frames import se2_to_world
from .rollout import Policy, rollout, same_device
from .samplers import GaussianSampler, NormalLogNormalSampler
from .systems import System

__all__ = ["CostFn", "MPPIResult", "mppi_weights", "MPPI", "LogMPPI", "CUniformMPPI", "CUMPPI", "COST_CAP",
           "BankRefreshWarning"]

COST_CAP = 1e10
"""NaN / inf costs are replaced by this finite value before weighting"""


CostFn = TrajectoryCost
"""Trajectory cost: ``states [K, T+1, d]``, ``actions [K, T, q]`` -> ``[K]`` (may be inf for collisions)."""


class BankRefreshWarning(RuntimeWarning):
    """A background bank refresh of :class:`CUniformMPPI` raised; the controller goes on with its current bank."""


@dataclass
class MPPIResult:
    """One command's work (returned, not kept as controller state)."""

    command: Tensor
    """``[q]`` the control to apply now"""
    nominal: Tensor
    """``[T, q]`` the weighted action sequence (before the warm-start shift)"""
    states: Tensor
    """``[K, T+1, d]`` the proposals"""
    actions: Tensor
    """``[K, T, q]``"""
    costs: Tensor
    """``[K]`` finite costs"""
    weights: Tensor
    """``[K]`` sum to 1"""

    @property
    def best(self) -> Tensor:
        """Index of the lowest-cost proposal (a 0-d tensor; no host sync)."""
        return torch.argmin(self.costs)


def mppi_weights(costs: Tensor, lambda_: float) -> Tensor:
    """``softmax(-(cost - min) / lambda)`` over ``costs [K]``; ``lambda_ = 0`` puts all weight on the argmin.

    ValueError when ``lambda_`` is not 0 nor a normal number of ``costs.dtype`` with a finite inverse.
    """
    return _weights(costs, _check_lambda(lambda_, costs.dtype))


def _weights(costs: Tensor, lambda_: float) -> Tensor:
    """:func:`mppi_weights` for a ``lambda_`` checked already (at a controller's construction)."""
    c = torch.nan_to_num(costs, nan=COST_CAP, posinf=COST_CAP, neginf=-COST_CAP).clamp(max=COST_CAP)
    if lambda_ == 0:
        return torch.nn.functional.one_hot(torch.argmin(c), c.shape[0]).to(c.dtype)
    return torch.softmax(-(c - c.min()) / lambda_, dim=0)


def _check_lambda(lambda_: float, dtype: torch.dtype) -> float:
    """``lambda_`` as a float: 0, or a positive number that ``dtype`` holds as a normal number with a finite
    inverse (else ``-(c - min) / lambda`` is 0 / 0 or inf - inf in that dtype, and the weights are NaN)."""
    if isinstance(lambda_, bool) or not isinstance(lambda_, numbers.Real) or not (math.isfinite(lambda_) and lambda_ >= 0):
        raise ValueError(f"lambda_ must be a finite number >= 0, got {lambda_!r}")
    value = float(lambda_)
    if value == 0:
        return value
    held = torch.tensor(value, dtype=dtype).item()  # lambda_ as the controller's dtype rounds it
    inverse = torch.tensor(1.0 / held, dtype=dtype).item() if held > 0 else math.inf
    if not (held >= torch.finfo(dtype).tiny and math.isfinite(held) and math.isfinite(inverse)):
        info = torch.finfo(dtype)
        raise ValueError(f"lambda_={lambda_!r} is out of range for {dtype}: it must be 0 or between {info.tiny:.3g} "
                         f"and {info.max:.3g} with a finite 1/lambda_ (it becomes {held!r} in {dtype})")
    return value


def _check_seed(seed: int | None) -> int | None:
    if seed is not None and (isinstance(seed, bool) or not isinstance(seed, numbers.Integral)):
        raise TypeError(f"seed must be an int or None, got {type(seed).__name__} ({seed!r:.40})")
    return None if seed is None else int(seed)


def _callable_name(fn: object) -> str:
    """A user callable's name for an error message: its ``__qualname__``, else a short repr."""
    name = getattr(fn, "__qualname__", None)
    if isinstance(name, str):
        return name
    text = repr(fn)
    return text if len(text) <= 80 else f"{type(fn).__qualname__} object"


def _check_costs(costs: object, who: str, fn: object, k: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    """``costs`` as returned by the user's ``fn``, checked to be a ``[k]`` tensor of ``dtype`` on ``device``."""
    expected = f"expected a [{k}] tensor of {dtype} on {device} (one cost per proposal, the controller's dtype and device)"
    if not isinstance(costs, Tensor):
        raise ValueError(f"{who} {_callable_name(fn)} returned {type(costs).__name__} {costs!r:.60}; {expected}")
    if costs.shape != (k,) or costs.dtype != dtype or not same_device(costs.device, device):
        raise ValueError(f"{who} {_callable_name(fn)} returned a {list(costs.shape)} tensor of {costs.dtype} on "
                         f"{costs.device}; {expected}")
    return costs.detach()


def _check_positive_int(name: str, value: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f"{name} must be a positive integer, got {value!r}")
    return value


class _Core:
    """Shared settings and the cost -> weights step."""

    def __init__(self, system: System, cost_fn: CostFn, num_samples: int, horizon: int, lambda_: float,
                 terminal_cost: Callable[[Tensor], Tensor] | None, device: torch.device | str,
                 dtype: torch.dtype, seed: int | None):
        self.system = system
        self.cost_fn = cost_fn
        self.terminal_cost = terminal_cost
        self.num_samples = _check_positive_int("num_samples", num_samples)
        self.horizon = _check_positive_int("horizon", horizon)
        self.device = torch.device(device)
        if not (isinstance(dtype, torch.dtype) and dtype.is_floating_point):
            raise ValueError(f"dtype must be a floating-point torch.dtype, got {dtype!r}")
        self.dtype = dtype
        self.lambda_ = _check_lambda(lambda_, dtype)
        seed = _check_seed(seed)
        self.state_dim = len(system.periodic)
        actions = system.action_set(dtype=dtype, device=self.device)  # [A, q]
        self.low, self.high = actions.min(dim=0).values, actions.max(dim=0).values  # [q] action bounds
        self.generator = torch.Generator(device=self.device)
        self.generator.manual_seed(seed) if seed is not None else self.generator.seed()

    def _check_state(self, state: Tensor) -> Tensor:
        """``state [d]`` of the controller's dtype and device, finite; detached (a state is an observation)."""
        if not isinstance(state, Tensor) or state.shape != (self.state_dim,):
            raise ValueError(f"state must be a tensor of shape [{self.state_dim}], got {getattr(state, 'shape', state)!r}")
        if not same_device(state.device, self.device):
            raise ValueError(f"state is on {state.device} but the controller is on {self.device}")
        if state.dtype != self.dtype:
            raise ValueError(f"state is {state.dtype} but the controller is {self.dtype}; pass state.to({self.dtype})")
        state = state.detach()
        if not bool(torch.isfinite(state).all()):
            raise ValueError(f"state contains NaN or infinite values: {state.tolist()}")
        return state

    def _evaluate(self, states: Tensor, actions: Tensor) -> tuple[Tensor, Tensor]:
        """Finite costs ``[K]`` of the proposals and their weights ``[K]``; the user's costs are checked first."""
        k = states.shape[0]
        costs = _check_costs(self.cost_fn(states, actions), "cost_fn", self.cost_fn, k, self.dtype, self.device)
        if self.terminal_cost is not None:
            costs = costs + _check_costs(self.terminal_cost(states[:, -1]), "terminal_cost", self.terminal_cost, k,
                                         self.dtype, self.device)
        if bool(torch.isnan(costs).all()):  # some NaN is a penalty; NaN everywhere is a broken cost, not a choice
            raise ValueError(f"cost_fn {_callable_name(self.cost_fn)}"
                             f"{'' if self.terminal_cost is None else ' + terminal_cost ' + _callable_name(self.terminal_cost)}"
                             f" returned NaN for all {k} proposals; expected a [{k}] tensor of costs")
        costs = torch.nan_to_num(costs, nan=COST_CAP, posinf=COST_CAP, neginf=-COST_CAP).clamp(max=COST_CAP)
        return costs, _weights(costs, self.lambda_)


class MPPI(_Core):
    """MPPI with Gaussian noise (std ``noise_std``, scalar or ``[q]``) around a warm-started nominal sequence."""

    sampler_class = GaussianSampler

    def __init__(self, system: System, cost_fn: CostFn, num_samples: int = 1000, horizon: int = 15,
                 lambda_: float = 0.567, noise_std: float | Tensor = 0.3,
                 terminal_cost: Callable[[Tensor], Tensor] | None = None, device: torch.device | str = "cpu",
                 dtype: torch.dtype = torch.float32, seed: int | None = None, **sampler_kwargs):
        super().__init__(system, cost_fn, num_samples, horizon, lambda_, terminal_cost, device, dtype, seed)
        self.noise_std = noise_std
        self.sampler_kwargs = sampler_kwargs
        self.reset()

    def reset(self) -> None:
        """Zero nominal sequence (the start of an episode)."""
        self.nominal = torch.zeros((self.horizon, self.low.shape[0]), dtype=self.dtype, device=self.device)  # [T, q]
        self._sampler()  # validates the noise settings now, not at the first command

    def _sampler(self) -> GaussianSampler:
        return self.sampler_class(self.nominal, self.noise_std, self.low, self.high, **self.sampler_kwargs)

    def plan(self, state: Tensor) -> MPPIResult:
        """One MPPI iteration from ``state [d]`` (does not shift the nominal)."""
        state = self._check_state(state)
        states, actions = rollout(self.system, self._sampler(), state, self.num_samples, self.horizon, self.generator)
        costs, weights = self._evaluate(states, actions)
        nominal = torch.einsum("k,ktq->tq", weights, actions)  # [T, q]
        return MPPIResult(nominal[0], nominal, states, actions, costs, weights)

    def command(self, state: Tensor) -> Tensor:
        """The control ``[q]`` to apply at ``state [d]``; warm-starts the next call by shifting the nominal."""
        result = self.plan(state)
        self.nominal = torch.cat((result.nominal[1:], result.nominal[-1:]))  # shift, repeat the last action
        return result.command


class LogMPPI(MPPI):
    """MPPI with normal x log-normal noise; ``lognormal_mean`` / ``lognormal_var`` set the log-normal factor."""

    sampler_class = NormalLogNormalSampler

    def __init__(self, system: System, cost_fn: CostFn, num_samples: int = 1000, horizon: int = 15,
                 lambda_: float = 0.567, noise_std: float | Tensor = 0.3, lognormal_mean: float = 1.0,
                 lognormal_var: float = 1.0, **kwargs):
        super().__init__(system, cost_fn, num_samples, horizon, lambda_, noise_std,
                         lognormal_mean=lognormal_mean, lognormal_var=lognormal_var, **kwargs)


def _as_policy(policy, device):
    """A Policy object, or a distilled-policy checkpoint dict (``torch.load(path, weights_only=True)``)."""
    if isinstance(policy, dict):
        from .mlp import load_policy

        return load_policy(policy, device=device)
    if not isinstance(policy, Policy):
        raise ValueError(f"policy must have actions [A, q] and action_probs(x, t); got {type(policy).__name__}")
    return policy


class CUniformMPPI(_Core):
    """C-Uniform MPPI: C-Uniform rollouts of ``policy`` from the robot's pose, softmax-weighted (paper 1).

    ``lambda_ = 0`` commands the best proposal's first action (as the reference robot code does). With
    ``bank_size`` set, ``bank_size`` rollouts are pre-sampled at the origin (SE(2)-invariant systems only); each
    command takes a fresh random subset of ``num_samples`` of them and moves it to the pose by a rigid
    transform; ``resample_bank()`` draws a new bank (also every ``bank_refresh`` commands when set). With
    ``bank_background=True`` that refresh runs in a worker thread while commands go on with the current bank;
    the new bank replaces it at the first command after it is ready (``wait_for_bank()`` blocks until then).
    Which command first sees a background bank depends on timing, so runs with it are not bit-reproducible;
    call ``close()`` to stop the worker (or use the controller as a context manager).

    A background refresh that raises does not break the controller: the exception is reported once, as a
    :class:`BankRefreshWarning` naming its type and message (``warnings.warn``, so a test or an application can
    turn it into an error with a warnings filter), the current bank stays in use, ``bank_failures`` counts it,
    ``last_bank_error`` keeps it, and the next due refresh is tried as usual.
    """

    def __init__(self, policy, cost_fn: CostFn, num_samples: int = 1000, lambda_: float = 0.567,
                 horizon: int | None = None, bank_size: int | None = None, bank_refresh: int | None = None,
                 bank_background: bool = False, terminal_cost: Callable[[Tensor], Tensor] | None = None,
                 device: torch.device | str | None = None, seed: int | None = None):
        device = torch.device(device) if device is not None else getattr(policy, "device", torch.device("cpu"))
        self.policy = _as_policy(policy, device)
        table_horizon = getattr(self.policy, "horizon", None)
        horizon = horizon if horizon is not None else table_horizon
        if horizon is None:
            raise ValueError("horizon is required for a policy without a table horizon")
        if table_horizon is not None and horizon > table_horizon:
            raise ValueError(f"horizon {horizon} is longer than the policy's table ({table_horizon} steps)")
        dtype = getattr(self.policy, "dtype", torch.float32)
        super().__init__(self.policy.system, cost_fn, num_samples, horizon, lambda_, terminal_cost, device, dtype, seed)
        if bank_refresh is not None:
            _check_positive_int("bank_refresh", bank_refresh)
            if bank_size is None:
                raise ValueError("bank_refresh needs a proposal bank: set bank_size too")
        if bank_background and bank_refresh is None:
            raise ValueError("bank_background refreshes the bank every bank_refresh commands: set bank_refresh too")
        self.bank_size = bank_size
        self.bank_refresh = bank_refresh
        self.bank_background = bool(bank_background)
        self._commands = 0
        self._pending: Future | None = None
        self._executor: ThreadPoolExecutor | None = None
        self.banks_swapped = 0
        """background banks put in use so far"""
        self.bank_failures = 0
        """background refreshes that raised (each reported once by a BankRefreshWarning)"""
        self.last_bank_error: BaseException | None = None
        """the exception of the latest failed background refresh"""
        if self.bank_background:
            self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="cuniform-bank")
            self._bank_generator = torch.Generator(device=self.device)  # the worker's own stream of random numbers
            self._bank_generator.manual_seed(seed + 1) if seed is not None else self._bank_generator.seed()
        if bank_size is not None:
            _check_positive_int("bank_size", bank_size)
            if not self.system.se2_invariant:
                raise ValueError(f"a proposal bank needs an SE(2)-invariant system; {self.system.name} is not")
            if self.state_dim > 3:  # the bank starts at rest; a state's speed etc. is not a change of frame
                raise ValueError(f"a proposal bank needs the state (x, y, theta) only; {self.system.name} has "
                                 f"{self.state_dim} dimensions, whose rollouts depend on the start's other dimensions")
            if bank_size < num_samples:
                raise ValueError(f"bank_size ({bank_size}) must be at least num_samples ({num_samples})")
            self.resample_bank()

    def reset(self) -> None:
        self._commands = 0

    def _draw_bank(self, generator: torch.Generator) -> tuple[Tensor, Tensor]:
        origin = torch.zeros(self.state_dim, dtype=self.dtype, device=self.device)
        return rollout(self.system, self.policy, origin, self.bank_size, self.horizon, generator)

    def resample_bank(self) -> None:
        """Draw ``bank_size`` fresh rollouts at the origin, now."""
        self.bank_states, self.bank_actions = self._draw_bank(self.generator)  # [M, T+1, d], [M, T, q]

    def _swap_if_ready(self, wait: bool = False) -> bool:
        """Put a finished background bank in use (True); a failed refresh is reported and leaves the bank as is."""
        if self._pending is None or not (wait or self._pending.done()):
            return False
        pending, self._pending = self._pending, None  # a failed refresh is never looked at twice
        error = pending.exception()  # blocks until it is done
        if error is not None:
            self._report_bank_error(error)
            return False
        self.bank_states, self.bank_actions = pending.result()
        self.banks_swapped += 1
        return True

    def _report_bank_error(self, error: BaseException) -> None:
        self.bank_failures += 1
        self.last_bank_error = error
        warnings.warn(f"CUniformMPPI: background bank refresh failed ({type(error).__name__}: {error}); "
                      f"the current bank stays in use and the next refresh is tried as usual",
                      BankRefreshWarning, stacklevel=4)

    def wait_for_bank(self) -> bool:
        """Block until a background refresh in flight is done and use its bank; False when none was pending or it
        failed (then reported by a :class:`BankRefreshWarning`)."""
        return self._swap_if_ready(wait=True)

    def close(self) -> None:
        """Stop the background worker: a pending refresh is finished first (and used, or reported if it failed).
        The thread is stopped even when a refresh failed; calling it again does nothing."""
        executor, self._executor = self._executor, None
        if executor is None:
            return
        self.bank_background = False
        try:
            self._swap_if_ready(wait=True)
        finally:
            executor.shutdown(wait=True)

    def __enter__(self) -> CUniformMPPI:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def propose(self, state: Tensor) -> tuple[Tensor, Tensor]:
        """``num_samples`` C-Uniform proposals from ``state [d]``: ``[K, T+1, d]``, ``[K, T, q]``."""
        if self.bank_size is None:
            return rollout(self.system, self.policy, state, self.num_samples, self.horizon, self.generator)
        idx = torch.randperm(self.bank_size, generator=self.generator, device=self.device)[: self.num_samples]
        return se2_to_world(self.bank_states[idx], state), self.bank_actions[idx]

    def plan(self, state: Tensor) -> MPPIResult:
        state = self._check_state(state)
        states, actions = self.propose(state)
        costs, weights = self._evaluate(states, actions)
        nominal = torch.einsum("k,ktq->tq", weights, actions)  # [T, q]
        return MPPIResult(nominal[0], nominal, states, actions, costs, weights)

    def command(self, state: Tensor) -> Tensor:
        self._commands += 1
        if self.bank_refresh and self.bank_size is not None:
            due = self._commands % self.bank_refresh == 0
            if self.bank_background:
                self._swap_if_ready()
                if due and self._pending is None:
                    self._pending = self._executor.submit(self._draw_bank, self._bank_generator)
            elif due:
                self.resample_bank()
        return self.plan(state).command


class CUMPPI:
    """CU-MPPI: the best C-Uniform rollout seeds one local MPPI (or log-MPPI) pass; its first control is applied.

    ``num_samples`` is split: ``round(cuniform_fraction * num_samples)`` C-Uniform proposals, the rest for the
    local pass (Gaussian noise of std ``noise_std`` around the best C-Uniform action sequence).
    """

    def __init__(self, policy, cost_fn: CostFn, num_samples: int = 1000, cuniform_fraction: float = 0.5,
                 lambda_: float = 0.567, noise_std: float | Tensor = 0.1, local: str = "mppi",
                 horizon: int | None = None, bank_size: int | None = None,
                 terminal_cost: Callable[[Tensor], Tensor] | None = None, device: torch.device | str | None = None,
                 seed: int | None = None, **local_kwargs):
        _check_positive_int("num_samples", num_samples)
        if not 0 < cuniform_fraction < 1:
            raise ValueError(f"cuniform_fraction must be in (0, 1), got {cuniform_fraction!r}")
        k_cu = max(1, min(num_samples - 1, round(cuniform_fraction * num_samples)))
        if num_samples < 2:
            raise ValueError("CU-MPPI needs num_samples >= 2 (C-Uniform proposals + a local pass)")
        self.cuniform = CUniformMPPI(policy, cost_fn, k_cu, lambda_=0.0, horizon=horizon, bank_size=bank_size,
                                     terminal_cost=terminal_cost, device=device, seed=seed)
        local_cls = {"mppi": MPPI, "log_mppi": LogMPPI}.get(local)
        if local_cls is None:
            raise ValueError(f"unknown local pass {local!r}; choose mppi or log_mppi")
        self.local = local_cls(self.cuniform.system, cost_fn, num_samples - k_cu, self.cuniform.horizon, lambda_,
                               noise_std, terminal_cost=terminal_cost, device=self.cuniform.device,
                               dtype=self.cuniform.dtype, seed=None if seed is None else seed + 1, **local_kwargs)
        self.system = self.cuniform.system

    def reset(self) -> None:
        self.cuniform.reset()
        self.local.reset()

    def plan(self, state: Tensor) -> MPPIResult:
        """C-Uniform stage, then a local pass around its best trajectory; returns the local pass's result."""
        seed_result = self.cuniform.plan(state)
        self.local.nominal = seed_result.actions[seed_result.best]  # [T, q]
        return self.local.plan(state)

    def command(self, state: Tensor) -> Tensor:
        return self.plan(state).command
