"""The one MPPI core: :class:`MPPICore` takes a :class:`~cuniform_torch.controllers.proposals.Proposal`.

Shapes: K samples (proposals), T horizon, d state dimensions, q action dimensions.

:meth:`MPPICore.plan` is the one MPPI iteration of every controller (:mod:`cuniform_torch.controllers.mppi`):

1. ``states [K, T+1, d], actions [K, T, q] = proposal.propose(state, generator)``;
2. cost each one, ``cost_fn(states, actions) -> [K]`` (+ ``terminal_cost(states[:, -1]) -> [K]``); NaN and
   +-inf (e.g. the paper's infinite collision cost) become a large finite penalty, so weights never go NaN;
3. weight them, ``w = softmax(-(cost - min cost) / lambda)`` (``lambda = 0``: all weight on the best one), and
   return the weighted average of the proposals' action sequences (its first action is the command).

:meth:`MPPICore.command` is ``plan``, then ``proposal.update(result)`` (the warm start), then the command.

Bad input is refused with one ValueError or TypeError naming it, all checked here: a ``lambda_`` that the
controller's dtype cannot hold (or whose inverse overflows it), a ``seed`` that is not an integer, a state of the
wrong shape, dtype or device or with NaN, a proposal that lacks a member of the protocol or returns trajectories
of the wrong shape, dtype or device, and a cost (or terminal cost) that is not a ``[K]`` tensor of the
controller's dtype and device, or is NaN for every proposal. A state that requires grad is detached (a
controller never differentiates through its input).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

import torch
from torch import Tensor

from cuniform_torch.common.tensors import check_generator
from cuniform_torch.controllers.checks import (
    COST_CAP,
    _callable_name,
    _check_costs,
    _check_lambda,
    _finite_costs,
    check_positive_int,
    check_proposals,
    check_state,
    make_generator,
)
from cuniform_torch.controllers.proposals import PROPOSAL_MEMBERS, Closeable, Proposal
from cuniform_torch.controllers.result import MPPIResult
from cuniform_torch.systems import System

__all__ = ["CostFn", "MPPIResult", "mppi_weights", "MPPICore", "COST_CAP"]


class CostFn(Protocol):
    """Trajectory cost: ``states [K, T+1, d]``, ``actions [K, T, q]`` -> ``[K]`` (may be inf for collisions), a
    tensor of the controller's dtype on its device (``cuniform_torch.envs.NavigationCost`` is one)."""

    def __call__(self, states: Tensor, actions: Tensor) -> Tensor: ...


def mppi_weights(costs: Tensor, lambda_: float) -> Tensor:
    """``softmax(-(cost - min) / lambda)`` over ``costs [K]``; ``lambda_ = 0`` puts all weight on the argmin.

    ValueError when ``lambda_`` is not 0 nor a normal number of ``costs.dtype`` with a finite inverse.
    """
    return _weights(_finite_costs(costs), _check_lambda(lambda_, costs.dtype))


def _weights(costs: Tensor, lambda_: float) -> Tensor:
    """:func:`mppi_weights` of finite ``costs`` for a ``lambda_`` checked already (at a controller's construction)."""
    if lambda_ == 0:
        return torch.nn.functional.one_hot(torch.argmin(costs), costs.shape[0]).to(costs.dtype)
    return torch.softmax((costs - costs.min()).div_(-lambda_), dim=0)


