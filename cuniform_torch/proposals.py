"""Proposals: the plug-in of the MPPI core (:class:`~cuniform_torch.mppi.MPPICore`).

Shapes: K proposals, T horizon, d state dimensions, q action dimensions, M rollouts in a bank.

A proposal draws the K trajectories a command weighs. Per command the core calls

* ``states [K, T+1, d], actions [K, T, q] = proposal.propose(state [d], generator)``, then costs and weights
  them into an :class:`~cuniform_torch.mppi.MPPIResult`;
* ``proposal.update(result)`` (only from ``command``; ``plan`` leaves the proposal as it was): the warm start;

and ``proposal.reset()`` at the start of an episode. :class:`Proposal` declares that, and the attributes the core
reads (``system``, ``num_samples`` K, ``horizon`` T, ``device``, ``dtype``). Any object with them drops into the
core; the ones here:

* :class:`GaussianProposal` (MPPI): Gaussian noise around a nominal sequence, clipped to the action bounds; the
  warm start is the command's weighted sequence shifted one step (its last action repeated).
* :class:`NormalLogNormalProposal` (log-MPPI): the same with normal x log-normal noise.
* :class:`PolicyProposal` (C-Uniform MPPI): fresh C-Uniform rollouts of a policy (a table or an MLP) from the
  pose; no warm start.
* :class:`BankProposal` (C-Uniform MPPI with a bank): M rollouts pre-sampled at the origin; each command takes a
  random subset of K of them and moves it to the pose by a rigid transform. Refreshed every ``refresh``
  commands, in the control loop or in a background worker thread (which lives here).
* :class:`CompositeProposal` (CU-MPPI): the lowest-cost trajectory of a first planner (C-Uniform MPPI) becomes
  the nominal of a local Gaussian or log-normal proposal.
"""

from __future__ import annotations

import numbers
import warnings
from concurrent.futures import Future, ThreadPoolExecutor
from typing import TYPE_CHECKING, Protocol, runtime_checkable

import torch
from torch import Tensor

from . import rollout_kernels
from .frames import se2_to_world
from .mlp import load_policy
from .rollout import Policy, PolicyTraits, RolloutPlan, check_generator, open_loop, same_device
from .samplers import GaussianSampler, NormalLogNormalSampler
from .systems import System

if TYPE_CHECKING:  # the result type only annotates; mppi imports this module
    from .mppi import MPPIResult

__all__ = ["Proposal", "GaussianProposal", "NormalLogNormalProposal", "PolicyProposal", "BankProposal",
           "CompositeProposal", "BankRefreshWarning", "PROPOSAL_MEMBERS"]

BANK_THREAD_PREFIX = "cuniform-bank"
"""name prefix of the background bank worker's thread"""


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


class BankRefreshWarning(RuntimeWarning):
    """A background bank refresh of :class:`BankProposal` raised; the controller goes on with its current bank."""


def check_positive_int(name: str, value: object) -> int:
    """``value`` as a positive int (ValueError otherwise; a bool is not an int here)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < 1:
        raise ValueError(f"{name} must be a positive integer, got {value!r}")
    return int(value)


def seeded_generator(seed: int | None, device: torch.device) -> torch.Generator:
    """A ``torch.Generator`` on ``device``: seeded with ``seed``, or from fresh entropy when it is None."""
    generator = torch.Generator(device=device)
    generator.manual_seed(seed) if seed is not None else generator.seed()
    return generator


def _check_dtype(dtype: object) -> torch.dtype:
    if not (isinstance(dtype, torch.dtype) and dtype.is_floating_point):
        raise ValueError(f"dtype must be a floating-point torch.dtype, got {dtype!r}")
    return dtype


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
    (:class:`~cuniform_torch.samplers.NormalLogNormalSampler`)."""

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
    :func:`~cuniform_torch.mlp.load_policy` (which knows the format)."""
    if isinstance(policy, dict):
        return load_policy(policy, device=device)
    if not isinstance(policy, Policy):
        raise ValueError(f"policy must have actions [A, q] and action_probs(x, t); got {type(policy).__name__}")
    return policy


class PolicyProposal:
    """C-Uniform MPPI's proposal: K rollouts of ``policy`` (a table, an MLP, any
    :class:`~cuniform_torch.rollout.Policy` with a ``system``, or a checkpoint dict) from the pose. No warm start.

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

    def propose(self, state: Tensor, generator: torch.Generator) -> tuple[Tensor, Tensor]:
        return self.rollout(state, self.num_samples, generator)

    def rollout(self, start: Tensor, num_samples: int, generator: torch.Generator) -> tuple[Tensor, Tensor]:
        """``num_samples`` rollouts of ``horizon`` steps from a checked ``start [d]`` (finite, of the proposal's
        dtype on its device): ``[N, T+1, d]``, ``[N, T, q]``."""
        return self.plan.run(self.system, self.policy, start, num_samples, self.horizon, generator)

    def update(self, result: MPPIResult) -> None:
        """Nothing to warm-start: every command rolls out afresh."""

    def reset(self) -> None:
        """Nothing to forget."""


# ------------------------------------------------------------------------------------------ bank

