"""Batched rollouts through a system: one batched step per time step, no Python loop over samples.

Shapes: N samples, T horizon, d state dimensions, q action dimensions, A actions.

* :func:`rollout` runs a discrete :class:`Policy` (a table or an MLP: ``actions [A, q]`` and
  ``action_probs(x, t) -> [N, A]``) in closed loop: each step's actions are drawn for each state. A policy
  that also has :class:`ActionSampler`'s ``sample(x, t, generator)`` (the table's alias sampler) draws through
  it; any other draws by categorical sampling of ``action_probs``. An :class:`ActionSampler` alone (a noise
  law of :mod:`cuniform_torch.sampling.noise`) drives it too, one ``sample`` per step.
* :func:`rollout_actions` runs given open-loop action sequences ``[N, T, q]`` (what the Gaussian and log-normal
  proposals of :mod:`cuniform_torch.controllers.proposals` draw).

What :func:`rollout` reads from a policy is declared once, in :mod:`cuniform_torch.sampling.contract`: the
:class:`Policy` protocol (required members) and :class:`PolicyCapabilities` (every optional one, read once when a
:class:`RolloutPlan` is made: ``horizon``, ``device``, ``dtype``, ``start_relative``, ``draw``, ``watch_start``,
``for_start``, ``fused_rollout``); a rollout only reads the plan.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, cast

import torch
from torch import Tensor

from cuniform_torch.common.frames import se2_to_world
from cuniform_torch.common.tensors import check_generator, check_states, same_device
from cuniform_torch.sampling import kernels as rollout_kernels
from cuniform_torch.sampling.contract import ActionSampler, Policy, PolicyCapabilities, PolicyTraits
from cuniform_torch.sampling.draws import inverse_cdf_pick
from cuniform_torch.sampling.start_watch import OWN_ROBOT, StartMismatchWarning, StartWatch
from cuniform_torch.systems import System, check_dynamics

__all__ = ["Policy", "ActionSampler", "PolicyTraits", "PolicyCapabilities", "RolloutPlan", "StartMismatchWarning",
           "StartWatch", "rollout", "rollout_actions", "check_states", "check_generator", "same_device", "OWN_ROBOT"]


def _check_args(system: System, x0: Tensor, num_samples: int, horizon: int) -> int:
    d = len(system.periodic)
    for name, value, least in (("num_samples", num_samples, 1), ("horizon", horizon, 0)):
        if isinstance(value, bool) or not isinstance(value, int) or value < least:
            raise ValueError(f"{name} must be an integer >= {least}, got {value!r}")
    if not isinstance(x0, torch.Tensor) or not x0.is_floating_point():
        raise ValueError(f"x0 must be a floating-point tensor, got {getattr(x0, 'dtype', type(x0).__name__)}")
    if x0.shape != (d,) and x0.shape != (num_samples, d):
        raise ValueError(f"x0 must have shape [{d}] or [{num_samples}, {d}], got {list(x0.shape)}")
    return d


def _step(system: System, x: Tensor, u: Tensor, n: int, d: int) -> Tensor:
    """``system.step`` with its output shape checked: ``[n, d]``."""
    x = system.step(x, u)
    if x.shape != (n, d):
        raise ValueError(f"{getattr(system, 'name', type(system).__name__)}.step returned shape {list(x.shape)} "
                         f"for {n} states of dimension {d}; expected [{n}, {d}]")
    return x


def open_loop(system: System, start: Tensor, actions: Tensor) -> Tensor:
    """The kernel of :func:`rollout_actions`, for checked input: ``start [d]`` (or ``[N, d]``), ``actions [N, T, q]``
    -> ``states [N, T+1, d]``. No host sync."""
    n, horizon = actions.shape[0], actions.shape[1]
    d = start.shape[-1]
    x = start.expand(n, d) if start.ndim == 1 else start  # [N, d]
    scan = _own_scan(system)
    if scan is not None:  # the whole horizon in a dozen ops: no per-step launches on a GPU, fewer passes on a CPU
        return scan(x, actions)
    column_major_ok = steps_column_major(system)
    if column_major_ok:
        x = x.T.contiguous().T  # column-major [N, d]: every column a step reads is contiguous (faster)
    states = [x]
    for t in range(horizon):
        x = _plain_step(system, x, actions[:, t], n, d, column_major_ok)
        states.append(x)
    return torch.stack(states, dim=1)  # [N, T+1, d]


def rollout_actions(system: System, x0: Tensor, actions: Tensor) -> Tensor:
    """The states that open-loop ``actions [N, T, q]`` drive from ``x0 [d]`` (or ``[N, d]``): ``[N, T+1, d]``.

    ``x0`` and ``actions`` must share dtype and device; no gradient flows (both are detached); ValueError on a
    non-finite ``x0``.
    """
    if not isinstance(actions, Tensor) or actions.ndim != 3 or not actions.is_floating_point():
        raise ValueError(f"actions must be a floating-point [N, T, q] tensor, got "
                         f"{list(actions.shape) if isinstance(actions, Tensor) else type(actions).__name__}")
    _check_args(system, x0, actions.shape[0], actions.shape[1])
    if actions.dtype != x0.dtype or not same_device(actions.device, x0.device):
        raise ValueError(f"actions are {actions.dtype} on {actions.device} but x0 is {x0.dtype} on {x0.device}")
    check_dynamics(system, x0.dtype, x0.device)  # a user system's step, probed once per dtype and device
    if not bool(torch.isfinite(x0).all()):
        raise ValueError("x0 contains NaN or infinite values")
    return open_loop(system, x0.detach(), actions.detach())


def _step_declares(system: System, flag: str) -> bool:
    """Whether the class that defines the ``step`` in use says ``flag = True`` itself (a subclass that overrides
    ``step`` without saying so gets the plain treatment)."""
    for klass in type(system).__mro__:
        if "step" in vars(klass):
            return vars(klass).get(flag, False) is True
    return False


def _own_scan(system: System) -> Callable[[Tensor, Tensor], Tensor] | None:
    """The system's ``scan(start [N, d], actions [N, T, q]) -> [N, T+1, d]`` (the open-loop states in closed form)
    when the class that defines the ``step`` in use defines it too (a subclass that changes ``step`` keeps the
    step loop), else None."""
    for klass in type(system).__mro__:
        if "step" in vars(klass):
            return getattr(system, "scan") if callable(vars(klass).get("scan")) else None
    return None


def _steps_into(system: System) -> bool:
    """Whether ``system.step`` takes ``out=`` (its class says ``step_out = True``)."""
    return _step_declares(system, "step_out")


def steps_column_major(system: System) -> bool:
    """Whether ``system.step`` may get column-major ``[N, d]`` states (its class says ``column_major_ok = True``,
    as the built-in models do: each column contiguous makes their steps cheaper). Any other system's ``step`` gets
    ordinary contiguous ``[N, d]`` tensors."""
    return _step_declares(system, "column_major_ok") or _steps_into(system)


def _plain_step(system: System, x: Tensor, u: Tensor, n: int, d: int, column_major_ok: bool) -> Tensor:
    """:func:`_step` with ``x`` made contiguous for a system that did not opt in to column-major states."""
    return _step(system, x if column_major_ok else x.contiguous(), u, n, d)


@dataclass(frozen=True)
class RolloutPlan:
    """How :func:`rollout` drives one policy, settled once (a proposal keeps it and skips the per-call checks): the
    policy's :class:`PolicyCapabilities` and the system's step flags. A rollout reads only this record."""

    capabilities: PolicyCapabilities
    """what the policy declares, read once"""
    relative: bool
    """roll out from the origin and move the states to the start pose (``start_relative`` on an SE(2)-invariant
    system)"""
    step_out: bool = False
    """the system's ``step`` takes ``out=`` (its class says ``step_out = True``): each step writes a row of one
    preallocated ``[T+1, d, N]`` buffer, which the results are read from (no stack of T+1 states)"""
    column_major_ok: bool = False
    """the system's ``step`` may get column-major states (:func:`steps_column_major`); else contiguous ones"""
    _members: dict[int, tuple[object, PolicyCapabilities]] = field(default_factory=dict, compare=False, repr=False)
    """the capabilities of each policy ``for_start`` has returned, read the first time it is returned (keyed by
    its id; the policy is kept so that the id is not reused)"""

    @property
    def traits(self) -> PolicyTraits:
        return self.capabilities.traits

    @property
    def sampler(self) -> bool:
        """draw through ``policy.sample`` (an :class:`ActionSampler`); else categorical draws of ``action_probs``"""
        return self.capabilities.sampler

    @property
    def draws(self) -> bool:
        """the policy has ``draw(x, t, r)``: it draws with given uniforms"""
        return self.capabilities.draw is not None

    @property
    def watch_start(self) -> Callable[[Tensor, bool], Callable[[], None] | None] | None:
        return self.capabilities.watch_start

    @property
    def for_start(self) -> Callable[[Tensor], Any] | None:
        return self.capabilities.for_start

    @property
    def fused_rollout(self) -> Callable[..., Any] | None:
        return self.capabilities.fused_rollout

    @classmethod
    def of(cls, system: System, policy: object, capabilities: PolicyCapabilities | None = None) -> RolloutPlan:
        """The plan for ``policy`` on ``system`` (``capabilities``: the policy's, when already read); ValueError when
        it is neither a Policy nor an ActionSampler."""
        caps = capabilities if capabilities is not None else PolicyCapabilities.of(policy)
        caps.check(policy)
        return cls(capabilities=caps, relative=caps.traits.start_relative and bool(system.se2_invariant),
                   step_out=_steps_into(system), column_major_ok=steps_column_major(system))

    def member_capabilities(self, member: object) -> PolicyCapabilities:
        """The capabilities of a policy ``for_start`` returned: read the first time, then kept."""
        known = self._members.get(id(member))
        if known is None or known[0] is not member:
            known = self._members[id(member)] = (member, PolicyCapabilities.of(member))
        return known[1]

    def check(self, x0: Tensor, horizon: int) -> None:
        """ValueError unless the policy serves ``horizon`` steps from ``x0`` (its device, finite)."""
        traits = self.traits
        if traits.horizon is not None and horizon > traits.horizon:
            raise ValueError(f"horizon {horizon} is longer than the policy's table ({traits.horizon} steps)")
        if traits.device is not None and not same_device(traits.device, x0.device):
            raise ValueError(f"x0 is on {x0.device} but the policy is on {traits.device}")
        if not bool(torch.isfinite(x0).all()):
            raise ValueError("x0 contains NaN or infinite values")

    def _steps(self, system: System, policy: Policy | ActionSampler, x0: Tensor, start: Tensor, num_samples: int,
               horizon: int, generator: torch.Generator | None,
               uniforms: Tensor | None = None,
               caps: PolicyCapabilities | None = None) -> tuple[Tensor | None, list[Tensor], Tensor]:
        """The step-by-step loop of :meth:`run`: the time-major buffer ``[T+1, d, N]`` (None without one), the
        column-major states ``[N, d]`` of each step, and the actions ``[N, T, q]``."""
        d = x0.shape[-1]
        # column-major [N, d] states: every column a policy or a step reads is contiguous (faster). With step_out all
        # T+1 of them are rows of one time-major buffer, each step writing the next in place
        buffer = x0.new_empty((horizon + 1, d, num_samples)) if self.step_out else None  # [T+1, d, N]
        x = buffer[0].T if buffer is not None else x0.new_empty((d, num_samples)).T  # [N, d], column-major
        if self.relative:  # in the start pose's frame the start is (0, 0, 0, *rest): speeds etc. are unchanged
            x[:, :3] = 0
            x[:, 3:] = start[:, 3:]
        else:
            x.copy_(start)
        caps = self.capabilities if caps is None else caps
        draw = caps.draw
        by_probs = not caps.sampler or (uniforms is not None and draw is None)
        actions = cast(Tensor, cast(Policy, policy).actions.to(dtype=x0.dtype) if by_probs else None)  # [A, q]
        states, taken = [x], []
        for t in range(horizon):
            if uniforms is not None and draw is not None:
                u = draw(x, t, uniforms[t])  # [N, q]
            elif uniforms is not None:
                u = inverse_cdf_pick(self._probs(policy, x, t, num_samples, actions).cumsum(dim=1), actions,
                                     uniforms[t])  # [N, q]
            elif caps.sampler:
                u = cast(ActionSampler, policy).sample(x, t, generator)  # [N, q]
            else:
                probs = self._probs(policy, x, t, num_samples, actions)
                u = actions[torch.multinomial(probs, 1, generator=generator).squeeze(1)]  # [N, q]
            if buffer is not None and u.dtype == x.dtype and u.device == x.device:
                x = cast(Any, system).step(x, u, out=buffer[t + 1].T)  # [N, d] into the buffer (step_out: takes out=)
            else:
                x = _plain_step(system, x, u, num_samples, d, self.column_major_ok)
                if buffer is not None and x.dtype == buffer.dtype:
                    buffer[t + 1].T.copy_(x)
                else:  # actions of another dtype promote the states: they are stacked from the list instead
                    buffer = None
            states.append(x)
            taken.append(u)
        if taken:
            # stacked time-major, then one transposing copy: cheaper on a CPU than stacking [N, q] along dim 1
            actions_t = torch.stack(taken).transpose(0, 1).contiguous()  # [N, T, q]
        else:
            q = (caps.action_dim if caps.action_dim is not None
                 else system.action_set(dtype=x0.dtype, device=x0.device).shape[1])
            actions_t = x0.new_zeros((num_samples, 0, q))
        return buffer, states, actions_t

    @staticmethod
    def _probs(policy: object, x: Tensor, t: int, num_samples: int, actions: Tensor) -> Tensor:
        """``policy.action_probs(x, t)`` checked to be ``[N, A]``."""
        probs = cast(Policy, policy).action_probs(x, t)  # [N, A]
        if not isinstance(probs, Tensor) or probs.shape != (num_samples, actions.shape[0]):
            raise ValueError(f"{type(policy).__name__}.action_probs returned "
                             f"{list(probs.shape) if isinstance(probs, Tensor) else type(probs).__name__} at "
                             f"step {t}; expected [{num_samples}, {actions.shape[0]}] probabilities (states x "
                             f"actions)")
        return probs

    def run(self, system: System, policy: Policy | ActionSampler, x0: Tensor, num_samples: int, horizon: int,
            generator: torch.Generator | None, uniforms: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """The rollout itself, for checked input (``x0 [d]`` or ``[N, d]``, detached, finite, on the policy's
        device; a generator on it): ``states [N, T+1, d]``, ``actions [N, T, q]``. With ``uniforms [T, N]`` in
        ``[0, 1)`` (the policy's dtype and device), step ``t`` draws with ``uniforms[t]`` (one per sample: what a
        batched controller draws up front, per robot) and ``generator`` is not used."""
        caps = self.capabilities
        if caps.for_start is not None:  # a table set: the table nearest to this start, and its start check
            policy = caps.for_start(x0)
            caps = self.member_capabilities(policy)  # a member's hooks are its own, read the first time it serves
        watch, fused = caps.watch_start, caps.fused_rollout
        report = watch(x0, self.relative) if watch is not None else None
        d = x0.shape[-1]
        start = x0.unsqueeze(0).expand(num_samples, d) if x0.ndim == 1 else x0  # [N, d]
        own = (fused(system, x0, num_samples, horizon, generator, uniforms) if self.relative and fused is not None
               else None)
        if own is not None:
            buffer, actions_t = own  # [T+1, d, N] start-frame states, [N, T, q]
            states: list[Tensor] = []
        else:
            buffer, states, actions_t = self._steps(system, policy, x0, start, num_samples, horizon, generator,
                                                    uniforms, caps)
        # the origin pose needs no change of frame (a host read to know it: only on a CPU, where it is free, and not
        # for a controller's rollouts, given their uniforms: a command reads nothing back)
        if self.relative and (uniforms is not None or x0.ndim == 2 or x0.device.type != "cpu"
                              or bool(x0[:3].any())):
            # the column-major states time-major ([T+1, d, N], contiguous rows: the buffer, else one stack); the
            # frame change reads that once and writes the [N, T+1, d] result once (a compiled loop on a CPU, else
            # torch ops). One arithmetic for one start [d] and per-sample starts [N, d]: a robot's states are the
            # same bits alone and in a batch (the kernel computes each pose's cos and sin alone; the torch path
            # takes the [N, 1, d] starts either way)
            local = buffer if buffer is not None else torch.stack([s.T for s in states])
            if rollout_kernels.usable(local):
                if buffer is not None:  # world states time-major too: [N, T+1, d] a view of [T+1, d, N]
                    states_t = rollout_kernels.to_world_time_major(local, x0).permute(2, 0, 1)
                else:
                    states_t = rollout_kernels.to_world(local, x0)
            else:
                states_t = se2_to_world(local.permute(2, 0, 1), start.unsqueeze(1))
        elif buffer is not None:
            states_t = buffer.permute(2, 0, 1)  # [N, T+1, d], a view of the time-major buffer
        else:
            states_t = torch.stack(states, dim=1)  # [N, T+1, d]
        if report is not None:
            report()
        return states_t, actions_t


def rollout(
    system: System,
    policy: Policy | ActionSampler,
    x0: Tensor,
    num_samples: int,
    horizon: int,
    generator: torch.Generator | None = None,
) -> tuple[Tensor, Tensor]:
    """Sample ``num_samples`` trajectories of ``horizon`` steps from ``x0 [d]`` (or ``[N, d]``).

    Returns ``states [N, T+1, d]`` (start included) and ``actions [N, T, q]``, in the dtype and on the device
    of ``x0`` (on a system whose ``step`` takes ``out=``, the states are a view of time-major ``[T+1, d, N]``
    storage, not contiguous: elementwise costs over them read whole rows); pass a seeded ``generator`` on that device for reproducible samples. No gradient flows through a
    rollout: an ``x0`` that requires grad is detached. A policy's ``action_probs`` must return ``[N, A]``.
    """
    _check_args(system, x0, num_samples, horizon)
    check_generator(generator, x0.device)
    check_dynamics(system, x0.dtype, x0.device)  # a user system's step, probed once per dtype and device
    x0 = x0.detach()
    plan = RolloutPlan.of(system, policy)
    plan.check(x0, horizon)
    return plan.run(system, policy, x0, num_samples, horizon, generator)
