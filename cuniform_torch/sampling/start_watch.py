"""The start check of a policy valid from one start (a table, an MLP distilled from one): :class:`StartWatch`
warns, :class:`StartMismatchWarning`, when such a policy is rolled out from another start (read by
:func:`cuniform_torch.rollout.rollout` through a policy's ``watch_start``), once per episode, and counts every
such rollout and its lookups in :class:`StartMisses`. :class:`WatchesStart` is the one implementation of the
members a policy answers through its watch (``watch_start``, ``new_episode``, ``start_misses``, ``build_start``).

An episode begins when the policy is made, when a controller around it is made or ``reset()``
(:class:`~cuniform_torch.controllers.proposals.PolicyProposal` calls the policy's ``new_episode``, read once), and
at :func:`new_episode` (or ``policy.new_episode()``). :func:`start_misses` reads the current episode's
counts.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable

import torch
from torch import Tensor

from cuniform_torch.grid.cells import Grid
from cuniform_torch.sampling.fallback_counts import FallbackCounts
from cuniform_torch.systems import System

__all__ = ["OWN_ROBOT", "StartMismatchWarning", "StartMisses", "StartWatch", "WatchesStart", "new_episode",
           "start_misses", "watch_of"]

OWN_ROBOT = 'README, "Your own robot"'
"""where the README tells how to build a table at another start, or a table set"""


class StartMismatchWarning(UserWarning):
    """A table (or an MLP distilled from one) rolled out from a start it was not built for: its probabilities
    there are mostly the fallback's (uniform actions), not C-Uniform ones."""


class StartMisses:
    """One episode's rollouts from a start the policy was not built for (off-start rollouts), counted by the
    :class:`StartWatch` es that share it (a table set's members share one).

    The counts may be device tensors until read (counting after the warning never syncs); reading syncs.
    """

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        """A new episode: nothing counted, and the next off-start rollout warns."""
        self.warned = False
        self._rollouts: int | Tensor = 0
        self._lookups: int | Tensor = 0
        self._misses: int | Tensor = 0

    @property
    def rollouts(self) -> int:
        """Off-start rollouts this episode."""
        return int(self._rollouts)

    @property
    def lookups(self) -> int:
        """Table lookups of those rollouts."""
        return int(self._lookups)

    @property
    def misses(self) -> int:
        """Lookups of those rollouts that fell back to uniform actions (the fallback's misses)."""
        return int(self._misses)

    @property
    def rate(self) -> float:
        """``misses / lookups`` (0 when nothing was counted)."""
        lookups = self.lookups
        return self.misses / lookups if lookups else 0.0

    def add(self, off: bool | Tensor, lookups: int, misses: int | Tensor) -> None:
        """Count one rollout: ``off`` (a bool or a 0-d device bool) says whether it was off-start."""
        self._rollouts = self._rollouts + off
        self._lookups = self._lookups + off * lookups
        self._misses = self._misses + off * misses

    def __repr__(self) -> str:
        return (f"StartMisses(rollouts={self.rollouts}, lookups={self.lookups}, misses={self.misses}, "
                f"warned={self.warned})")


