"""The :class:`System` protocol, the limits a system must respect, and the checks of a (user) system.

Shapes: N samples, d state dimensions, q action dimensions, A actions.
"""

from __future__ import annotations

import json
import math
from typing import Any, ClassVar, Protocol, runtime_checkable

import torch
from torch import Tensor

from cuniform_torch.common.checks import positive, positive_int, wrap_angle
from cuniform_torch.common.frames import se2_to_world
from cuniform_torch.grid.cells import check_grid

__all__ = ["System", "check_system", "se2_invariance_gap", "system_horizon", "DEFAULT_HORIZON", "MAX_ACTIONS",
           "MAX_HORIZON"]

DEFAULT_HORIZON = 10
"""horizon (steps) of a build when neither the command line nor the system (``default_horizon``) sets one"""

MAX_ACTIONS = 65536
"""the most actions a system may have: every table row holds one probability per action"""

MAX_HORIZON = 10000
"""the longest horizon (steps) a table or checkpoint may declare"""


@runtime_checkable
class System(Protocol):
    """What the table builder and the runtime need from a robot model.

    Attributes:
        name: registry name, so a table's system JSON can rebuild the system (``make_system(name, **params())``).
        dt: time step in seconds.
        cell_size: grid cell size per state dimension ``[d]`` (an angle dimension: ``2 pi / K`` for an integer K).
        periodic: which state dimensions are angles in ``[-pi, pi)`` (``step`` must wrap them there).
        cell_offset: grid offset per dimension, in cells (``|offset| < 0.5``); see :mod:`cuniform_torch.grid.cells`.
            A small offset keeps states that move by exact half cells off the cell boundaries.
        se2_invariant: whether the dynamics commute with planar rigid motions, so one table built at the origin
            serves any start pose after a change of frame. The contract of ``True``: the state is
            ``(x, y, theta, *rest)`` with ``theta`` periodic, and the frame change
            (:func:`cuniform_torch.common.frames.se2_to_world`) rotates and translates ``(x, y)``, adds the pose's heading
            to ``theta`` and leaves ``rest`` (speeds, steering angles, ...) unchanged; ``step`` must commute with
            it (:func:`se2_invariance_gap` measures that). ``False``: tables are used with the states as they are.

    Optional attribute: ``default_horizon`` (int), the build's horizon when ``--horizon`` is not given
    (:data:`DEFAULT_HORIZON` otherwise).

    Methods: ``action_set`` (the finite actions ``[A, q]``), ``step`` (batched, differentiable torch ops; the
    dtype and device of its inputs), ``params`` (JSON-serializable constructor arguments). A table is built
    from the zero state, so the zero state must be a valid start.
    """

    name: ClassVar[str]
    periodic: ClassVar[tuple[bool, ...]]
    se2_invariant: ClassVar[bool]

    # read-only members: a frozen dataclass (the built-in systems) or a plain attribute both satisfy them
    @property
    def dt(self) -> float: ...

    @property
    def cell_size(self) -> tuple[float, ...]: ...

    @property
    def cell_offset(self) -> tuple[float, ...]: ...

    @property
    def state_dim(self) -> int: ...

    def action_set(self, dtype: torch.dtype = torch.float32, device: torch.device | str | None = None) -> Tensor:
        """The finite action set ``[A, q]``."""
        ...

    def step(self, x: Tensor, u: Tensor) -> Tensor:
        """One step of the dynamics: ``x [N, d]``, ``u [N, q]`` -> ``[N, d]`` (same dtype and device)."""
        ...

    def params(self) -> dict[str, Any]:
        """JSON-serializable constructor arguments: ``make_system(name, **params)`` rebuilds the system."""
        ...


def system_horizon(system: Any) -> int:
    """The system's ``default_horizon`` when it has one, else :data:`DEFAULT_HORIZON`."""
    horizon = getattr(system, "default_horizon", None)
    if horizon is None:
        return DEFAULT_HORIZON
    return positive_int(repr(getattr(system, "name", system)), "default_horizon", horizon)


