"""Proposals: the plug-in of the MPPI core (:class:`~cuniform_torch.controllers.mppi.MPPICore`).

Shapes: B robots, K proposals per robot, T horizon, d state dimensions, q action dimensions, M rollouts in a bank.

A proposal draws the K trajectories per robot that a command weighs, for B robots at once. Per command the core
calls

* ``states [B, K, T+1, d], actions [B, K, T, q] = proposal.propose_batch(states [B, d], streams)`` (robot ``b``
  draws from ``streams.generators[b]``), then costs and weights them into an
  :class:`~cuniform_torch.controllers.result.MPPIResult`;
* ``proposal.update(result)`` (only from ``command``; ``plan`` leaves the proposal as it was): the warm starts;

and ``proposal.reset(robots)`` at the start of an episode. :class:`Proposal` declares that, and the attributes the
core reads (``system``, ``num_samples`` K, ``horizon`` T, ``num_robots`` B, ``device``, ``dtype``). Any object
with them drops into the core; a proposal of one robot (:class:`SingleRobotProposal`: ``propose(state [d],
generator)``) still does, for one robot. The ones here:

* :class:`GaussianProposal` (MPPI): Gaussian noise around a nominal sequence, clipped to the action bounds; the
  warm start is the command's weighted sequence shifted one step (its last action repeated).
* :class:`NormalLogNormalProposal` (log-MPPI): the same with normal x log-normal noise.
* :class:`PolicyProposal` (C-Uniform MPPI): fresh C-Uniform rollouts of a policy (a table or an MLP) from the
  pose; no warm start.
* ``BankProposal`` (C-Uniform MPPI with a bank, in :mod:`cuniform_torch.controllers.bank`, with its background
  worker): M rollouts pre-sampled at the origin; each command takes a random subset of K of them and moves it to
  the pose by a rigid transform, refreshed every ``refresh`` commands.
* :class:`CompositeProposal` (CU-MPPI): the lowest-cost trajectory of a first planner (C-Uniform MPPI) becomes
  the nominal of a local Gaussian or log-normal proposal.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol, cast, runtime_checkable

import torch
from torch import Tensor

from cuniform_torch.controllers.checks import _check_dtype, check_positive_int
from cuniform_torch.controllers.result import MPPIResult
from cuniform_torch.controllers.streams import RobotStreams
from cuniform_torch.policies.checkpoint import load_policy
from cuniform_torch.policies.table_set import MemberRows
from cuniform_torch.sampling.noise import GaussianSampler, NormalLogNormalSampler
from cuniform_torch.sampling.rollout import (
    Policy,
    PolicyCapabilities,
    PolicyTraits,
    RolloutPlan,
    open_loop,
    same_device,
)
from cuniform_torch.systems import System, check_dynamics

__all__ = ["Proposal", "SingleRobotProposal", "as_batched", "GaussianProposal", "NormalLogNormalProposal", "PolicyProposal", "CompositeProposal",
           "PROPOSAL_MEMBERS", "SINGLE_ROBOT_MEMBERS", "OneRobotCall", "PipelinedProposal", "default_noise_std",
           "NOISE_FRACTION"]


@runtime_checkable
class Proposal(Protocol):
    """What the MPPI core needs from a proposal: K trajectories per robot and command, for B robots at once, and
    the hooks around a command. Settled when the core is made (no probing per command)."""

    system: System
    """the dynamics the trajectories follow (the core reads its state dimension and action set)"""
    num_samples: int
    """K: trajectories per robot and :meth:`propose_batch`"""
    horizon: int
    """T: steps per trajectory"""
    num_robots: int
    """B: robots per call (each with its own warm start)"""
    device: torch.device
    """where the trajectories are (the states handed to :meth:`propose_batch` are there too)"""
    dtype: torch.dtype
    """their floating-point dtype (the states' too)"""

    def propose_batch(self, states: Tensor, streams: RobotStreams) -> tuple[Tensor, Tensor]:
        """``states [B, d]`` (checked: of ``dtype`` on ``device``) -> ``[B, K, T+1, d]`` (``[:, :, 0]`` the
        states) and ``[B, K, T, q]``. Robot ``b`` draws from ``streams.generators[b]`` only (all robots' draws in
        one :meth:`~cuniform_torch.controllers.streams.RobotStreams.rand` / ``randn`` call), so a batch repeats
        what its robots would draw alone."""
        ...

    def update(self, result: MPPIResult) -> None:
        """After a command: warm-start the next one from the batched ``result`` (or do nothing)."""
        ...

    def reset(self, robots: Tensor | None = None) -> None:
        """The start of an episode for ``robots`` (``[n]`` int64 indices; None: all): forget their warm starts."""
        ...


@runtime_checkable
class SingleRobotProposal(Protocol):
    """A proposal of one robot (the protocol before batching, still accepted for one robot):
    ``propose(state [d], generator) -> [K, T+1, d], [K, T, q]``, ``update(result)`` of that robot,
    ``reset()``."""

    system: System
    num_samples: int
    horizon: int
    device: torch.device
    dtype: torch.dtype

    def propose(self, state: Tensor, generator: torch.Generator) -> tuple[Tensor, Tensor]:
        ...

    def update(self, result: MPPIResult) -> None:
        ...

    def reset(self) -> None:
        ...


PROPOSAL_MEMBERS = ("system", "num_samples", "horizon", "num_robots", "device", "dtype", "propose_batch", "update",
                    "reset")
"""the members of :class:`Proposal`, for error messages"""
SINGLE_ROBOT_MEMBERS = ("system", "num_samples", "horizon", "device", "dtype", "propose", "update", "reset")
"""the members of :class:`SingleRobotProposal`"""


class OneRobotCall:
    """``propose(state [d], generator)``: one robot's proposals from a batched proposal of one robot (robot 0 of a
    batch of one; a convenience for tests and tools)."""

    num_robots: int
    propose_batch: Callable[[Tensor, RobotStreams], tuple[Tensor, Tensor]]
    """the subclass's batched draw (:class:`Proposal`)"""

    def propose(self, state: Tensor, generator: torch.Generator) -> tuple[Tensor, Tensor]:
        """``state [d]`` -> ``[K, T+1, d]``, ``[K, T, q]``."""
        if self.num_robots != 1:
            raise ValueError(f"propose(state, generator) is one robot's; this proposal has {self.num_robots}: "
                             f"use propose_batch(states, streams)")
        states, actions = self.propose_batch(state.unsqueeze(0), RobotStreams([generator]))
        return states[0], actions[0]


class _OneRobot:
    """A :class:`SingleRobotProposal` seen through the batched protocol, for one robot."""

    num_robots = 1

    def __init__(self, proposal: SingleRobotProposal):
        self.inner = proposal
        self.system, self.num_samples, self.horizon = proposal.system, proposal.num_samples, proposal.horizon
        self.device, self.dtype = proposal.device, proposal.dtype

    def propose_batch(self, states: Tensor, streams: RobotStreams) -> tuple[Tensor, Tensor]:
        out_states, out_actions = self.inner.propose(states[0], streams.generators[0])
        if not (isinstance(out_states, Tensor) and isinstance(out_actions, Tensor)):
            raise ValueError(f"{type(self.inner).__name__}.propose returned {type(out_states).__name__} and "
                             f"{type(out_actions).__name__}; expected [K, T+1, d] and [K, T, q] tensors")
        return out_states.unsqueeze(0), out_actions.unsqueeze(0)

    def update(self, result: MPPIResult) -> None:
        self.inner.update(result.robot(0))

    def reset(self, robots: Tensor | None = None) -> None:
        self.inner.reset()


def as_batched(proposal: Proposal | SingleRobotProposal) -> Proposal:
    """``proposal`` as the batched protocol (a :class:`SingleRobotProposal` serves one robot)."""
    if isinstance(proposal, Proposal):
        return proposal
    return _OneRobot(proposal)


@runtime_checkable
class Closeable(Protocol):
    """A proposal that holds a resource (a worker thread) until ``close()``."""

    def close(self) -> None:
        ...


class Planner(Protocol):
    """A controller's first stage (what :class:`CompositeProposal` seeds from): ``_best_actions(states [B, d])``
    -> each robot's lowest-cost proposal ``[B, T, q]``, drawing from its ``streams``."""

    streams: RobotStreams

    def _best_actions(self, state: Tensor) -> Tensor:
        ...

    def reset(self, robots: Tensor | None = None) -> None:
        ...


def _start_rows(states: Tensor, k: int) -> Tensor:
    """Each robot's state once per sample: ``[B, d]`` -> ``[B*K, d]`` (one robot: the ``[d]`` state itself, which
    the rollouts expand for free)."""
    return states[0] if states.shape[0] == 1 else states.repeat_interleave(k, dim=0)


# ------------------------------------------------------------------------------------------ Gaussian, log-normal

NOISE_FRACTION = 0.25
"""the default noise std, per action dimension, as a fraction of its range ``high - low``: the range is the mean
+- 2 std (a system whose actions span [-2, 2] gets std 1)"""


def default_noise_std(low: Tensor, high: Tensor) -> Tensor:
    """The noise std when none is given: :data:`NOISE_FRACTION` of each action dimension's range, ``[q]``.
    ValueError for an unbounded (or zero-width) dimension, naming what to give instead."""
    std = (high - low) * NOISE_FRACTION  # [q]
    if not bool(torch.isfinite(std).all()) or not bool((std > 0).all()):
        raise ValueError(f"no noise scale was given and the action bounds [{low.tolist()}, {high.tolist()}] do not "
                         f"set one (an unbounded or zero-width dimension): give noise_std (a std, scalar or [q]) or "
                         f"noise_sigma (a covariance), or finite bounds u_min / u_max")
    return std

class GaussianProposal(OneRobotCall):
    """MPPI's proposal: ``actions = clip(nominal + eps)``, ``eps ~ N(0, noise_std^2)`` (scalar or ``[q]`` std),
    rolled out open-loop from each robot's state; the warm start shifts each robot's weighted sequence one step.

    ``nominal`` (``[T, q]`` for one robot, ``[B, T, q]`` for ``num_robots`` B) starts at zero (``reset()``); set it
    to seed the next proposals. ``noise_std=None``: a quarter of each action dimension's range
    (:func:`default_noise_std`).
    """

    def __init__(self, system: System, num_samples: int, horizon: int, noise_std: float | Tensor | None = 0.3,
                 device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32, num_robots: int = 1):
        self.system = system
        self.num_samples = check_positive_int("num_samples", num_samples)
        self.horizon = check_positive_int("horizon", horizon)
        self.num_robots = check_positive_int("num_robots", num_robots)
        self.device = torch.device(device)
        self.dtype = _check_dtype(dtype)
        actions = check_dynamics(system, self.dtype, self.device)  # [A, q]: the user's step probed once, here
        self.low, self.high = actions.min(dim=0).values, actions.max(dim=0).values  # [q] action bounds
        self.low, self.high = self._bounds(self.low, self.high)
        if noise_std is None:
            noise_std = default_noise_std(self.low, self.high)
        self.noise_std = noise_std
        self._nominal = torch.zeros((self.num_robots, self.horizon, self.low.shape[0]), dtype=self.dtype,
                                    device=self.device)  # [B, T, q]
        self.law = self._law(noise_std)  # the noise law, built (and its std checked) once
        self.std = self.law.std  # [q]

    def _bounds(self, low: Tensor, high: Tensor) -> tuple[Tensor, Tensor]:
        """The action bounds ``[q]`` each, from the action set's range; a subclass may widen them (to +-inf)."""
        return low, high

    def _law(self, noise_std: float | Tensor) -> GaussianSampler:
        return GaussianSampler(self._nominal[0], noise_std, self.low, self.high)

    @property
    def nominal(self) -> Tensor:
        """The sequences the next proposals are drawn around: ``[T, q]`` for one robot, else ``[B, T, q]``."""
        return (self._nominal[0] if self.num_robots == 1 else self._nominal).clone()  # a snapshot: updated in place

    @nominal.setter
    def nominal(self, value: Tensor) -> None:
        t, q = self.horizon, self.low.shape[0]
        ok = (isinstance(value, Tensor) and value.shape in ((t, q), (self.num_robots, t, q))
              and value.dtype == self.dtype and same_device(value.device, self.device))
        if not ok:
            want = f"[{t}, {q}]" + (f" or [{self.num_robots}, {t}, {q}]" if self.num_robots > 1 else "")
            raise ValueError(f"nominal must be a {want} tensor of {self.dtype} on {self.device}, got "
                             + (f"{list(value.shape)} of {value.dtype} on {value.device}" if isinstance(value, Tensor)
                                else type(value).__name__))
        self._nominal.copy_(value.detach().expand(self.num_robots, t, q))

    # the warm start is updated in place: a command captured in a CUDA graph reads and writes this one tensor
    def seed(self, nominal: Tensor) -> None:
        """Draw the next proposals around ``nominal [B, T, q]`` (checked by the caller; CU-MPPI's first stage)."""
        self._nominal.copy_(nominal)

    def _noise(self, streams: RobotStreams, n: int) -> Tensor:
        """``[B, n, q]`` zero-mean noise, robot ``b``'s from its own stream."""
        return streams.randn((n, self.low.shape[0]), self.dtype).mul_(self.std)

    def _sequences(self, streams: RobotStreams, k: int, t: int) -> Tensor:
        """``[B, K, T, q]`` zero-mean noise sequences (a fresh tensor: updated in place)."""
        return self._noise(streams, k * t).view(-1, k, t, self.low.shape[0])

    def propose_batch(self, states: Tensor, streams: RobotStreams) -> tuple[Tensor, Tensor]:
        b, k, t, q = states.shape[0], self.num_samples, self.horizon, self.low.shape[0]
        actions = self._sequences(streams, k, t)  # [B, K, T, q], a fresh tensor: updated in place
        actions.add_(self._nominal.unsqueeze(1)).clamp_(self.low, self.high)  # [B, K, T, q]
        trajectories = open_loop(self.system, _start_rows(states, k), actions.view(b * k, t, q))  # [B*K, T+1, d]
        return trajectories.view(b, k, t + 1, -1), actions

    def update(self, result: MPPIResult) -> None:
        """Warm start: each robot's weighted sequence shifted one step, its last action repeated."""
        nominal = result.nominal if result.nominal.ndim == 3 else result.nominal.unsqueeze(0)  # [B, T, q]
        self._nominal.copy_(torch.cat((nominal[:, 1:], nominal[:, -1:]), dim=1))

    def reset(self, robots: Tensor | None = None) -> None:
        """Zero nominal (the start of an episode) for ``robots`` (None: all)."""
        if robots is None:
            self._nominal.zero_()
        else:
            self._nominal.index_fill_(0, robots.to(self.device), 0.0)


class NormalLogNormalProposal(GaussianProposal):
    """log-MPPI's proposal: :class:`GaussianProposal` with normal x log-normal noise (Mohamed et al.); the
    log-normal factor has mean ``lognormal_mean`` and variance ``lognormal_var``
    (:class:`~cuniform_torch.sampling.noise.NormalLogNormalSampler`)."""

    def __init__(self, system: System, num_samples: int, horizon: int, noise_std: float | Tensor | None = 0.3,
                 lognormal_mean: float = 1.0, lognormal_var: float = 1.0, device: torch.device | str = "cpu",
                 dtype: torch.dtype = torch.float32, num_robots: int = 1):
        self.lognormal_mean, self.lognormal_var = lognormal_mean, lognormal_var
        super().__init__(system, num_samples, horizon, noise_std, device, dtype, num_robots)

    def _law(self, noise_std: float | Tensor) -> NormalLogNormalSampler:
        return NormalLogNormalSampler(self._nominal[0], noise_std, self.low, self.high,
                                      lognormal_mean=self.lognormal_mean, lognormal_var=self.lognormal_var)

    def _noise(self, streams: RobotStreams, n: int) -> Tensor:
        """``[B, n, q]``: normal x log-normal; each robot's two factors from one draw of its stream."""
        law = cast(NormalLogNormalSampler, self.law)
        z = streams.randn((2, n, self.low.shape[0]), self.dtype)  # [B, 2, n, q]
        return (z[:, 0] * self.std).mul_(z[:, 1].mul_(law.sigma).add_(law.mu).exp_())  # [B, n, q] contiguous


# ------------------------------------------------------------------------------------------ policy

def _as_policy(policy: object, device: torch.device) -> Policy:
    """A Policy object, or a distilled-policy checkpoint dict (``torch.load(path, weights_only=True)``), loaded by
    :func:`~cuniform_torch.policies.checkpoint.load_policy` (which knows the format)."""
    if isinstance(policy, dict):
        return load_policy(policy, device=device)
    if not isinstance(policy, Policy):
        raise ValueError(f"policy must have actions [A, q] and action_probs(x, t); got {type(policy).__name__}")
    return policy


class PolicyProposal(OneRobotCall):
    """C-Uniform MPPI's proposal: K rollouts of ``policy`` (a table, an MLP, any
    :class:`~cuniform_torch.sampling.rollout.Policy` with a ``system``, or a checkpoint dict) from each robot's
    pose. No warm start.

    ``horizon`` defaults to the policy's own (a table's T; required for a policy without one); ``device`` to the
    policy's (else the CPU); the dtype is the policy's (else float32). Each command draws every robot's uniforms up
    front (``[B, T, K]``, one call per robot) and rolls all B x K out together: one rollout for a policy that serves
    every start (a table, an MLP: on an SE(2)-invariant system in each robot's frame), one per member used for a
    table set (each robot's member is the one nearest its start), one per robot for a policy that is set per start
    (``for_start``: a start-conditioned MLP). What it reads of the policy is settled here, once
    (:class:`~cuniform_torch.sampling.contract.PolicyCapabilities`).

    :param policy: a :class:`~cuniform_torch.sampling.contract.Policy` with a ``system``, or a checkpoint dict
    :param num_samples: K rollouts per robot
    :param horizon: T (default: the policy's)
    :param device: where a checkpoint dict is loaded (default: the policy's, else the CPU)
    :param num_robots: B robots per command
    :param condition: ``condition(states [B, d])``, called once per command before the rollout: the caller sets
        the policy's per-robot input there (CFU-MPPI: each robot's local map, sensed and encoded as one batch)
    """

    def __init__(self, policy: object, num_samples: int, horizon: int | None = None,
                 device: torch.device | str | None = None, num_robots: int = 1,
                 condition: Callable[[Tensor], None] | None = None):
        if condition is not None and not callable(condition):
            raise ValueError(f"condition must be a callable of the robots' states [B, d], got "
                             f"{type(condition).__name__}")
        self.condition = condition
        """called once per command with every robot's state ``[B, d]``, before the rollout: what the policy is
        conditioned on is set there, by its owner (CFU-MPPI senses and encodes each robot's local map)"""
        traits = PolicyTraits.of(policy) if not isinstance(policy, dict) else PolicyTraits()
        self.device = torch.device(device) if device is not None else (traits.device or torch.device("cpu"))
        self.policy = _as_policy(policy, self.device)
        caps = PolicyCapabilities.of(self.policy)
        self.capabilities = caps
        """what the policy declares (:class:`~cuniform_torch.sampling.contract.PolicyCapabilities`), read here once:
        a command reads only this record"""
        traits = caps.traits
        if traits.device is not None and not same_device(traits.device, self.device):
            raise ValueError(f"the policy is on {traits.device} but device={self.device} was asked for")
        if caps.system is None:
            raise ValueError(f"{type(self.policy).__name__} has no system: a proposal needs the policy's dynamics")
        self.system: System = caps.system
        horizon = horizon if horizon is not None else traits.horizon
        if horizon is None:
            raise ValueError("horizon is required for a policy without a table horizon")
        self.horizon = check_positive_int("horizon", horizon)
        if traits.horizon is not None and self.horizon > traits.horizon:
            raise ValueError(f"horizon {self.horizon} is longer than the policy's table ({traits.horizon} steps)")
        self.num_samples = check_positive_int("num_samples", num_samples)
        self.num_robots = check_positive_int("num_robots", num_robots)
        self.dtype = traits.dtype or torch.float32
        check_dynamics(self.system, self.dtype, self.device)  # a user system's step, probed once (cached)
        self.plan = RolloutPlan.of(self.system, self.policy, caps)
        """how the policy is rolled out, settled here: a command runs it without the per-call checks"""
        self._members = caps.table_set
        """a table set: robots are grouped by the member nearest their start"""
        self._dispatch = (MemberRows.reusable(caps.member(0)) if self._members and caps.member is not None
                          else None)
        """a table set's members answering their robots' rows of one rollout (set per command), and its plan"""
        self._dispatch_plan = (RolloutPlan.of(self.system, self._dispatch) if self._dispatch is not None else None)
        self._per_start = not self._members and caps.for_start is not None
        """a policy set per start (``for_start`` only): each robot is rolled out on its own"""
        self._episode = caps.new_episode
        if self._episode is not None:
            self._episode()  # a controller's first episode: its off-start rollouts warn afresh

    def _groups(self, states: Tensor) -> list[list[int]] | None:
        """Robots rolled out together (each group in one rollout); None: all of them at once. Only a policy set per
        start (``for_start`` alone) needs groups: one robot each."""
        b = states.shape[0]
        return [[i] for i in range(b)] if b > 1 and self._per_start else None

    def propose_batch(self, states: Tensor, streams: RobotStreams) -> tuple[Tensor, Tensor]:
        b, k, t = states.shape[0], self.num_samples, self.horizon
        uniforms = streams.rand((t, k), self.dtype)  # [B, T, K]: robot b's from its own stream
        if self.condition is not None:  # the controller's per-command input (B local maps), set before the rollout
            self.condition(states)
        if b > 1 and self._members:  # a table set: one rollout, each member drawing for its robots' rows
            assert self.capabilities.nearest is not None  # a table set declares it
            index = self.capabilities.nearest(states)[0].tolist()  # [B] each robot's member (host ints)
            return self._members_rollout(states, index, uniforms)
        groups = self._groups(states)
        if groups is None:
            flat = uniforms[0] if b == 1 else uniforms.transpose(0, 1).reshape(t, b * k)  # [T, B*K] robot-major
            x, u = self.plan.run(self.system, self.policy, _start_rows(states, k), b * k, t, None, flat)
            return x.view(b, k, t + 1, -1), u.view(b, k, t, -1)
        out_x = out_u = None
        for robots in groups:  # the robots of a per-start policy
            rows = torch.tensor(robots, device=states.device)
            n = len(robots)
            flat = uniforms.index_select(0, rows).transpose(0, 1).reshape(t, n * k)
            x, u = self.plan.run(self.system, self.policy, _start_rows(states.index_select(0, rows), k), n * k, t,
                                 None, flat)
            if out_x is None or out_u is None:
                out_x = x.new_empty((b, k, t + 1, x.shape[-1]))
                out_u = u.new_empty((b, k, t, u.shape[-1]))
            out_x[rows] = x.view(n, k, t + 1, -1)
            out_u[rows] = u.view(n, k, t, -1)
        assert out_x is not None and out_u is not None
        return out_x, out_u

    def _members_rollout(self, states: Tensor, index: list[int], uniforms: Tensor) -> tuple[Tensor, Tensor]:
        """All robots of a table set in one rollout (``index``: each robot's member): the dynamics stepped once for
        all, each member used drawing its robots' rows (:class:`~cuniform_torch.policies.table_set.MemberRows`)."""
        b, k, t = states.shape[0], self.num_samples, self.horizon
        by_member: dict[int, list[int]] = {}
        for robot, member in enumerate(index):
            by_member.setdefault(member, []).append(robot)
        samples = torch.arange(k, device=states.device)
        rows = [torch.cat([robot * k + samples for robot in robots]) for robots in by_member.values()]
        member_of = self.capabilities.member
        assert member_of is not None and self._dispatch is not None and self._dispatch_plan is not None
        dispatch = self._dispatch.assign([member_of(m) for m in by_member], rows)
        flat = uniforms.transpose(0, 1).reshape(t, b * k)  # [T, B*K] robot-major
        x, u = self._dispatch_plan.run(self.system, dispatch, _start_rows(states, k), b * k, t, None, flat)
        return x.view(b, k, t + 1, -1), u.view(b, k, t, -1)

    def rollout(self, start: Tensor, num_samples: int, generator: torch.Generator) -> tuple[Tensor, Tensor]:
        """``num_samples`` rollouts of ``horizon`` steps from a checked ``start [d]`` (finite, of the proposal's
        dtype on its device): ``[N, T+1, d]``, ``[N, T, q]``."""
        return self.plan.run(self.system, self.policy, start, num_samples, self.horizon, generator)

    def update(self, result: MPPIResult) -> None:
        """Nothing to warm-start: every command rolls out afresh."""

    def reset(self, robots: Tensor | None = None) -> None:
        """The start of an episode: the policy's start check warns afresh and counts anew
        (its ``new_episode``, read once)."""
        if self._episode is not None:
            self._episode()


# ------------------------------------------------------------------------------------------ composite

class CompositeProposal(OneRobotCall):
    """CU-MPPI's two stages: ``first`` plans (C-Uniform MPPI, with its own streams, so that it can be planned alone
    and repeat), each robot's lowest-cost trajectory becomes the nominal of ``local`` (a Gaussian or log-normal
    proposal), whose K proposals are this proposal's. The local nominal is re-seeded every command, so there is no
    warm start."""

    def __init__(self, first: Planner, local: GaussianProposal):
        self.first, self.local = first, local
        self.extra_streams = first.streams
        """the first stage's streams, drawn within a command too (a CUDA graph registers them)"""
        self.system, self.num_samples, self.horizon = local.system, local.num_samples, local.horizon
        self.num_robots, self.device, self.dtype = local.num_robots, local.device, local.dtype

    def propose_batch(self, states: Tensor, streams: RobotStreams) -> tuple[Tensor, Tensor]:
        self.local.seed(self.first._best_actions(states))  # [B, T, q], no host sync
        return self.local.propose_batch(states, streams)

    def update(self, result: MPPIResult) -> None:
        """Nothing to warm-start: the next command seeds the local pass afresh."""

    def reset(self, robots: Tensor | None = None) -> None:
        self.first.reset(robots)
        self.local.reset(robots)

    def close(self) -> None:
        if isinstance(self.first, Closeable):
            self.first.close()


class PipelinedProposal(OneRobotCall):
    """CU-MPPI in one pass (``CUMPPI(..., pipelined=True)``): each command proposes the first stage's C-Uniform
    rollouts (``first``, K1 per robot, from its own ``first_streams``) and the local Gaussian (or log-normal)
    rollouts (``local``, K2 per robot) around the best C-Uniform sequence of the *previous* command, shifted one step,
    side by side: ``[B, K1 + K2, ...]``, rolled out and costed together, so nothing waits on a first-stage plan. The
    core weighs all K1 + K2 (a mixture proposal); :meth:`update` takes each robot's lowest-cost C-Uniform sequence
    of this command as the next command's local nominal. The first command's local rollouts are around zero."""

    def __init__(self, first: Proposal, first_streams: RobotStreams, local: GaussianProposal):
        self.first, self.first_streams, self.local = first, first_streams, local
        self.extra_streams = first_streams
        """the first stage's streams, drawn within a command too (a CUDA graph registers them)"""
        self.system, self.horizon, self.num_robots = local.system, local.horizon, local.num_robots
        self.num_samples = first.num_samples + local.num_samples
        self.device, self.dtype = local.device, local.dtype

    def propose_batch(self, states: Tensor, streams: RobotStreams) -> tuple[Tensor, Tensor]:
        cu_states, cu_actions = self.first.propose_batch(states, self.first_streams)  # [B, K1, ...]
        local_states, local_actions = self.local.propose_batch(states, streams)  # [B, K2, ...]
        return torch.cat((cu_states, local_states), dim=1), torch.cat((cu_actions, local_actions), dim=1)

    def update(self, result: MPPIResult) -> None:
        """The next local nominal: each robot's lowest-cost C-Uniform sequence, shifted one step (last repeated)."""
        k1 = self.first.num_samples
        costs, actions = result.costs, result.actions
        if costs.ndim == 1:  # one robot's result
            costs, actions = costs.unsqueeze(0), actions.unsqueeze(0)
        best = torch.argmin(costs[:, :k1], dim=1)  # [B]
        index = best.view(-1, 1, 1, 1).expand(-1, 1, *actions.shape[2:])
        seq = actions[:, :k1].gather(1, index)[:, 0]  # [B, T, q]
        self.local.seed(torch.cat((seq[:, 1:], seq[:, -1:]), dim=1))

    def reset(self, robots: Tensor | None = None) -> None:
        self.first.reset(robots)
        self.local.reset(robots)