class MPPICore:
    """One MPPI controller around any :class:`~cuniform_torch.controllers.proposals.Proposal`.

    ``plan(state [d]) -> MPPIResult`` proposes, costs, weights (``lambda_``; 0 puts all the weight on the best
    proposal) and averages; ``command(state) -> [q]`` plans, lets the proposal warm-start from the result and
    returns its first action. The controller's ``generator`` (seeded by ``seed``, or passed in) is the one
    stream of random numbers the proposal draws from. ``close()`` (or ``with``) releases what the proposal holds
    (a bank's worker thread).
    """

    def __init__(self, proposal: Proposal, cost_fn: CostFn, lambda_: float = 0.567,
                 terminal_cost: Callable[[Tensor], Tensor] | None = None, seed: int | None = None, *,
                 generator: torch.Generator | None = None):
        if not isinstance(proposal, Proposal):
            missing = [m for m in PROPOSAL_MEMBERS if not hasattr(proposal, m)]
            raise TypeError(f"{type(proposal).__name__} is not a Proposal: it lacks {', '.join(missing)} (a proposal "
                            f"has {', '.join(PROPOSAL_MEMBERS)})")
        for name, fn in (("cost_fn", cost_fn), ("terminal_cost", terminal_cost)):
            if fn is not None and not callable(fn):
                raise TypeError(f"{name} must be callable (states, actions) -> [K], got {type(fn).__name__}")
        if cost_fn is None:
            raise TypeError("cost_fn must be callable (states, actions) -> [K], got None")
        self.proposal = proposal
        self.system: System = proposal.system
        self.cost_fn = cost_fn
        self.terminal_cost = terminal_cost
        self.num_samples = check_positive_int("num_samples", proposal.num_samples)
        self.horizon = check_positive_int("horizon", proposal.horizon)
        self.device = torch.device(proposal.device)
        dtype = proposal.dtype
        if not (isinstance(dtype, torch.dtype) and dtype.is_floating_point):
            raise ValueError(f"dtype must be a floating-point torch.dtype, got {dtype!r}")
        self.dtype = dtype
        self.lambda_ = _check_lambda(lambda_, dtype)
        self.state_dim = len(self.system.periodic)
        self.action_dim = self.system.action_set(dtype=dtype, device=self.device).shape[1]
        if generator is None:
            generator = make_generator(seed, self.device)
        elif seed is not None:
            raise ValueError("pass a seed or a generator, not both")
        else:
            check_generator(generator, self.device)
        self.generator = generator
        """the stream of random numbers of every proposal drawn by this controller"""

    # -------------------------------------------------------------------------------- the one MPPI iteration

    def plan(self, state: Tensor) -> MPPIResult:
        """One MPPI iteration from ``state [d]``; the proposal's warm start is left as it was."""
        state = self._check_state(state)
        states, actions = self.proposal.propose(state, self.generator)
        self._check_proposals(states, actions)
        costs, weights = self._evaluate(states, actions)
        k, t, q = actions.shape
        nominal = (weights @ actions.reshape(k, t * q)).reshape(t, q)  # [T, q] weighted sequences
        return MPPIResult(nominal[0], nominal, states, actions, costs, weights)

    def command(self, state: Tensor) -> Tensor:
        """The control ``[q]`` to apply at ``state [d]``; the proposal warm-starts the next command from this one."""
        result = self.plan(state)
        self.proposal.update(result)
        return result.command

    def reset(self) -> None:
        """The start of an episode (the proposal forgets its warm start)."""
        self.proposal.reset()

    def close(self) -> None:
        """Release what the proposal holds (a background worker); calling it again does nothing."""
        if isinstance(self.proposal, Closeable):
            self.proposal.close()

    def __enter__(self) -> MPPICore:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    # -------------------------------------------------------------------------------- checks

    def _check_state(self, state: Tensor) -> Tensor:
        """``state [d]`` of the controller's dtype and device, finite; detached (a state is an observation)."""
        return check_state(state, self.state_dim, self.dtype, self.device)

    def _check_proposals(self, states: object, actions: object) -> None:
        """What ``propose`` returned: ``[K, T+1, d]`` states and ``[K, T, q]`` actions of the dtype and device."""
        check_proposals(type(self.proposal).__name__, states, actions,
                        (self.num_samples, self.horizon, self.state_dim, self.action_dim), self.dtype, self.device)

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
        costs = _finite_costs(costs)
        return costs, _weights(costs, self.lambda_)