class StartWatch:
    """Warns once per episode (:class:`StartMismatchWarning`) when a policy valid from one start is rolled out
    from another, and counts every such rollout of the episode in :attr:`episode`.

    ``build_start [d]`` is the start the table was built from (the zero state: tables record no other). A start
    *differs* when its cell (:class:`~cuniform_torch.grid.cells.Grid`) differs from the build start's in a dimension
    the rollout does not move into the start's frame: every dimension, or for an SE(2)-relative rollout the
    dimensions after ``(x, y, theta)`` (speeds, steering angles: a frame change does not move them). A pose-only
    SE(2) rollout is never watched; any other costs one host read of the start per rollout until the episode has
    warned, then a few device operations (no sync) per rollout to count it.
    """

    def __init__(self, who: str, system: System, build_start: Tensor | None = None,
                 counts: FallbackCounts | None = None):
        self.who = who
        self.counts = counts
        """the policy's fallback counts, read for the miss rate of an off-start rollout (None: not counted)"""
        self.system = system
        self.grid = Grid.of(system)
        d = self.grid.dim
        start = torch.zeros(d, dtype=torch.float64) if build_start is None else build_start.detach().double().cpu()
        if start.shape != (d,):
            raise ValueError(f"{who}: build_start must have shape [{d}], got {list(start.shape)}")
        self.build_start = start  # [d] float64
        self._build_cell = self.grid.cells(start)  # [d] int64
        self._device_cells: dict[torch.device, Tensor] = {}
        self.episode = StartMisses()
        """this episode's off-start rollouts (a table set gives its members one shared object: they warn once
        together)"""

    @property
    def warned(self) -> bool:
        """Whether this episode has warned."""
        return self.episode.warned

    def new_episode(self) -> None:
        """Forget the episode: zero its counts; the next off-start rollout warns again."""
        self.episode.reset()

    def begin(self, x0: Tensor, relative: bool) -> Callable[[], None] | None:
        """Before a rollout from ``x0 [d]`` (or ``[N, d]``): None when there is nothing to say, else the call that
        counts (and, the first time in the episode, warns) after the rollout, with the miss rate of that rollout
        (from :attr:`counts`)."""
        first = 3 if relative else 0
        if first >= self.grid.dim:
            return None
        counts = self.counts
        queries = counts.queries if counts is not None else 0
        misses = counts.misses.clone() if counts is not None else None  # 0-d device tensor: no sync yet
        if self.episode.warned:  # said already: count on x0's device, with no host read
            cells = self.grid.cells(x0.detach().double())[..., first:]
            off = (cells != self._cell_on(x0.device)[first:]).any()  # 0-d bool
            return lambda: self._count(off, queries, misses)
        cells = self.grid.cells(x0.detach().double().cpu())[..., first:]  # [d - first] or [N, d - first]
        if bool((cells == self._build_cell[first:]).all()):
            return None
        return lambda: self._warn(x0, relative, queries, misses)

    def _cell_on(self, device: torch.device) -> Tensor:
        cell = self._device_cells.get(device)
        if cell is None:
            cell = self._device_cells[device] = self._build_cell.to(device)
        return cell

    def _since(self, queries: int, misses: Tensor | None) -> tuple[int, int | Tensor]:
        """Lookups and misses counted since ``(queries, misses)`` were read (misses: a device tensor, no sync)."""
        counts = self.counts
        if counts is None or misses is None:
            return 0, 0
        return counts.queries - queries, counts.misses - misses

    def _count(self, off: bool | Tensor, queries: int, misses: Tensor | None) -> None:
        asked, missed = self._since(queries, misses)
        self.episode.add(off, asked, missed)

    def _warn(self, x0: Tensor, relative: bool, queries: int, misses: Tensor | None) -> None:
        self.episode.warned = True
        asked, missed_t = self._since(queries, misses)
        missed = int(missed_t)
        self.episode.add(True, asked, missed)
        rate = f"{missed / asked:.3f} ({missed} of {asked} lookups)" if asked else "not counted"
        name = getattr(self.system, "name", type(self.system).__name__)
        why = (f"{name}'s dimensions after (x, y, theta) are not moved by the frame change" if relative
               else f"{name} is not SE(2)-invariant, so no frame change moves the table to another start")
        start = [round(v, 4) for v in (x0 if x0.ndim == 1 else x0[0]).tolist()]
        warnings.warn(
            f"{self.who} is valid from its build start {self.build_start.tolist()} only and is rolled out from {start}; "
            f"{why}. Miss rate on this rollout: {rate}; a miss gets the fallback's uniform actions, not C-Uniform "
            f"ones. Build a table at that start, or a table set over the starts you need (see {OWN_ROBOT}). "
            f"Warned once per episode (a controller's construction or reset(), or new_episode(policy)); "
            f"start_misses(policy) counts every such rollout of the episode.", StartMismatchWarning, stacklevel=5)


class WatchesStart:
    """The start check of a policy valid from one start (a table, an MLP, a map policy), written once: the policy
    keeps a :class:`StartWatch` as ``_start_watch`` (made with its :class:`FallbackCounts`) and answers through it
    ``watch_start`` (what the rollout calls), ``new_episode`` (what a controller calls), ``start_misses`` and
    ``build_start``."""

    _start_watch: StartWatch

    @property
    def build_start(self) -> Tensor:
        """The start the policy is valid from, ``[d]`` float64."""
        return self._start_watch.build_start

    def watch_start(self, x0: Tensor, relative: bool) -> Callable[[], None] | None:
        """Before a rollout from ``x0 [d]`` (or ``[N, d]``): :meth:`StartWatch.begin`."""
        return self._start_watch.begin(x0, relative)

    def new_episode(self) -> None:
        """Begin an episode: the off-start warning is armed again and :attr:`start_misses` restarts."""
        self._start_watch.new_episode()

    @property
    def start_misses(self) -> StartMisses:
        """This episode's off-start rollouts (``rollouts``, ``lookups``, ``misses``, ``rate``, ``warned``)."""
        return self._start_watch.episode


def watch_of(policy: object) -> StartWatch | None:
    """The :class:`StartWatch` of a policy valid from one start (a :class:`WatchesStart`), else None."""
    return policy._start_watch if isinstance(policy, WatchesStart) else None


def new_episode(policy: object) -> None:
    """Begin an episode for ``policy``: its start check warns again and its counts restart (its own
    ``new_episode()``: a :class:`WatchesStart` policy, a table set; others: nothing)."""
    own = getattr(policy, "new_episode", None)  # a user's call, not a command's: read here
    if callable(own):
        own()


def start_misses(policy: object) -> StartMisses | None:
    """The current episode's off-start rollouts of ``policy`` (its ``start_misses``: a :class:`WatchesStart`
    policy's, a table set's), None for a policy that watches no start."""
    own = getattr(policy, "start_misses", None)  # a user's call, not a command's: read here
    return own if isinstance(own, StartMisses) else None
