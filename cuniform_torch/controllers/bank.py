"""The proposal bank of C-Uniform MPPI (:class:`BankProposal`) and its background worker.

M rollouts pre-sampled at the origin; each command takes a random subset of K of them and moves it to the pose by
a rigid transform. With a table set (a policy with ``members`` and ``starts``, e.g. a ``ks_speed`` set over the
speed) the bank holds M rollouts per member, from its start at the origin pose; a command takes a subset of the
actions of the member nearest to the state and rolls them out from the state (the exact states for its speed). Refreshed every ``refresh`` commands, in the control loop or in a background worker thread
(which lives here).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor

import torch
from torch import Tensor

from cuniform_torch.common.frames import se2_to_world
from cuniform_torch.controllers.checks import check_positive_int, seeded_generator
from cuniform_torch.controllers.proposals import OneRobotCall, PolicyProposal
from cuniform_torch.controllers.result import MPPIResult
from cuniform_torch.controllers.streams import RobotStreams
from cuniform_torch.sampling import kernels as rollout_kernels
from cuniform_torch.sampling.rollout import check_generator, rollout_actions

__all__ = ["BankProposal", "BankRefreshWarning", "BANK_THREAD_PREFIX"]

BANK_THREAD_PREFIX = "cuniform-bank"
"""name prefix of the background bank worker's thread"""


class BankRefreshWarning(RuntimeWarning):
    """A background bank refresh of :class:`BankProposal` raised; the controller goes on with its current bank."""


class BankProposal(OneRobotCall):
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
        self.num_samples, self.num_robots = source.num_samples, source.num_robots
        self.state_dim = len(self.system.periodic)
        if not self.system.se2_invariant:
            raise ValueError(f"a proposal bank needs an SE(2)-invariant system; {self.system.name} is not")
        caps = source.capabilities  # read once, by the source
        self.member_starts = caps.member_starts if caps.table_set else None
        """``[S, d]`` the starts of a table set's members (one bank each), None for one table or MLP"""
        if self.state_dim > 3 and self.member_starts is None:  # a state's speed etc. is not a change of frame
            raise ValueError(f"a proposal bank needs the state (x, y, theta) only; {self.system.name} has "
                             f"{self.state_dim} dimensions, whose rollouts depend on the start's other dimensions "
                             "(a table set over them, load_table(DIR), gets a bank per start)")
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
        self.draw_bank: Callable[[torch.Generator], tuple[Tensor, Tensor]] = self.draw_rollouts
        """``generator -> (states, actions)``, what a refresh calls: :meth:`draw_rollouts`; an attribute, not a
        method, so that a soak run or a test can swap it on one bank (fault injection)"""
        self.resample(generator)
        if self.background:
            self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix=BANK_THREAD_PREFIX)

    @property
    def worker_running(self) -> bool:
        """Whether the background worker is up (False after :meth:`close`)."""
        return self._executor is not None

    def draw_rollouts(self, generator: torch.Generator) -> tuple[Tensor, Tensor]:
        """``bank_size`` fresh rollouts at the origin: ``[M, T+1, d]``, ``[M, T, q]`` (not put in use); with a
        table set, per member from its start at the origin pose: ``[S, M, T+1, d]``, ``[S, M, T, q]``."""
        check_generator(generator, self.device)
        if self.member_starts is None:
            origin = torch.zeros(self.state_dim, dtype=self.dtype, device=self.device)
            states, actions = self.source.rollout(origin, self.bank_size, generator)
            return states.contiguous(), actions  # a subset is gathered by rows (a rollout may give a time-major view)
        origins = self.member_starts.to(self.dtype).to(self.device).clone()
        origins[:, :3] = 0.0  # the frame change moves the pose; the other dimensions pick the member
        drawn = [self.source.rollout(o, self.bank_size, generator) for o in origins]  # S draws, at refresh time only
        return torch.stack([s.contiguous() for s, _ in drawn]), torch.stack([a for _, a in drawn])

    def resample(self, generator: torch.Generator | None = None) -> None:
        """Draw a new bank now and use it (from ``generator``, default the refresh stream)."""
        self.bank_states, self.bank_actions = self.draw_bank(generator or self.refresh_generator)

    def propose_batch(self, states: Tensor, streams: RobotStreams) -> tuple[Tensor, Tensor]:
        """Each robot's random subset of K bank rollouts (its own stream's permutation), moved to its pose:
        ``states [B, d]`` -> ``[B, K, T+1, d]``, ``[B, K, T, q]``."""
        idx = torch.stack([torch.randperm(self.bank_size, generator=g, device=self.device)[: self.num_samples]
                           for g in streams.generators])  # [B, K]: a permutation per robot, from its stream
        if self.member_starts is not None:  # the nearest member's actions, rolled out from the state itself
            nearest = self.source.capabilities.nearest
            assert nearest is not None  # member_starts: a table set
            members = nearest(states)[0].tolist()  # stateless: a background draw may run for_start
            actions = torch.stack([self.bank_actions[m][i] for m, i in zip(members, idx)])  # [B, K, T, q]
            b, k, t, q = actions.shape
            return (rollout_actions(self.system, states.repeat_interleave(k, dim=0), actions.view(b * k, t, q))
                    .view(b, k, t + 1, -1), actions)
        b, k = idx.shape
        local = self.bank_states[idx.view(-1)]  # [B*K, T+1, d]
        # one arithmetic for any B (a robot's states are the same bits alone and in a batch): the compiled frame
        # change with per-robot poses (each pose's cos and sin computed alone), else torch ops on [B*K, 1, d] poses
        if rollout_kernels.usable(local):
            world = rollout_kernels.to_world(local.permute(1, 2, 0), states)  # [B*K, T+1, d]
        else:
            world = se2_to_world(local, states.repeat_interleave(k, dim=0).unsqueeze(1))
        return world.view(b, k, *world.shape[1:]), self.bank_actions[idx]

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

    def reset(self, robots: Tensor | None = None) -> None:
        """Restart the refresh count (the bank itself is kept; shared by the robots)."""
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

