"""Proposals: the plug-in of the MPPI core (:class:`~cuniform_torch.controllers.mppi.MPPICore`).

Shapes: K proposals, T horizon, d state dimensions, q action dimensions, M rollouts in a bank.

A proposal draws the K trajectories a command weighs. Per command the core calls

* ``states [K, T+1, d], actions [K, T, q] = proposal.propose(state [d], generator)``, then costs and weights
  them into an :class:`~cuniform_torch.controllers.result.MPPIResult`;
* ``proposal.update(result)`` (only from ``command``; ``plan`` leaves the proposal as it was): the warm start;

and ``proposal.reset()`` at the start of an episode. :class:`Proposal` declares that, and the attributes the core
reads (``system``, ``num_samples`` K, ``horizon`` T, ``device``, ``dtype``). Any object with them drops into the
core; the ones here:

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

from typing import Protocol, runtime_checkable

import torch
from torch import Tensor

from cuniform_torch.controllers.checks import _check_dtype, check_positive_int
from cuniform_torch.controllers.result import MPPIResult
from cuniform_torch.policies.checkpoint import load_policy
from cuniform_torch.sampling.noise import GaussianSampler, NormalLogNormalSampler
from cuniform_torch.sampling.rollout import Policy, PolicyTraits, RolloutPlan, open_loop, same_device
from cuniform_torch.sampling.start_watch import new_episode
from cuniform_torch.systems import System

__all__ = ["Proposal", "GaussianProposal", "NormalLogNormalProposal", "PolicyProposal", "CompositeProposal",
           "PROPOSAL_MEMBERS"]


@runtime_checkable
class Proposal(Protocol):
    """What the MPPI core needs from a proposal: K trajectories per command, and the hooks around a command."""

    system: System
    """the dynamics the trajectories follow (the core reads its state dimension and action set)"""
    num_samples: int
    """K: trajectories per :meth:`propose`"""
    horizon: int
    """T: steps per trajectory"""
    device: torch.device
    """where the trajectories are (the state handed to :meth:`propose` is there too)"""
    dtype: torch.dtype
    """their floating-point dtype (the state's too)"""

    def propose(self, state: Tensor, generator: torch.Generator) -> tuple[Tensor, Tensor]:
        """``state [d]`` (checked: finite, of ``dtype`` on ``device``) -> ``states [K, T+1, d]`` (``states[:, 0]`` the
        state) and ``actions [K, T, q]``. Draw random numbers from ``generator`` only (seeded controllers repeat)."""
        ...

    def update(self, result: MPPIResult) -> None:
        """After a command: warm-start the next one from ``result`` (or do nothing)."""
        ...

    def reset(self) -> None:
        """The start of an episode: forget any warm start."""
        ...


PROPOSAL_MEMBERS = ("system", "num_samples", "horizon", "device", "dtype", "propose", "update", "reset")
"""the members of :class:`Proposal`, for error messages"""


@runtime_checkable
class Closeable(Protocol):
    """A proposal that holds a resource (a worker thread) until ``close()``."""

    def close(self) -> None:
        ...


class Planner(Protocol):
    """A controller's planning step (what :class:`CompositeProposal` seeds from): ``plan(state) -> MPPIResult``."""

    def plan(self, state: Tensor) -> MPPIResult:
        ...

    def reset(self) -> None:
        ...



# ------------------------------------------------------------------------------------------ Gaussian, log-normal

class GaussianProposal:
    """MPPI's proposal: ``actions = clip(nominal + eps)``, ``eps ~ N(0, noise_std^2)`` (scalar or ``[q]`` std),
    rolled out open-loop from the state; the warm start shifts the command's weighted sequence one step.

    ``nominal [T, q]`` starts at zero (``reset()``); set it to seed the next proposals (CU-MPPI does).
    """

    def __init__(self, system: System, num_samples: int, horizon: int, noise_std: float | Tensor = 0.3,
                 device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32):
        self.system = system
        self.num_samples = check_positive_int("num_samples", num_samples)
        self.horizon = check_positive_int("horizon", horizon)
        self.device = torch.device(device)
        self.dtype = _check_dtype(dtype)
        actions = system.action_set(dtype=dtype, device=self.device)  # [A, q]
        self.low, self.high = actions.min(dim=0).values, actions.max(dim=0).values  # [q] action bounds
        self.noise_std = noise_std
        self.reset()
        self.law = self._law(noise_std)  # the noise law, built (and its std checked) once

    def _law(self, noise_std: float | Tensor) -> GaussianSampler:
        return GaussianSampler(self._nominal, noise_std, self.low, self.high)

    @property
    def nominal(self) -> Tensor:
        """``[T, q]`` the sequence the next proposals are drawn around"""
        return self._nominal

    @nominal.setter
    def nominal(self, value: Tensor) -> None:
        expected = (self.horizon, self.low.shape[0])
        if not isinstance(value, Tensor) or value.shape != expected or value.dtype != self.dtype \
                or not same_device(value.device, self.device):
            raise ValueError(f"nominal must be a {list(expected)} tensor of {self.dtype} on {self.device}, got "
                             + (f"{list(value.shape)} of {value.dtype} on {value.device}" if isinstance(value, Tensor)
                                else type(value).__name__))
        self._nominal = value.detach()

    def propose(self, state: Tensor, generator: torch.Generator) -> tuple[Tensor, Tensor]:
        actions = self.law.perturb(self._nominal, self.num_samples, generator)  # [K, T, q]
        return open_loop(self.system, state, actions), actions  # [K, T+1, d], [K, T, q]

    def update(self, result: MPPIResult) -> None:
        """Warm start: the weighted sequence shifted one step, its last action repeated."""
        self._nominal = torch.cat((result.nominal[1:], result.nominal[-1:]))  # [T, q]

    def reset(self) -> None:
        """Zero nominal (the start of an episode)."""
        self._nominal = torch.zeros((self.horizon, self.low.shape[0]), dtype=self.dtype, device=self.device)


class NormalLogNormalProposal(GaussianProposal):
    """log-MPPI's proposal: :class:`GaussianProposal` with normal x log-normal noise (Mohamed et al.); the
    log-normal factor has mean ``lognormal_mean`` and variance ``lognormal_var``
    (:class:`~cuniform_torch.sampling.noise.NormalLogNormalSampler`)."""

    def __init__(self, system: System, num_samples: int, horizon: int, noise_std: float | Tensor = 0.3,
                 lognormal_mean: float = 1.0, lognormal_var: float = 1.0, device: torch.device | str = "cpu",
                 dtype: torch.dtype = torch.float32):
        self.lognormal_mean, self.lognormal_var = lognormal_mean, lognormal_var
        super().__init__(system, num_samples, horizon, noise_std, device, dtype)

    def _law(self, noise_std: float | Tensor) -> NormalLogNormalSampler:
        return NormalLogNormalSampler(self._nominal, noise_std, self.low, self.high,
                                      lognormal_mean=self.lognormal_mean, lognormal_var=self.lognormal_var)


# ------------------------------------------------------------------------------------------ policy

def _as_policy(policy: object, device: torch.device | None) -> Policy:
    """A Policy object, or a distilled-policy checkpoint dict (``torch.load(path, weights_only=True)``), loaded by
    :func:`~cuniform_torch.policies.checkpoint.load_policy` (which knows the format)."""
    if isinstance(policy, dict):
        return load_policy(policy, device=device)
    if not isinstance(policy, Policy):
        raise ValueError(f"policy must have actions [A, q] and action_probs(x, t); got {type(policy).__name__}")
    return policy


class PolicyProposal:
    """C-Uniform MPPI's proposal: K rollouts of ``policy`` (a table, an MLP, any
    :class:`~cuniform_torch.sampling.rollout.Policy` with a ``system``, or a checkpoint dict) from the pose. No warm start.

    ``horizon`` defaults to the policy's own (a table's T; required for a policy without one); ``device`` to the
    policy's (else the CPU); the dtype is the policy's (else float32).
    """

    def __init__(self, policy: object, num_samples: int, horizon: int | None = None,
                 device: torch.device | str | None = None):
        traits = PolicyTraits.of(policy) if not isinstance(policy, dict) else PolicyTraits()
        self.device = torch.device(device) if device is not None else (traits.device or torch.device("cpu"))
        self.policy = _as_policy(policy, self.device)
        traits = PolicyTraits.of(self.policy)
        if traits.device is not None and not same_device(traits.device, self.device):
            raise ValueError(f"the policy is on {traits.device} but device={self.device} was asked for")
        self.system = getattr(self.policy, "system", None)
        if self.system is None:
            raise ValueError(f"{type(self.policy).__name__} has no system: a proposal needs the policy's dynamics")
        horizon = horizon if horizon is not None else traits.horizon
        if horizon is None:
            raise ValueError("horizon is required for a policy without a table horizon")
        self.horizon = check_positive_int("horizon", horizon)
        if traits.horizon is not None and self.horizon > traits.horizon:
            raise ValueError(f"horizon {self.horizon} is longer than the policy's table ({traits.horizon} steps)")
        self.num_samples = check_positive_int("num_samples", num_samples)
        self.dtype = traits.dtype or torch.float32
        self.plan = RolloutPlan.of(self.system, self.policy)
        """how the policy is rolled out, settled here: a command runs it without the per-call checks"""
        new_episode(self.policy)  # a controller's first episode: its off-start rollouts warn afresh

    def propose(self, state: Tensor, generator: torch.Generator) -> tuple[Tensor, Tensor]:
        return self.rollout(state, self.num_samples, generator)

    def rollout(self, start: Tensor, num_samples: int, generator: torch.Generator) -> tuple[Tensor, Tensor]:
        """``num_samples`` rollouts of ``horizon`` steps from a checked ``start [d]`` (finite, of the proposal's
        dtype on its device): ``[N, T+1, d]``, ``[N, T, q]``."""
        return self.plan.run(self.system, self.policy, start, num_samples, self.horizon, generator)

    def update(self, result: MPPIResult) -> None:
        """Nothing to warm-start: every command rolls out afresh."""

    def reset(self) -> None:
        """The start of an episode: the policy's start check warns afresh and counts anew
        (:func:`~cuniform_torch.sampling.start_watch.new_episode`)."""
        new_episode(self.policy)


# ------------------------------------------------------------------------------------------ composite

class CompositeProposal:
    """CU-MPPI's two stages: ``first.plan(state)`` (C-Uniform MPPI, with its own generator, so that it can be
    planned alone and repeat), its lowest-cost trajectory becomes the nominal of ``local`` (a Gaussian or
    log-normal proposal), whose K proposals are this proposal's. The local nominal is re-seeded every command,
    so there is no warm start."""

    def __init__(self, first: Planner, local: GaussianProposal):
        self.first, self.local = first, local
        self.system, self.num_samples, self.horizon = local.system, local.num_samples, local.horizon
        self.device, self.dtype = local.device, local.dtype

    def propose(self, state: Tensor, generator: torch.Generator) -> tuple[Tensor, Tensor]:
        seed = self.first.plan(state)
        self.local.nominal = seed.actions.index_select(0, seed.best.reshape(1))[0]  # [T, q], no host sync
        return self.local.propose(state, generator)

    def update(self, result: MPPIResult) -> None:
        """Nothing to warm-start: the next command seeds the local pass afresh."""

    def reset(self) -> None:
        self.first.reset()
        self.local.reset()

    def close(self) -> None:
        if isinstance(self.first, Closeable):
            self.first.close()
