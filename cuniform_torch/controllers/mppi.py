"""The MPPI family: four controllers on the one core :class:`~cuniform_torch.controllers.core.MPPICore`, each with a
:class:`~cuniform_torch.controllers.proposals.Proposal`, built by thin constructors.

Shapes: K samples (proposals), T horizon, d state dimensions, q action dimensions.

* :class:`MPPI`: :class:`~cuniform_torch.controllers.proposals.GaussianProposal` (noise around a nominal, shifted one step);
* :class:`LogMPPI`: :class:`~cuniform_torch.controllers.proposals.NormalLogNormalProposal` (Mohamed et al.);
* :class:`CUniformMPPI` (the C-Uniform paper): :class:`~cuniform_torch.controllers.proposals.PolicyProposal` (C-Uniform
  rollouts of a table or an MLP from the pose) or, with ``bank_size``,
  :class:`~cuniform_torch.controllers.bank.BankProposal` (a random subset of pre-sampled rollouts + a rigid transform);
* :class:`CUMPPI` (arXiv 2503.05819): :class:`~cuniform_torch.controllers.proposals.CompositeProposal` (the lowest-cost
  C-Uniform rollout seeds one local MPPI or log-MPPI pass, whose first control is applied).

The core (:mod:`cuniform_torch.controllers.core`: ``plan``, ``command``, the weights and every input check) and its
names (:class:`MPPICore`, :class:`MPPIResult`, :class:`CostFn`, :func:`mppi_weights`, ``COST_CAP``) are
importable from here too.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import torch
from torch import Tensor

from cuniform_torch.controllers.bank import BankProposal, BankRefreshWarning
from cuniform_torch.controllers.callables import (
    CallableOptions,
    CallableProposal,
    DynamicsFn,
    RunningCostFn,
    TerminalStateCostFn,
    is_system,
    resolve,
)
from cuniform_torch.controllers.checks import check_positive_int
from cuniform_torch.controllers.core import COST_CAP, CostFn, MPPICore, MPPIResult, mppi_weights
from cuniform_torch.controllers.proposals import (
    CompositeProposal,
    GaussianProposal,
    NormalLogNormalProposal,
    PipelinedProposal,
    PolicyProposal,
)
from cuniform_torch.controllers.streams import RobotStreams, robot_seeds, shifted
from cuniform_torch.sampling.rollout import Policy
from cuniform_torch.systems import System

__all__ = ["CostFn", "MPPIResult", "mppi_weights", "MPPICore", "MPPI", "LogMPPI", "CUniformMPPI", "CUMPPI",
           "COST_CAP", "BankRefreshWarning"]


# ------------------------------------------------------------------------------------------ the four controllers

class MPPI(MPPICore):
    """MPPI: the core with a :class:`~cuniform_torch.controllers.proposals.GaussianProposal` (std ``noise_std``, scalar or
    ``[q]``, around a nominal sequence that the command's weighted sequence, shifted one step, warm-starts).

    The dynamics come one of two ways: a :class:`~cuniform_torch.systems.protocol.System` with a trajectory
    ``cost_fn``; or pytorch_mppi's: a function ``dynamics(state [K, d], action [K, q]) -> [K, d]`` with ``nx``,
    ``u_min`` / ``u_max`` and a per-step ``running_cost`` (``MPPI(dynamics, nx=2, running_cost=cost,
    noise_sigma=..., u_min=..., u_max=...)``, the names and meanings of pytorch_mppi's ``MPPI``:
    :mod:`~cuniform_torch.controllers.callables`; the guide "Coming from pytorch_mppi" maps every argument).

    :param system: the dynamics: a :class:`~cuniform_torch.systems.protocol.System` (its action set's range bounds
        the actions), or a function ``(state [K, d], action [K, q]) -> [K, d]`` (then give ``nx``)
    :param cost_fn: trajectory cost, ``states [N, T+1, d]``, ``actions [N, T, q]`` -> ``[N]`` (all robots' rollouts
        at once, N = B*K; with ``cost_fn.batched = True``: ``[B, K, T+1, d]`` -> ``[B, K]``), may be inf; or
        None with ``running_cost``
    :param num_samples: K, rollouts per robot and command
    :param lambda_: the temperature of ``softmax(-(cost - min) / lambda_)``; 0 puts all weight on the best rollout;
        ``"auto"``: per command and robot, the one whose weights' effective sample size is ``target_ess``
    :param terminal_cost: optional, ``states [N, d]`` (the last states) -> ``[N]``, added to ``cost_fn``
    :param seed: an int, one int per robot, or None (fresh entropy); robot ``b`` of an int seed ``s`` uses
        ``s + b * 1_000_003``
    :param num_robots: B, robots per call: ``command(states [B, d]) -> [B, q]``
    :param debug: per-command checks that read values (a NaN state, all-NaN costs); default on a CPU, off on CUDA
    :param cuda_graph: capture the first command in one CUDA graph and replay it (CUDA only)
    :param horizon: T, steps per rollout
    :param noise_std: the Gaussian noise's standard deviation, a scalar or one per action dimension ``[q]``; None
        (and no ``noise_sigma``): a quarter of each action dimension's range
        (:func:`~cuniform_torch.controllers.proposals.default_noise_std`)
    :param device: where the controller runs
    :param dtype: its floating-point dtype (default: ``noise_sigma``'s when it is a floating tensor, else float32)
    :param nx: with a dynamics function: the state dimension d
    :param running_cost: per-step cost ``(state [N, d], action [N, q]) -> [N]`` of the state each action led to
        (pytorch_mppi's; instead of ``cost_fn``), called once per command on all ``B*K*T`` rows
    :param terminal_state_cost: with ``running_cost``: pytorch_mppi's ``(states [1, N, T, d], actions [1, N, T, q])
        -> [1, N]``
    :param noise_sigma: the noise covariance (pytorch_mppi's): a scalar variance or ``[q, q]`` (a full matrix is
        sampled through its Cholesky factor); instead of ``noise_std``
    :param noise_mu: ``[q]`` the noise's mean (default 0)
    :param u_min: with a dynamics function: ``[q]`` (or scalar) lower action bounds (default: ``-u_max``, or none)
    :param u_max: upper bounds (default: ``-u_min``, or none)
    :param u_init: ``[q]`` the action appended when the nominal shifts (default: the last action repeated)
    :param U_init: ``[T, q]`` the first nominal (default: ``u_init``, or zeros, at every step)
    :param control_cost: add pytorch_mppi's ``lambda * sum_t U_t Sigma^-1 eps_t`` to each rollout's cost (default:
        on when ``noise_sigma`` is given)
    :param target_ess: with ``lambda_="auto"``: the effective sample size aimed for (default K / 10)
    :param convert_states: accept numpy states and tensors of another floating dtype, the command coming back as
        the state's type and dtype (default: on for a dynamics function, off for a System)
    """

    proposal: GaussianProposal  # what _proposal builds (MPPICore types it as any proposal)

    def __init__(self, system: System | DynamicsFn, cost_fn: CostFn | None = None, num_samples: int = 1000,
                 horizon: int = 15, lambda_: float | str = 0.567, noise_std: float | Tensor | None = None,
                 terminal_cost: Callable[[Tensor], Tensor] | None = None, device: torch.device | str = "cpu",
                 dtype: torch.dtype | None = None, seed: int | Sequence[int] | None = None, num_robots: int = 1,
                 debug: bool | None = None, cuda_graph: bool = False, *, nx: int | None = None,
                 running_cost: RunningCostFn | None = None, terminal_state_cost: TerminalStateCostFn | None = None,
                 noise_sigma: float | Tensor | None = None, noise_mu: float | Tensor | None = None,
                 u_min: float | Tensor | None = None, u_max: float | Tensor | None = None,
                 u_init: float | Tensor | None = None, U_init: Tensor | None = None, control_cost: bool | None = None,
                 target_ess: float | None = None, convert_states: bool | None = None):
        self._options: CallableOptions | None = None
        pytorch_style = {"nx": nx, "running_cost": running_cost, "terminal_state_cost": terminal_state_cost,
                         "noise_sigma": noise_sigma, "noise_mu": noise_mu, "u_min": u_min, "u_max": u_max,
                         "u_init": u_init, "U_init": U_init, "control_cost": control_cost}
        fn_given = not is_system(system)
        if fn_given or any(v is not None for v in pytorch_style.values()):
            parts = resolve(type(self).__name__, system, cost_fn, noise_std=noise_std, dtype=dtype,
                            **pytorch_style)  # type: ignore[arg-type]
            system, cost_fn, noise_std, dtype = parts.system, parts.cost_fn, parts.noise_std, parts.dtype
            self._options = parts.options
            if self._options is not None and type(self)._proposal is not MPPI._proposal:
                raise ValueError(f"{type(self).__name__} draws its own noise (std noise_std, bounded actions): "
                                 f"a full noise_sigma, noise_mu, u_init, U_init, control_cost and unbounded actions "
                                 f"(no u_min / u_max) are MPPI's; give finite u_min / u_max and noise_std, or use "
                                 f"MPPI")
        elif cost_fn is None:
            raise ValueError(f"{type(self).__name__}: give a cost: cost_fn(states [N, T+1, d], actions [N, T, q]) -> "
                             f"[N], or a per-step running_cost(state [K, d], action [K, q]) -> [K]")
        dtype = torch.float32 if dtype is None else dtype
        proposal = self._proposal(system, num_samples, horizon, noise_std, device, dtype, num_robots)
        super().__init__(proposal, cost_fn, lambda_, terminal_cost, seed, debug=debug, cuda_graph=cuda_graph,
                         target_ess=target_ess, convert_states=fn_given if convert_states is None else convert_states)
        self.noise_std = noise_std if noise_std is not None else proposal.std

    def _proposal(self, system, num_samples, horizon, noise_std, device, dtype, num_robots) -> GaussianProposal:
        if self._options is not None:
            return CallableProposal(system, num_samples, horizon, noise_std, self._options, device, dtype,
                                    num_robots)
        return GaussianProposal(system, num_samples, horizon, noise_std, device, dtype, num_robots)

    @property
    def nominal(self) -> Tensor:
        """``[T, q]`` the sequence the next command samples around (the proposal's)."""
        return self.proposal.nominal

    @nominal.setter
    def nominal(self, value: Tensor) -> None:
        self.proposal.nominal = value

    @property
    def low(self) -> Tensor:
        """``[q]`` lower action bounds"""
        return self.proposal.low

    @property
    def high(self) -> Tensor:
        """``[q]`` upper action bounds"""
        return self.proposal.high


class LogMPPI(MPPI):
    """log-MPPI: the core with a :class:`~cuniform_torch.controllers.proposals.NormalLogNormalProposal`; ``lognormal_mean``
    / ``lognormal_var`` set the log-normal factor.

    :param lognormal_mean: the log-normal factor's mean
    :param lognormal_var: its variance
    :param kwargs: the rest, as :class:`MPPI`'s (``device``, ``dtype``, ``terminal_cost``, ``seed``, ``num_robots``,
        ``debug``, ``cuda_graph``)
    """

    def __init__(self, system: System | DynamicsFn, cost_fn: CostFn | None = None, num_samples: int = 1000,
                 horizon: int = 15, lambda_: float | str = 0.567, noise_std: float | Tensor | None = None,
                 lognormal_mean: float = 1.0,
                 lognormal_var: float = 1.0, **kwargs: Any):
        self.lognormal_mean, self.lognormal_var = lognormal_mean, lognormal_var
        super().__init__(system, cost_fn, num_samples, horizon, lambda_, noise_std, **kwargs)

    def _proposal(self, system, num_samples, horizon, noise_std, device, dtype, num_robots) -> NormalLogNormalProposal:
        return NormalLogNormalProposal(system, num_samples, horizon, noise_std, self.lognormal_mean,
                                       self.lognormal_var, device, dtype, num_robots)


class CUniformMPPI(MPPICore):
    """C-Uniform MPPI: C-Uniform rollouts of ``policy`` from the robot's pose, softmax-weighted (paper 1).

    ``policy`` is a table, an MLP, any Policy with a ``system``, or a distilled checkpoint dict
    (:func:`~cuniform_torch.policies.checkpoint.load_policy` loads it). ``lambda_ = 0`` commands the best proposal's first action
    (as the reference robot code does). Without ``bank_size`` the proposal is a
    :class:`~cuniform_torch.controllers.proposals.PolicyProposal` (fresh rollouts every command). With ``bank_size`` it is a
    :class:`~cuniform_torch.controllers.bank.BankProposal`: ``bank_size`` rollouts pre-sampled at the origin
    (SE(2)-invariant systems only); each command takes a fresh random subset of ``num_samples`` of them and moves
    it to the pose by a rigid transform; ``resample_bank()`` draws a new bank (also every ``bank_refresh`` commands
    when set, from a stream seeded by ``seed + 1``). With ``bank_background=True`` that refresh runs in a worker
    thread while commands go on with the current bank; see the bank's docstring for when it is swapped in and
    what a failed refresh does. Call ``close()`` to stop the worker (or use the controller as a context manager).

    :param policy: a table (``load_table``), a table set, an MLP, any Policy with a ``system``, or a distilled
        checkpoint dict
    :param cost_fn: as :class:`MPPI`'s, and so are ``num_samples`` (K per robot), ``lambda_``, ``terminal_cost``,
        ``seed``, ``num_robots``, ``debug`` and ``cuda_graph``
    :param horizon: T, steps per rollout (default: the policy's)
    :param bank_size: M rollouts pre-sampled at the origin (None: fresh rollouts every command)
    :param bank_refresh: draw a new bank every this many commands (None: never)
    :param bank_background: draw refreshed banks in a worker thread
    :param device: the policy's device when a checkpoint dict is given
    :param condition: ``condition(states [B, d])``, called once per command before the rollouts: sets the
        policy's per-robot input (:class:`~cuniform_torch.controllers.proposals.PolicyProposal`)
    """

    def __init__(self, policy: Policy | dict[str, Any], cost_fn: CostFn, num_samples: int = 1000,
                 lambda_: float = 0.567, horizon: int | None = None, bank_size: int | None = None,
                 bank_refresh: int | None = None,
                 bank_background: bool = False, terminal_cost: Callable[[Tensor], Tensor] | None = None,
                 device: torch.device | str | None = None, seed: int | Sequence[int] | None = None,
                 num_robots: int = 1, debug: bool | None = None, cuda_graph: bool = False,
                 condition: Callable[[Tensor], None] | None = None):
        if bank_refresh is not None:
            check_positive_int("bank_refresh", bank_refresh)
            if bank_size is None:
                raise ValueError("bank_refresh needs a proposal bank: set bank_size too")
        if bank_background and bank_refresh is None:
            raise ValueError("bank_background refreshes the bank every bank_refresh commands: set bank_refresh too")
        if cuda_graph and bank_size is not None:
            raise ValueError("cuda_graph: a proposal bank swaps its tensors when refreshed; use it without a bank")
        source = PolicyProposal(policy, num_samples, horizon, device, num_robots, condition)
        self.policy = source.policy
        seeds = robot_seeds(seed, source.num_robots)
        streams = RobotStreams.seeded(seeds, source.device)
        proposal: PolicyProposal | BankProposal = source
        if bank_size is not None:  # the first bank comes from robot 0's stream, refreshes from its seed + 1
            proposal = BankProposal(source, bank_size, streams.generators[0], bank_refresh, bank_background,
                                    seed=None if seeds[0] is None else seeds[0] + 1)
        super().__init__(proposal, cost_fn, lambda_, terminal_cost, generator=streams.generators, debug=debug,
                         cuda_graph=cuda_graph)
        self.bank_size = bank_size
        self.bank_refresh = bank_refresh

    @property
    def bank(self) -> BankProposal | None:
        """The proposal bank, None without one."""
        return self.proposal if isinstance(self.proposal, BankProposal) else None

    def _need_bank(self) -> BankProposal:
        if self.bank is None:
            raise AttributeError("this CUniformMPPI has no proposal bank (bank_size=None)")
        return self.bank

    @property
    def bank_states(self) -> Tensor:
        """``[M, T+1, d]`` the bank's rollouts at the origin"""
        return self._need_bank().bank_states

    @property
    def bank_actions(self) -> Tensor:
        """``[M, T, q]``"""
        return self._need_bank().bank_actions

    @property
    def bank_background(self) -> bool:
        """Whether bank refreshes run in a worker thread (False after ``close()``)"""
        return self.bank is not None and self.bank.background

    @property
    def banks_swapped(self) -> int:
        """background banks put in use so far"""
        return 0 if self.bank is None else self.bank.banks_swapped

    @property
    def bank_failures(self) -> int:
        """background refreshes that raised (each reported once by a BankRefreshWarning)"""
        return 0 if self.bank is None else self.bank.bank_failures

    @property
    def last_bank_error(self) -> BaseException | None:
        """the exception of the latest failed background refresh"""
        return None if self.bank is None else self.bank.last_bank_error

    @property
    def _draw_bank(self) -> Callable[[torch.Generator], tuple[Tensor, Tensor]]:
        """The bank's draw (``generator -> (states, actions)``); assignable, for fault injection (eval.bench.soak_bank)."""
        return self._need_bank().draw_bank

    @_draw_bank.setter
    def _draw_bank(self, fn: Callable[[torch.Generator], tuple[Tensor, Tensor]]) -> None:
        self._need_bank().draw_bank = fn

    def resample_bank(self) -> None:
        """Draw ``bank_size`` fresh rollouts at the origin, now, from the controller's generator."""
        self._need_bank().resample(self.generator)

    def wait_for_bank(self) -> bool:
        """Block until a background refresh in flight is done and use its bank; False when none was pending or it
        failed (then reported by a :class:`BankRefreshWarning`)."""
        return self.bank is not None and self.bank.wait_for_bank()

    def _best_actions(self, state: Tensor) -> Tensor:
        """The lowest-cost proposal's action sequence per robot from checked ``state [B, d]``: ``[B, T, q]``, no
        host sync. CU-MPPI's first stage: what ``self._plan(state).best_actions()`` returns (the same draws,
        costs and argmin) without the weights, the weighted sequence and the result that it does not read."""
        if self._action_cost is not None:  # a proposal's own action cost enters the argmin: the whole plan
            return self._plan(state).best_actions()
        states, actions = self._batch.propose_batch(state, self.streams)  # [B, K, T+1, d], [B, K, T, q]
        if self.debug:
            self._check_proposals(states, actions)
        best = torch.argmin(self._state_costs(states, actions), dim=1)  # [B]
        return actions.gather(1, best.view(-1, 1, 1, 1).expand(-1, 1, *actions.shape[2:]))[:, 0]

    def propose(self, state: Tensor) -> tuple[Tensor, Tensor]:
        """``num_samples`` C-Uniform proposals from ``state [d]``: ``[K, T+1, d]``, ``[K, T, q]`` (from ``[B, d]``:
        ``[B, K, T+1, d]``, ``[B, K, T, q]``)."""
        states, single = self._check_state(state)
        out_states, out_actions = self._batch.propose_batch(states, self.streams)
        return (out_states[0], out_actions[0]) if single else (out_states, out_actions)


class CUMPPI(MPPICore):
    """CU-MPPI: the best C-Uniform rollout seeds one local MPPI (or log-MPPI) pass; its first control is applied.

    ``num_samples`` is split: ``round(cuniform_fraction * num_samples)`` C-Uniform proposals (the first stage,
    ``self.cuniform``: a :class:`CUniformMPPI` with ``lambda_ = 0`` seeded by ``seed``), the rest for the local
    pass (``self.local``: Gaussian noise of std ``noise_std`` around the best C-Uniform action sequence, or
    normal x log-normal with ``local="log_mppi"``; drawn from the controller's generator, seeded by ``seed + 1``).
    The core weighs the local pass with ``lambda_``; ``plan`` returns its result. ``local_kwargs`` go to the local
    proposal (``lognormal_mean``, ``lognormal_var``).

    :param policy: as :class:`CUniformMPPI`'s
    :param cost_fn: as :class:`MPPI`'s, and so are ``num_samples`` (K per robot), ``lambda_``, ``terminal_cost``,
        ``seed``, ``num_robots``, ``debug`` and ``cuda_graph``
    :param cuniform_fraction: the share of ``num_samples`` (both stages together) that the C-Uniform first stage draws
    :param noise_std: the local pass's noise standard deviation (scalar or ``[q]``)
    :param local: ``"mppi"`` (Gaussian) or ``"log_mppi"`` (normal x log-normal) local pass
    :param horizon: T (default: the policy's)
    :param bank_size: a proposal bank for the first stage (see :class:`CUniformMPPI`)
    :param device: the policy's device when a checkpoint dict is given
    :param pipelined: one pass per command (:class:`~cuniform_torch.controllers.proposals.PipelinedProposal`): the
        local rollouts around the previous command's best C-Uniform sequence, rolled out and costed together with
        this command's C-Uniform rollouts, and all of them weighed (a mixture); False: the two stages of the paper
    :param condition: as :class:`CUniformMPPI`'s (the first stage's per-robot input, set once per command)
    """

    def __init__(self, policy: Policy | dict[str, Any], cost_fn: CostFn, num_samples: int = 1000,
                 cuniform_fraction: float = 0.5, lambda_: float = 0.567, noise_std: float | Tensor = 0.1,
                 local: str = "mppi", horizon: int | None = None, bank_size: int | None = None,
                 terminal_cost: Callable[[Tensor], Tensor] | None = None, device: torch.device | str | None = None,
                 seed: int | Sequence[int] | None = None, num_robots: int = 1, debug: bool | None = None,
                 cuda_graph: bool = False, pipelined: bool = False,
                 condition: Callable[[Tensor], None] | None = None, **local_kwargs: Any):
        check_positive_int("num_samples", num_samples)
        if not 0 < cuniform_fraction < 1:
            raise ValueError(f"cuniform_fraction must be in (0, 1), got {cuniform_fraction!r}")
        if num_samples < 2:
            raise ValueError("CU-MPPI needs num_samples >= 2 (C-Uniform proposals + a local pass)")
        local_cls = {"mppi": GaussianProposal, "log_mppi": NormalLogNormalProposal}.get(local)
        if local_cls is None:
            raise ValueError(f"unknown local pass {local!r}; choose mppi or log_mppi")
        robot_seeds(seed, check_positive_int("num_robots", num_robots))  # checked here, before any work
        k_cu = max(1, min(num_samples - 1, round(cuniform_fraction * num_samples)))
        self.cuniform = CUniformMPPI(policy, cost_fn, k_cu, lambda_=0.0, horizon=horizon, bank_size=bank_size,
                                     terminal_cost=terminal_cost, device=device, seed=seed, num_robots=num_robots,
                                     debug=debug, condition=condition)
        self.local = local_cls(self.cuniform.system, num_samples - k_cu, self.cuniform.horizon, noise_std=noise_std,
                               device=self.cuniform.device, dtype=self.cuniform.dtype, num_robots=num_robots,
                               **local_kwargs)
        self.pipelined = bool(pipelined)
        proposal: CompositeProposal | PipelinedProposal = (
            PipelinedProposal(self.cuniform._batch, self.cuniform.streams, self.local) if self.pipelined
            else CompositeProposal(self.cuniform, self.local))
        super().__init__(proposal, cost_fn, lambda_, terminal_cost, seed=shifted(seed, 1), debug=debug,
                         cuda_graph=cuda_graph)
