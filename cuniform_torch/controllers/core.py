"""The one MPPI core: :class:`MPPICore` takes a :class:`~cuniform_torch.controllers.proposals.Proposal`.

Shapes: B robots, K samples (proposals) per robot, T horizon, d state dimensions, q action dimensions.

:meth:`MPPICore.plan` is the one MPPI iteration of every controller (:mod:`cuniform_torch.controllers.mppi`), for
B robots at once (``state [B, d]``; a ``[d]`` state is one robot and gets results without the robot dimension):

1. ``states [B, K, T+1, d], actions [B, K, T, q] = proposal.propose_batch(state, streams)``: every robot's K
   proposals in one tensor program, each robot drawing from its own random stream
   (:class:`~cuniform_torch.controllers.streams.RobotStreams`);
2. cost each one: ``cost_fn(states, actions)`` gets all B x K rollouts flattened, ``[B*K, T+1, d]`` -> ``[B*K]``
   (the same cost for every robot), or, when the cost declares ``batched = True``, ``[B, K, T+1, d]`` ->
   ``[B, K]`` (a cost per robot: goals per robot); likewise ``terminal_cost(states[..., -1, :])``. NaN and
   +-inf (e.g. the paper's infinite collision cost) become a large finite penalty, so weights never go NaN;
3. weight them per robot, ``w = softmax(-(cost - min cost) / lambda)`` (``lambda = 0``: all weight on the best
   one; ``lambda_="auto"``: per command and robot, the ``lambda`` whose weights have the effective sample size
   ``target_ess``, :mod:`~cuniform_torch.controllers.temperature`), and return the weighted average of each
   robot's action sequences (its first action is the command). A proposal with an ``action_cost(actions) ->
   [B, K]`` (pytorch_mppi's control cost ``U Sigma^-1 eps``) adds ``lambda * action_cost`` to the costs.

:meth:`MPPICore.command` is ``plan``, then ``proposal.update(result)`` (the warm starts), then the commands.
:attr:`MPPICore.on_plan` (opt-in, None by default: then it costs one attribute test per command) is called with each
eager command's :class:`MPPIResult` after the warm-start update, so a caller sees the proposals' costs without
spelling the command out again (the navigation benchmark's trace, :mod:`eval.navigate.episode`).
:meth:`MPPICore.reset` forgets the warm start of every robot, or of the robots named (their episodes ended).

Checks: the constructor refuses bad arguments with one ValueError or TypeError naming them (a ``lambda_`` that the
controller's dtype cannot hold, a ``seed`` that is not an integer or one per robot, a proposal that lacks a member
of the protocol). Per command the state's shape, dtype and device are checked (no host sync); its values (NaN),
the proposals' shapes and the costs' (all NaN for a robot) are checked when ``debug`` is on: by default on a CPU,
where reading a value is free, and off on CUDA, where it would wait for the device (``debug=True`` turns them on
there). A state that requires grad is detached (a controller never differentiates through its input). With
``convert_states=True`` a numpy state, or a tensor of another floating dtype, is converted once at the edge and the
command comes back as the state's type and dtype (without it such a state is refused, naming that fix).

``cuda_graph=True`` (a CUDA device): the first command is captured in one CUDA graph (plan and warm-start update,
for that batch shape) and every later command is one replay, so a command costs a few microseconds of launch
instead of one launch per small op. The proposal, cost and dynamics must be capturable: no value read back to
the host, no shape that depends on values (a table set, which picks members on the host, is not). Host-side
counters (a table's ``queries``) count the captured command only; device-side counts count every replay.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Protocol, overload

import numpy as np
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
    check_state_batch,
)
from cuniform_torch.controllers.proposals import (
    PROPOSAL_MEMBERS,
    SINGLE_ROBOT_MEMBERS,
    Closeable,
    Proposal,
    SingleRobotProposal,
    as_batched,
)
from cuniform_torch.controllers.result import MPPIResult
from cuniform_torch.controllers.streams import RobotStreams, robot_seeds
from cuniform_torch.controllers.temperature import auto_temperature, check_target_ess, temperature_weights
from cuniform_torch.systems import System, check_dynamics

__all__ = ["CostFn", "MPPIResult", "mppi_weights", "weighted_average", "MPPICore", "COST_CAP"]


class CostFn(Protocol):
    """Trajectory cost: ``states [N, T+1, d]``, ``actions [N, T, q]`` -> ``[N]`` (may be inf for collisions), a
    tensor of the controller's dtype on its device (``cuniform_torch.envs.NavigationCost`` is one). A batched
    controller hands it all B x K rollouts at once (N = B*K). A cost that differs per robot says
    ``batched = True`` (an attribute) and gets ``[B, K, T+1, d]``, ``[B, K, T, q]`` -> ``[B, K]``."""

    def __call__(self, states: Tensor, actions: Tensor) -> Tensor: ...


def mppi_weights(costs: Tensor, lambda_: float) -> Tensor:
    """``softmax(-(cost - min) / lambda)`` over the last dimension of ``costs [K]`` (or ``[B, K]``); ``lambda_ = 0``
    puts all weight on the argmin.

    ValueError when ``lambda_`` is not 0 nor a normal number of ``costs.dtype`` with a finite inverse.
    """
    return _weights(_finite_costs(costs), _check_lambda(lambda_, costs.dtype))


def weighted_average(weights: Tensor, actions: Tensor) -> Tensor:
    """Each robot's average of its K sequences: ``weights [B, K]``, ``actions [B, K, T, q]`` -> ``[B, T, q]``.

    A product summed over K, not a batched gemm: torch's sum over dim 1 of ``[B, K, T*q]`` adds a robot's K terms in
    an order that does not depend on B, so robot b's average is the same bits alone and in a batch, where a BLAS
    bmm's blocking rounds robots 1, 2, ... of a batch unlike one robot (float32, T*q = 15 or 30).
    ``tests/test_batch_invariance.py`` checks B = 1..64, K = 16..4096, T*q = 1..60, 1 and 4 threads.
    """
    b, k, t, q = actions.shape
    return (weights.unsqueeze(-1) * actions.reshape(b, k, t * q)).sum(dim=1).view(b, t, q)


def _weights(costs: Tensor, lambda_: float) -> Tensor:
    """:func:`mppi_weights` of finite ``costs [..., K]`` for a ``lambda_`` checked already."""
    if lambda_ == 0:
        return torch.nn.functional.one_hot(torch.argmin(costs, dim=-1), costs.shape[-1]).to(costs.dtype)
    return torch.softmax((costs - costs.amin(dim=-1, keepdim=True)).div_(-lambda_), dim=-1)


class MPPICore:
    """One MPPI controller of ``num_robots`` robots around any :class:`~cuniform_torch.controllers.proposals.Proposal`.

    ``plan(state) -> MPPIResult`` proposes, costs, weights (``lambda_``; 0 puts all the weight on the best
    proposal) and averages, per robot; ``command(state)`` plans, lets the proposal warm-start from the result and
    returns the first actions: ``state [B, d]`` -> ``[B, q]``, or one robot's ``state [d]`` -> ``[q]``. The
    number of robots is the proposal's (``num_robots``, set where the proposal is made: every controller takes
    it). Each robot draws from its own ``torch.Generator`` (``seed``: an int, one int per robot, or None; see
    :func:`~cuniform_torch.controllers.streams.robot_seeds`), so robot ``b`` of a batch commands exactly what a
    controller of that robot alone, seeded the same, commands. ``generator`` (one per robot) passes the streams in.
    ``close()`` (or ``with``) releases what the proposal holds (a bank's worker thread). ``debug``: see the module.
    ``on_plan``: an optional ``callable(result)`` seeing every command's result (the module docstring).

    :param proposal: a :class:`~cuniform_torch.controllers.proposals.Proposal` (or a one-robot proposal)
    :param cost_fn: ``states [N, T+1, d]``, ``actions [N, T, q]`` -> ``[N]`` over all robots' rollouts (or, with
        ``batched = True``, ``[B, K, T+1, d]`` -> ``[B, K]``)
    :param lambda_: the softmax temperature (0: all weight on the best rollout), or ``"auto"``: chosen per command
        and robot so that the weights' effective sample size is ``target_ess`` (reported in
        :attr:`MPPIResult.lambda_ <cuniform_torch.controllers.result.MPPIResult.lambda_>`)
    :param terminal_cost: optional cost of the last states, ``[N, d]`` -> ``[N]``
    :param seed: an int, one int per robot, or None
    :param generator: the streams themselves, one ``torch.Generator`` per robot (instead of ``seed``)
    :param debug: per-command value checks (default: on a CPU, off on CUDA)
    :param cuda_graph: one CUDA graph per command (CUDA only)
    :param target_ess: with ``lambda_="auto"``: the effective sample size aimed for, in ``[1, K]`` (default K / 10)
    :param convert_states: accept numpy states and tensors of another floating dtype (converted once; the command
        comes back as the state's type and dtype); False: such a state is a ValueError naming the fix
    """

    def __init__(self, proposal: Proposal | SingleRobotProposal, cost_fn: CostFn, lambda_: float | str = 0.567,
                 terminal_cost: Callable[[Tensor], Tensor] | None = None,
                 seed: int | Sequence[int] | None = None, *,
                 generator: torch.Generator | Sequence[torch.Generator] | None = None, debug: bool | None = None,
                 cuda_graph: bool = False, target_ess: float | None = None, convert_states: bool = False):
        if not isinstance(proposal, (Proposal, SingleRobotProposal)):
            members = SINGLE_ROBOT_MEMBERS if hasattr(proposal, "propose") else PROPOSAL_MEMBERS
            missing = [m for m in members if not hasattr(proposal, m)]
            raise TypeError(f"{type(proposal).__name__} is not a Proposal: it lacks {', '.join(missing)} (a proposal "
                            f"has {', '.join(PROPOSAL_MEMBERS)}; one of one robot has {', '.join(SINGLE_ROBOT_MEMBERS)})")
        for name, fn in (("cost_fn", cost_fn), ("terminal_cost", terminal_cost)):
            if fn is not None and not callable(fn):
                raise TypeError(f"{name} must be callable (states, actions) -> [K], got {type(fn).__name__}")
        if cost_fn is None:
            raise TypeError("cost_fn must be callable (states, actions) -> [K], got None")
        self.proposal = proposal
        self._batch = as_batched(proposal)
        """the proposal as the batched protocol (a one-robot proposal is adapted)"""
        self.system: System = proposal.system
        self.cost_fn = cost_fn
        self.terminal_cost = terminal_cost
        self._cost_batched = getattr(cost_fn, "batched", False) is True
        self._terminal_batched = getattr(terminal_cost, "batched", False) is True
        self.num_samples = check_positive_int("num_samples", proposal.num_samples)
        self.horizon = check_positive_int("horizon", proposal.horizon)
        self.num_robots = check_positive_int("num_robots", self._batch.num_robots)
        self.device = torch.device(proposal.device)
        dtype = proposal.dtype
        if not (isinstance(dtype, torch.dtype) and dtype.is_floating_point):
            raise ValueError(f"dtype must be a floating-point torch.dtype, got {dtype!r}")
        self.dtype = dtype
        self.auto_lambda = isinstance(lambda_, str) and lambda_ == "auto"
        """the temperature is chosen per command (``lambda_="auto"``)"""
        if target_ess is not None and not self.auto_lambda:
            raise ValueError(f"target_ess={target_ess!r} sets the automatic temperature: pass lambda_=\"auto\" too "
                             f"(lambda_={lambda_!r} is a fixed temperature)")
        if isinstance(lambda_, str) and not self.auto_lambda:
            raise ValueError(f"lambda_ must be a number >= 0 or \"auto\", got {lambda_!r}")
        self.lambda_: float | str = "auto" if self.auto_lambda else _check_lambda(lambda_, dtype)  # type: ignore[arg-type]
        self.target_ess = check_target_ess(target_ess, self.num_samples) if self.auto_lambda else None
        """the effective sample size the automatic temperature aims for (None: a fixed ``lambda_``)"""
        self.convert_states = bool(convert_states)
        action_cost = getattr(proposal, "action_cost", None)
        self._action_cost: Callable[[Tensor], Tensor] | None = action_cost if callable(action_cost) else None
        """the proposal's cost of its own actions (``[B, K, T, q]`` -> ``[B, K]``), weighed as pytorch_mppi does"""
        self.state_dim = len(self.system.periodic)
        # a user system's action set and step, probed once here (a no-op for one its proposal already probed)
        self.action_dim = check_dynamics(self.system, dtype, self.device).shape[1]
        self.debug = (self.device.type == "cpu") if debug is None else bool(debug)
        """check values per command (NaN states, the proposals' shapes, all-NaN costs): needs a host read"""
        if generator is not None:
            if seed is not None:
                raise ValueError("pass a seed or a generator, not both")
            generators = [generator] if isinstance(generator, torch.Generator) else list(generator)
            if len(generators) != self.num_robots:
                raise ValueError(f"generator: this controller has {self.num_robots} robots and needs one stream each, "
                                 f"got {len(generators)}; or pass seed (an int, or one per robot)")
            for g in generators:
                check_generator(g, self.device)
            self.streams = RobotStreams(generators)
        else:
            self.streams = RobotStreams.seeded(robot_seeds(seed, self.num_robots), self.device)
        self.generator = self.streams.generators[0]
        """robot 0's stream of random numbers (the only one of a one-robot controller)"""
        self.cuda_graph = bool(cuda_graph)
        """``command`` replays one CUDA graph of the whole command (captured at the first one)"""
        if self.cuda_graph and (self.device.type != "cuda" or self.debug):
            raise ValueError("cuda_graph=True needs a CUDA device and debug off (a per-command value check reads the "
                             f"device); this controller is on {self.device} with debug={self.debug}")
        self._graph: torch.cuda.CUDAGraph | None = None
        self._static_state: Tensor | None = None
        self._static_command: Tensor | None = None
        self._fixed_lambda = (None if self.auto_lambda else torch.full(
            (self.num_robots,), float(self.lambda_), dtype=dtype, device=self.device))  # type: ignore[arg-type]
        """``[B]`` the fixed temperature, made once: every result reports it (no tensor made per command)"""
        self._on_plan: Callable[[MPPIResult], None] | None = None

    @property
    def on_plan(self) -> Callable[[MPPIResult], None] | None:
        """A trace hook: ``callable(result)`` called by :meth:`command` and :meth:`command_result` with the command's
        :class:`MPPIResult` (batched ``[B, ...]``, or one robot's when the state was ``[d]``), after the warm-start
        update and before the command is returned; None (the default): nothing is called. Not with ``cuda_graph``
        (a replay has no result to show)."""
        return self._on_plan

    @on_plan.setter
    def on_plan(self, hook: Callable[[MPPIResult], None] | None) -> None:
        if hook is not None and not callable(hook):
            raise TypeError(f"on_plan must be a callable(result) or None, got {type(hook).__name__}")
        if hook is not None and self.cuda_graph:
            raise ValueError("on_plan sees each command's result; with cuda_graph=True a command is one replay of a "
                             "captured graph and has none: use cuda_graph=False to trace")
        self._on_plan = hook

    # -------------------------------------------------------------------------------- the one MPPI iteration

    def plan(self, state: Tensor | np.ndarray) -> MPPIResult:
        """One MPPI iteration from ``state [B, d]`` (or one robot's ``[d]``); the warm starts are left as they were.
        (With ``convert_states``, the result is in the controller's dtype, whatever the state's.)"""
        given: object = self._convert(state)[0] if self.convert_states else state
        states, single = self._check_state(given)
        result = self._plan(states)
        return result.robot(0) if single else result

    def _plan(self, state: Tensor) -> MPPIResult:
        """The iteration for checked ``state [B, d]``: a batched result."""
        states, actions = self._batch.propose_batch(state, self.streams)
        if self.debug:
            self._check_proposals(states, actions)
        costs, weights, lambdas = self._evaluate(states, actions)
        nominal = weighted_average(weights, actions)  # [B, T, q]
        return MPPIResult(nominal[:, 0], nominal, states, actions, costs, weights, lambdas)

    @overload
    def command(self, state: Tensor) -> Tensor: ...

    @overload
    def command(self, state: np.ndarray) -> np.ndarray: ...

    def command(self, state: Tensor | np.ndarray) -> Tensor | np.ndarray:
        """The controls to apply at ``state [B, d]``: ``[B, q]`` (one robot's ``[d]`` -> ``[q]``); the proposal
        warm-starts the next command from this one. With ``convert_states``, a numpy state gets a numpy command
        and a tensor of another dtype a command of its dtype."""
        given, back = self._convert(state) if self.convert_states else (state, None)
        states, single = self._check_state(given)
        if self.cuda_graph:
            command = self._replay(states)
        else:
            result = self._plan(states)
            self._batch.update(result)
            command = result.command
            if self._on_plan is not None:
                self._on_plan(result.robot(0) if single else result)
        command = command[0] if single else command
        return command if back is None else back(command)

    def command_result(self, state: Tensor | np.ndarray) -> MPPIResult:
        """:meth:`command`'s whole work: the same iteration and warm start, returning the :class:`MPPIResult`
        (``result.command`` is what ``command`` returns, in the controller's dtype; ``result.lambda_`` the
        temperature used, ``result.ess`` the weights' effective sample size). Eager: not with ``cuda_graph``."""
        if self.cuda_graph:
            raise ValueError("command_result runs the command eagerly; with cuda_graph=True use command(state) (one "
                             "replay of the captured graph)")
        given: object = self._convert(state)[0] if self.convert_states else state
        states, single = self._check_state(given)
        result = self._plan(states)
        self._batch.update(result)
        result = result.robot(0) if single else result
        if self._on_plan is not None:
            self._on_plan(result)
        return result

    # -------------------------------------------------------------------------------- one CUDA graph per command

    def _generators(self) -> list[torch.Generator]:
        """Every stream a command draws from (a two-stage controller's first stage has its own)."""
        extra = getattr(self.proposal, "extra_streams", None)  # a two-stage proposal's first-stage streams
        return list(self.streams.generators) + (list(extra.generators) if isinstance(extra, RobotStreams) else [])

    def _replay(self, states: Tensor) -> Tensor:
        """The command of ``states [B, d]`` by one replay of the captured graph: ``[B, q]``."""
        if self._graph is None:
            self._capture(states)
        assert self._graph is not None and self._static_state is not None and self._static_command is not None
        self._static_state.copy_(states)
        self._graph.replay()
        return self._static_command.clone()

    def _capture(self, states: Tensor) -> None:
        """Capture plan + warm-start update for states of this shape in one CUDA graph (after two warm-up plans on a
        side stream, whose draws are given back to the streams, so the first command draws what an eager one
        would). Every stream is registered with the graph: each replay draws fresh numbers."""
        gens = self._generators()
        saved = [g.get_state() for g in gens]
        self._static_state = states.clone()
        side = torch.cuda.Stream(device=self.device)
        side.wait_stream(torch.cuda.current_stream(self.device))
        with torch.cuda.stream(side):
            for _ in range(2):  # lazy initialisations (cuBLAS workspaces, caches) happen outside the capture
                self._plan(self._static_state)
        torch.cuda.current_stream(self.device).wait_stream(side)
        for g, state in zip(gens, saved):
            g.set_state(state)
        graph = torch.cuda.CUDAGraph()
        for g in gens:
            graph.register_generator_state(g)
        try:
            with torch.cuda.graph(graph):
                result = self._plan(self._static_state)
                self._batch.update(result)
        except RuntimeError as exc:
            raise RuntimeError(f"cuda_graph: the command could not be captured ({exc}); a cost, dynamics or proposal "
                               f"that reads a value back to the host, or whose shapes depend on values, cannot run "
                               f"in a CUDA graph: use cuda_graph=False") from None
        self._graph, self._static_command = graph, result.command

    def reset(self, robots: Sequence[int] | Tensor | None = None) -> None:
        """The start of an episode for ``robots`` (indices; None: all): the proposal forgets their warm starts (in
        place: a captured CUDA graph goes on reading them)."""
        if robots is not None:
            ids = torch.as_tensor(robots).reshape(-1)
            if ids.dtype.is_floating_point or ids.dtype == torch.bool or bool(
                    ((ids < 0) | (ids >= self.num_robots)).any()):
                raise ValueError(f"robots must be indices in 0..{self.num_robots - 1}, got {robots!r:.80}")
            robots = ids.to(torch.long)
        self._batch.reset(robots)

    def close(self) -> None:
        """Release what the proposal holds (a background worker); calling it again does nothing."""
        if isinstance(self.proposal, Closeable):
            self.proposal.close()

    def __enter__(self) -> MPPICore:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    # -------------------------------------------------------------------------------- checks

    def _convert(self, state: object) -> tuple[object, Callable[[Tensor], Tensor | np.ndarray] | None]:
        """``convert_states``: a numpy state (or a floating tensor of another dtype) as a tensor of the controller's
        dtype and device, converted once, and how to give the command back in the state's type and dtype (None:
        nothing to convert). Anything else passes through to the state check."""
        if isinstance(state, Tensor):
            if state.dtype == self.dtype or not state.is_floating_point():
                return state, None
            dtype = state.dtype
            return state.to(self.dtype), lambda u: u.to(dtype)
        if isinstance(state, np.ndarray):
            if state.dtype.kind != "f":
                raise ValueError(f"state is a numpy array of {state.dtype}; a state is floating point (e.g. "
                                 f"state.astype(np.float64))")
            np_dtype = state.dtype
            tensor = torch.as_tensor(state, dtype=self.dtype, device=self.device)
            return tensor, lambda u: u.detach().cpu().numpy().astype(np_dtype, copy=False)
        return state, None

    def _check_state(self, state: object) -> tuple[Tensor, bool]:
        """``state [B, d]`` (or ``[d]``: one robot) of the controller's dtype and device, detached; finite when
        ``debug``. Returns ``[B, d]`` and whether one ``[d]`` state was given."""
        return check_state_batch(state, self.num_robots, self.state_dim, self.dtype, self.device, self.debug)

    def _check_proposals(self, states: Tensor, actions: Tensor) -> None:
        """What ``propose_batch`` returned: ``[B, K, T+1, d]`` states and ``[B, K, T, q]`` actions (a proposal of
        one robot: its ``[K, T+1, d]`` and ``[K, T, q]``)."""
        shape = (self.num_samples, self.horizon, self.state_dim, self.action_dim)
        if self._batch is self.proposal:
            check_proposals(type(self.proposal).__name__, states, actions, (self.num_robots, *shape), self.dtype,
                            self.device)
        else:
            check_proposals(type(self.proposal).__name__, states[0], actions[0], shape, self.dtype, self.device)

    def _cost(self, fn: Callable, batched: bool, who: str, states: Tensor, actions: Tensor | None) -> Tensor:
        """``fn``'s costs ``[B, K]`` of ``states [B, K, T+1, d]`` (``actions`` None: a terminal cost of the last
        states), called batched or on the flattened ``B*K`` rollouts."""
        b, k = states.shape[:2]
        if batched:
            out = fn(states, actions) if actions is not None else fn(states[:, :, -1])
            return _check_costs(out, who, fn, (b, k), self.dtype, self.device)
        flat = states.reshape(b * k, *states.shape[2:])
        out = fn(flat, actions.reshape(b * k, *actions.shape[2:])) if actions is not None else fn(flat[:, -1])
        return _check_costs(out, who, fn, (b * k,), self.dtype, self.device).view(b, k)

    def _state_costs(self, states: Tensor, actions: Tensor) -> Tensor:
        """Finite costs ``[B, K]`` of the proposals (``cost_fn`` + ``terminal_cost``, checked; no action cost)."""
        costs = self._cost(self.cost_fn, self._cost_batched, "cost_fn", states, actions)
        if self.terminal_cost is not None:
            costs = costs + self._cost(self.terminal_cost, self._terminal_batched, "terminal_cost", states, None)
        if self.debug and bool(torch.isnan(costs).all(dim=-1).any()):  # NaN everywhere: a broken cost, not a choice
            k = costs.shape[-1]
            raise ValueError(f"cost_fn {_callable_name(self.cost_fn)}"
                             f"{'' if self.terminal_cost is None else ' + terminal_cost ' + _callable_name(self.terminal_cost)}"
                             f" returned NaN for all {k} proposals of a robot; expected a [{k}] tensor of costs")
        return _finite_costs(costs)

    def _evaluate(self, states: Tensor, actions: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Finite costs ``[B, K]`` of the proposals, their weights ``[B, K]`` and the temperature ``[B]`` that
        weighed them; the user's costs are checked."""
        costs = self._state_costs(states, actions)
        extra = None if self._action_cost is None else self._action_cost(actions)  # [B, K], not over lambda
        if self._fixed_lambda is not None:
            lam = float(self.lambda_)  # type: ignore[arg-type]
            if extra is not None:  # pytorch_mppi's total cost: state costs + lambda * U Sigma^-1 eps
                costs = _finite_costs(costs + lam * extra)
            return costs, _weights(costs, lam), self._fixed_lambda
        assert self.target_ess is not None
        lambdas = auto_temperature(costs, self.target_ess, extra)  # [B]
        weights = temperature_weights(costs, lambdas, extra)
        if extra is not None:
            costs = _finite_costs(costs + lambdas.unsqueeze(1) * extra)
        return costs, weights, lambdas
