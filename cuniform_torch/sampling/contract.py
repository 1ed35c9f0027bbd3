"""The policy contract of the rollout and the controllers, declared in one place.

Shapes: N states, d state dimensions, q action dimensions, A actions, S members of a table set.

* :class:`Policy` (runtime-checkable): the required members, ``actions [A, q]`` and
  ``action_probs(x [N, d], t) -> [N, A]``; or :class:`ActionSampler`'s ``sample(x, t, generator) -> [N, q]``.
* :class:`PolicyCapabilities`: every optional member that :func:`~cuniform_torch.sampling.rollout.rollout`, a
  :class:`~cuniform_torch.controllers.proposals.PolicyProposal` or a proposal bank uses, read *once*, by
  :meth:`PolicyCapabilities.of`, when the rollout plan or the proposal is made; a command only reads the record
  (no ``getattr`` of the policy per call). A policy declares a capability by having the member; a member it
  lacks (or that is None) takes the default.

Write your own policy as a class with ``actions`` and ``action_probs`` (and a ``system`` for a controller); add
the optional members below that it can answer.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import torch
from torch import Tensor

__all__ = ["Policy", "ActionSampler", "PolicyTraits", "PolicyCapabilities"]


@runtime_checkable
class Policy(Protocol):
    """A discrete action set and per-state action probabilities: what :func:`~cuniform_torch.sampling.rollout.rollout`
    and :class:`~cuniform_torch.controllers.mppi.CUniformMPPI` roll out.

    The optional members a rollout or a controller uses are listed, with their shapes, in
    :class:`PolicyCapabilities`.
    """

    actions: Tensor
    """``[A, q]``"""

    def action_probs(self, x: Tensor, t: int) -> Tensor:
        """``x [N, d]`` at step ``t`` -> ``[N, A]`` probabilities (rows sum to 1)."""
        ...


@runtime_checkable
class ActionSampler(Protocol):
    """Anything that draws actions for a batch of states (a table's alias sampler, a noise law)."""

    def sample(self, x: Tensor, t: int, generator: torch.Generator | None) -> Tensor:
        """``x [N, d]`` at step ``t`` -> actions ``[N, q]``."""
        ...


def _member(policy: object, name: str) -> Any:
    """``policy.name``, or None where it has none (the one place the contract is read by name)."""
    return getattr(policy, name, None)


def _hook(policy: object, name: str) -> Callable[..., Any] | None:
    """``policy.name`` when it is callable, else None."""
    value = _member(policy, name)
    return value if callable(value) else None


@dataclass(frozen=True)
class PolicyTraits:
    """The descriptive optional attributes of a policy (or sampler), with their defaults."""

    horizon: int | None = None
    """the longest rollout the policy serves (a table's T); None: any"""
    device: torch.device | None = None
    """the policy's device: the start must be there; None: not checked"""
    dtype: torch.dtype | None = None
    """the policy's dtype (what a controller around it runs in; None: float32). A policy checks the states it is
    given itself: a uniform policy serves any dtype"""
    start_relative: bool = False
    """True: the policy was built at the origin of an SE(2)-invariant system (tables, MLPs), its probabilities are
    in the start pose's frame"""

    @classmethod
    def of(cls, policy: object) -> PolicyTraits:
        """The traits ``policy`` declares (an attribute it lacks, or that is None, takes the default)."""
        device, dtype = _member(policy, "device"), _member(policy, "dtype")
        return cls(horizon=_member(policy, "horizon"),
                   device=None if device is None else torch.device(device),
                   dtype=dtype if isinstance(dtype, torch.dtype) else None,
                   start_relative=bool(_member(policy, "start_relative") or False))


@dataclass(frozen=True)
class PolicyCapabilities:
    """What a policy can do beyond :class:`Policy`, settled once (:meth:`of`) and then only read.

    | capability | member the policy declares | who reads it |
    | --- | --- | --- |
    | ``sampler`` | ``sample(x [N, d], t, generator) -> [N, q]`` | the rollout (draws through it) |
    | ``draw`` | ``draw(x [N, d], t, r [N]) -> [N, q]`` (given uniforms in [0, 1)) | the rollout, in a command |
    | ``traits`` | ``horizon``, ``device``, ``dtype``, ``start_relative`` | the rollout's checks, the proposal |
    | ``watch_start`` | ``watch_start(x0, relative) -> report or None`` | the rollout (the start check) |
    | ``for_start`` | ``for_start(x0 [d]) -> policy`` (the policy for that start) | the rollout |
    | ``fused_rollout`` | ``fused_rollout(system, x0, N, T, generator, uniforms)`` | the rollout |
    | ``new_episode`` | ``new_episode()`` (the start check warns afresh) | the proposal's construction and reset |
    | ``nearest``, ``member``, ``member_starts`` | a table set's ``nearest``, ``member(i)``, ``starts [S, d]`` | the proposal, the bank |
    | ``system`` | ``system`` | the proposal (the dynamics it rolls out) |
    """

    sampler: bool
    """``sample(x, t, generator) -> [N, q]``: an :class:`ActionSampler`; the rollout draws through it"""
    probs: bool
    """``actions [A, q]`` and ``action_probs(x, t) -> [N, A]``: a :class:`Policy`"""
    traits: PolicyTraits
    action_dim: int | None = None
    """q, from ``actions [A, q]`` (None without actions)"""
    system: Any = None
    """the policy's system (None: none; a controller needs one)"""
    draw: Callable[[Tensor, int, Tensor], Tensor] | None = None
    """``draw(x [N, d], t, r [N]) -> [N, q]``: actions drawn with given uniforms (else, given uniforms, the rollout
    draws from ``action_probs`` by inverse CDF)"""
    watch_start: Callable[[Tensor, bool], Callable[[], None] | None] | None = None
    """``watch_start(x0, relative)`` before a rollout from ``x0 [d]`` (or ``[N, d]``): None, or the call that counts
    (and warns) after it (a :class:`~cuniform_torch.sampling.start_watch.StartWatch`'s ``begin``)"""
    for_start: Callable[[Tensor], Any] | None = None
    """``for_start(x0 [d]) -> policy``: the policy that serves rollouts from ``x0`` (a table set's nearest member,
    a start-conditioned MLP set to that start); its own capabilities are read once per member"""
    fused_rollout: Callable[..., Any] | None = None
    """``fused_rollout(system, x0 [d], N, T, generator, uniforms) -> (states [T+1, d, N], actions [N, T, q]) or
    None``: the policy rolls itself out in the start frame (None: the step loop)"""
    new_episode: Callable[[], None] | None = None
    """``new_episode()``: the start check warns afresh and counts anew (a controller's construction and reset)"""
    nearest: Callable[[Tensor], tuple[Tensor, Tensor]] | None = None
    """a table set's ``nearest(x0 [N, d]) -> (member [N], distance [N])``: robots grouped by member"""
    member: Callable[[int], Any] | None = None
    """a table set's ``member(i)``"""
    member_starts: Tensor | None = None
    """a table set's member starts ``[S, d]``"""

    @property
    def table_set(self) -> bool:
        """A set of policies chosen by the start (``nearest``, ``member``, ``for_start``)."""
        return self.nearest is not None and self.member is not None and self.for_start is not None

    @classmethod
    def of(cls, policy: object) -> PolicyCapabilities:
        """The capabilities ``policy`` declares, read now (each member by name, once)."""
        actions = _member(policy, "actions")
        probs = actions is not None and _hook(policy, "action_probs") is not None
        starts = _member(policy, "starts")
        nearest, member = _hook(policy, "nearest"), _hook(policy, "member")
        return cls(sampler=_hook(policy, "sample") is not None, probs=probs, traits=PolicyTraits.of(policy),
                   action_dim=int(actions.shape[-1]) if isinstance(actions, Tensor) and actions.ndim == 2 else None,
                   system=_member(policy, "system"), draw=_hook(policy, "draw"),
                   watch_start=_hook(policy, "watch_start"), for_start=_hook(policy, "for_start"),
                   fused_rollout=_hook(policy, "fused_rollout"), new_episode=_hook(policy, "new_episode"),
                   nearest=nearest, member=member,
                   member_starts=starts if isinstance(starts, Tensor) and nearest is not None and member is not None
                   else None)

    def check(self, policy: object) -> None:
        """ValueError unless ``policy`` is a :class:`Policy` or an :class:`ActionSampler`."""
        if not (self.sampler or self.probs):
            raise ValueError(f"{type(policy).__name__} is neither a Policy (actions [A, q], action_probs(x, t)) nor "
                             f"an ActionSampler (sample(x, t, generator))")