def check_system(system: Any) -> None:
    """Raise ValueError naming what a (user) system lacks or gets wrong; a no-op for a good one.

    Checks the attributes of :class:`System`, the grid (:func:`~cuniform_torch.grid.cells.check_grid`: sizes, offsets,
    angle cells of ``2 pi / K``), the action set (a finite float ``[A, q]``), the SE(2) contract (``x, y, theta``
    first, ``theta`` an angle), that ``step`` maps ``[2, d]`` zeros to ``[2, d]`` in the same dtype, and that
    ``params()`` is JSON-serializable.
    """
    who = f"system {getattr(system, 'name', type(system).__name__)!r}"
    missing = [a for a in ("name", "dt", "cell_size", "periodic", "cell_offset", "se2_invariant")
               if not hasattr(system, a)]
    missing += [m for m in ("action_set", "step", "params") if not callable(getattr(system, m, None))]
    if missing:
        raise ValueError(f"{who} ({type(system).__name__}) lacks {', '.join(missing)} of the System protocol "
                         "(see cuniform_torch.systems.System)")
    if not isinstance(system.name, str) or not system.name or ":" in system.name:
        raise ValueError(f"{who}: name must be a non-empty string without ':'")
    periodic = tuple(system.periodic)
    if not periodic or not all(isinstance(p, bool) for p in periodic):
        raise ValueError(f"{who}: periodic must be a non-empty tuple of bools, one per state dimension, got {periodic!r}")
    d = len(periodic)
    if getattr(system, "state_dim", d) != d:
        raise ValueError(f"{who}: state_dim is {system.state_dim} but periodic has {d} entries")
    positive(who, dt=system.dt)
    check_grid(system.cell_size, periodic, system.cell_offset, f"{who}: bad grid")
    if not isinstance(system.se2_invariant, bool):
        raise ValueError(f"{who}: se2_invariant must be True or False, got {system.se2_invariant!r}")
    if system.se2_invariant and (d < 3 or periodic[:3] != (False, False, True)):
        raise ValueError(f"{who}: an SE(2)-invariant system needs the state (x, y, theta, ...) with theta "
                         f"periodic and x, y not; periodic is {periodic}")
    system_horizon(system)
    actions = system.action_set(dtype=torch.float64)
    if not isinstance(actions, Tensor) or actions.ndim != 2 or actions.shape[0] < 1 or actions.shape[1] < 1:
        raise ValueError(f"{who}: action_set must return a [A, q] tensor with A, q >= 1, got "
                         f"{list(actions.shape) if isinstance(actions, Tensor) else type(actions).__name__}")
    if actions.shape[0] > MAX_ACTIONS:
        raise ValueError(f"{who}: action_set has {actions.shape[0]} actions; at most {MAX_ACTIONS} are supported")
    if actions.dtype != torch.float64 or not bool(torch.isfinite(actions).all()):
        raise ValueError(f"{who}: action_set(dtype=torch.float64) must return finite float64 actions, got {actions.dtype}")
    x = torch.zeros((2, d), dtype=torch.float64)
    out = system.step(x, actions[:1].expand(2, -1))
    if not isinstance(out, Tensor) or out.shape != (2, d) or out.dtype != torch.float64:
        raise ValueError(f"{who}: step(x [2, {d}] float64, u [2, {actions.shape[1]}]) must return [2, {d}] float64, "
                         f"got {getattr(out, 'dtype', type(out).__name__)} {list(getattr(out, 'shape', []))}")
    try:
        json.dumps(system.params())
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{who}: params() must be JSON-serializable ({exc})") from None


def se2_invariance_gap(system: System, states: Tensor | None = None, num_states: int = 256, seed: int = 0) -> float:
    """How far ``step`` is from commuting with planar rigid motions: the largest difference (float64) between
    stepping a state in a random frame and stepping it at the origin, then changing frame.

    ``states [N, d]`` are the local states to test (default: ``num_states`` random ``x, y`` in [-2, 2] m and
    headings, other dimensions 0); each gets a random pose and a random action. About 1e-15 for an
    SE(2)-invariant system; order 1 for one that is not. ValueError for a system whose state is not
    ``(x, y, theta, *rest)`` (x, y not angles, theta an angle): there is no planar motion to commute with.
    """
    periodic = tuple(system.periodic)
    d = len(periodic)
    if d < 3 or periodic[:3] != (False, False, True):
        who = getattr(system, "name", type(system).__name__)
        raise ValueError(f"se2_invariance_gap: system {who!r} has {d} state dimension(s) with periodic {periodic}; "
                         "it needs the state (x, y, theta, ...) with x, y not periodic and theta periodic")
    gen = torch.Generator().manual_seed(seed)
    if states is None:
        states = torch.zeros((num_states, d), dtype=torch.float64)
        states[:, :2] = torch.rand((num_states, 2), generator=gen, dtype=torch.float64) * 4 - 2
        states[:, 2] = torch.rand(num_states, generator=gen, dtype=torch.float64) * 2 * math.pi - math.pi
    states = states.to(torch.float64)
    n = states.shape[0]
    pose = torch.zeros((n, d), dtype=torch.float64)
    pose[:, :2] = torch.rand((n, 2), generator=gen, dtype=torch.float64) * 10 - 5
    pose[:, 2] = torch.rand(n, generator=gen, dtype=torch.float64) * 2 * math.pi - math.pi
    actions = system.action_set(dtype=torch.float64)
    u = actions[torch.randint(0, actions.shape[0], (n,), generator=gen)]
    world_then_step = system.step(se2_to_world(states, pose), u)  # [N, d]
    step_then_world = se2_to_world(system.step(states, u), pose)
    diff = world_then_step - step_then_world
    per = torch.tensor(system.periodic)
    diff = torch.where(per, wrap_angle(diff), diff)
    return float(diff.abs().max())