class BankProposal:
    """C-Uniform MPPI's bank: ``bank_size`` (M) rollouts of ``source``'s policy pre-sampled at the origin; each
    command proposes a fresh random subset of K = ``source.num_samples`` of them, moved to the pose by a rigid
    transform. SE(2)-invariant systems with the state (x, y, theta) only.

    The initial bank is drawn with ``generator``. ``refresh`` (commands) draws a new bank every that many
    commands (counted by :meth:`update`) from the bank's own stream (seeded by ``seed``); with ``background=True``
    a worker thread (named ``cuniform-bank...``) draws it while commands go on with the current bank, and the new
    bank replaces it at the first command after it is ready (:meth:`wait_for_bank` blocks until then). Which
    command first sees a background bank depends on timing, so runs with it are not bit-reproducible; call
    :meth:`close` to stop the worker.

    A background refresh that raises does not break the controller: the exception is reported once, as a
    :class:`BankRefreshWarning` naming its type and message (``warnings.warn``, so a test or an application can
    turn it into an error with a warnings filter), the current bank stays in use, ``bank_failures`` counts it,
    ``last_bank_error`` keeps it, and the next due refresh is tried as usual.
    """

    def __init__(self, source: PolicyProposal, bank_size: int, generator: torch.Generator,
                 refresh: int | None = None, background: bool = False, seed: int | None = None):
        if refresh is not None:
            check_positive_int("bank_refresh", refresh)
        if background and refresh is None:
            raise ValueError("bank_background refreshes the bank every bank_refresh commands: set bank_refresh too")
        self.bank_size = check_positive_int("bank_size", bank_size)
        self.source = source
        self.system, self.horizon, self.device, self.dtype = source.system, source.horizon, source.device, source.dtype
        self.num_samples = source.num_samples
        self.state_dim = len(self.system.periodic)
        if not self.system.se2_invariant:
            raise ValueError(f"a proposal bank needs an SE(2)-invariant system; {self.system.name} is not")
        if self.state_dim > 3:  # the bank starts at rest; a state's speed etc. is not a change of frame
            raise ValueError(f"a proposal bank needs the state (x, y, theta) only; {self.system.name} has "
                             f"{self.state_dim} dimensions, whose rollouts depend on the start's other dimensions")
        if bank_size < self.num_samples:
            raise ValueError(f"bank_size ({bank_size}) must be at least num_samples ({self.num_samples})")
        self.refresh = refresh
        self.background = bool(background)
        self.refresh_generator = seeded_generator(seed, self.device)
        """the stream refreshes draw from (the worker's, when in the background)"""
        self.commands = 0
        """commands since the last reset()"""
        self.banks_swapped = 0
        """background banks put in use so far"""
        self.bank_failures = 0
        """background refreshes that raised (each reported once by a BankRefreshWarning)"""
        self.last_bank_error: BaseException | None = None
        """the exception of the latest failed background refresh"""
        self._pending: Future | None = None
        self._executor: ThreadPoolExecutor | None = None
        self.resample(generator)
        if self.background:
            self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix=BANK_THREAD_PREFIX)

    @property
    def worker_running(self) -> bool:
        """Whether the background worker is up (False after :meth:`close`)."""
        return self._executor is not None

    def draw_bank(self, generator: torch.Generator) -> tuple[Tensor, Tensor]:
        """``bank_size`` fresh rollouts at the origin: ``[M, T+1, d]``, ``[M, T, q]`` (not put in use)."""
        check_generator(generator, self.device)
        origin = torch.zeros(self.state_dim, dtype=self.dtype, device=self.device)
        states, actions = self.source.rollout(origin, self.bank_size, generator)
        return states.contiguous(), actions  # a subset is gathered by rows (a rollout may give a time-major view)

    def resample(self, generator: torch.Generator | None = None) -> None:
        """Draw a new bank now and use it (from ``generator``, default the refresh stream)."""
        self.bank_states, self.bank_actions = self.draw_bank(generator or self.refresh_generator)

    def propose(self, state: Tensor, generator: torch.Generator) -> tuple[Tensor, Tensor]:
        idx = torch.randperm(self.bank_size, generator=generator, device=self.device)[: self.num_samples]  # [K]
        local = self.bank_states[idx]  # [K, T+1, d]
        if rollout_kernels.usable(local):  # the compiled frame change, reading the subset in its own order
            return rollout_kernels.to_world(local.permute(1, 2, 0), state), self.bank_actions[idx]
        return se2_to_world(local, state), self.bank_actions[idx]  # [K, T+1, d], [K, T, q]

    def update(self, result: MPPIResult) -> None:
        """Count the command; every ``refresh`` commands, draw a new bank (or, in the background, put a finished
        one in use and submit the next)."""
        self.commands += 1
        if self.refresh is None:
            return
        due = self.commands % self.refresh == 0
        if self._executor is not None:
            self._swap_if_ready()
            if due and self._pending is None:
                self._pending = self._executor.submit(self.draw_bank, self.refresh_generator)
        elif due:
            self.resample()

    def reset(self) -> None:
        """Restart the refresh count (the bank itself is kept)."""
        self.commands = 0

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
        warnings.warn(f"proposal bank: background bank refresh failed ({type(error).__name__}: {error}); "
                      f"the current bank stays in use and the next refresh is tried as usual",
                      BankRefreshWarning, stacklevel=5)

    def wait_for_bank(self) -> bool:
        """Block until a background refresh in flight is done and use its bank; False when none was pending or it
        failed (then reported by a :class:`BankRefreshWarning`)."""
        return self._swap_if_ready(wait=True)

    def close(self) -> None:
        """Stop the background worker: a pending refresh is finished first (and used, or reported if it failed).
        The thread is stopped even when a refresh failed; calling it again does nothing. Refreshes after it run
        in the control loop."""
        executor, self._executor = self._executor, None
        if executor is None:
            return
        self.background = False
        try:
            self._swap_if_ready(wait=True)
        finally:
            executor.shutdown(wait=True)


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
