"""The :class:`System` protocol, the limits a system must respect, and the checks of a (user) system.

Shapes: N samples, d state dimensions, q action dimensions, A actions.
"""

from __future__ import annotations

import json
import math
import weakref
from typing import Any, ClassVar, Protocol, runtime_checkable

import torch
from torch import Tensor

from cuniform_torch.common.checks import positive, positive_int, wrap_angle
from cuniform_torch.common.frames import se2_to_world
from cuniform_torch.grid.cells import check_grid

__all__ = ["System", "check_system", "check_dynamics", "se2_invariance_gap", "system_horizon", "DEFAULT_HORIZON", "MAX_ACTIONS",
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
    dtype and device of its inputs; a new tensor, its inputs left unchanged: :func:`check_dynamics` probes it once
    where a controller, proposal or rollout is made), ``params`` (JSON-serializable constructor arguments). A table is built
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
    first, ``theta`` an angle), ``step`` by :func:`check_dynamics` (float64, on the CPU), and that ``params()`` is
    JSON-serializable.
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
    try:
        actions = check_dynamics(system, torch.float64, "cpu", who=who)
    except TypeError as exc:  # this check's one error type
        raise ValueError(str(exc)) from None
    if actions.shape[0] > MAX_ACTIONS:
        raise ValueError(f"{who}: action_set has {actions.shape[0]} actions; at most {MAX_ACTIONS} are supported")
    try:
        json.dumps(system.params())
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{who}: params() must be JSON-serializable ({exc})") from None


_CHECKED: dict[int, tuple[weakref.ref[Any], set[tuple[torch.dtype, str]]]] = {}
"""systems whose dynamics passed :func:`check_dynamics`, by ``id``: (a weak reference, the (dtype, device) pairs)"""


def _describe(value: Any) -> str:
    if isinstance(value, Tensor):
        return f"a {list(value.shape)} tensor of {value.dtype} on {value.device}"
    return f"{type(value).__module__}.{type(value).__qualname__}" if value is not None else "None"


def check_dynamics(system: Any, dtype: torch.dtype = torch.float64, device: torch.device | str = "cpu",
                   who: str | None = None) -> Tensor:
    """Check a (user) system's ``action_set`` and ``step`` once, in ``dtype`` on ``device``; return the action set.

    What a controller, proposal or rollout relies on and never checks per step: ``action_set(dtype, device)`` is a
    non-empty finite ``[A, q]`` tensor of that dtype and device, and ``step`` (probed twice on a few states: from
    zeros, then from where that led) returns a *new* ``[N, d]`` tensor of its input's dtype and device and leaves
    its inputs ``x`` and ``u`` unchanged (a ``step`` that updates ``x`` in place corrupts the rollouts it is part
    of; an integer result would be cast silently). TypeError (not a tensor) or ValueError naming the system and
    the rule otherwise. A system that passed for this dtype and device is not probed again (by identity).
    """
    who = who or f"system {getattr(system, 'name', type(system).__name__)!r} ({type(system).__name__})"
    device = torch.device(device)
    key = (dtype, device.type if device.index is None else str(device))
    if _probed(system, key):
        return system.action_set(dtype=dtype, device=device)
    missing = [m for m in ("action_set", "step") if not callable(getattr(system, m, None))]
    missing += [] if hasattr(system, "periodic") else ["periodic"]
    if missing:
        raise TypeError(f"{who} lacks {', '.join(missing)} of the System protocol (see cuniform_torch.systems.System)")
    d = len(tuple(system.periodic))
    actions = system.action_set(dtype=dtype, device=device)
    if not isinstance(actions, Tensor):
        raise TypeError(f"{who}: action_set(dtype, device) must return a torch.Tensor [A, q], got {_describe(actions)}")
    if actions.ndim != 2 or actions.shape[0] < 1 or actions.shape[1] < 1:
        raise ValueError(f"{who}: action_set must return a non-empty [A, q] tensor (A, q >= 1), got "
                         f"{_describe(actions)}")
    if actions.dtype != dtype or not _same_device(actions.device, device):
        raise ValueError(f"{who}: action_set(dtype={dtype}, device={device}) must return actions of that dtype and "
                         f"device, got {_describe(actions)} (use torch.tensor(..., dtype=dtype, device=device))")
    if not bool(torch.isfinite(actions).all()):
        raise ValueError(f"{who}: action_set must return finite actions (it has NaN or infinite values)")
    a = actions.shape[0]
    n = max(2, min(a, 4))
    u = actions[torch.arange(n, device=device) % a]  # [n, q]: a few different actions
    x = torch.zeros((n, d), dtype=dtype, device=device)
    with torch.no_grad():
        for probe in ("zero states", "the states the first step reached"):
            x_before, u_before = x.clone(), u.clone()
            out = system.step(x, u)
            where = f"step(x, u) from {probe} (x a [{n}, {d}] tensor of {dtype} on {device})"
            if not isinstance(out, Tensor):
                raise TypeError(f"{who}: {where} must return a torch.Tensor [{n}, {d}], got {_describe(out)}")
            if out.dtype != dtype or not _same_device(out.device, device) or out.shape != (n, d):
                raise ValueError(f"{who}: {where} returned {_describe(out)}; it must return [{n}, {d}] in the dtype "
                                 f"and on the device of x (nothing is cast silently: compute in x.dtype)")
            if not torch.allclose(x, x_before, rtol=0, atol=0, equal_nan=True) or not torch.allclose(
                    u, u_before, rtol=0, atol=0, equal_nan=True):
                raise ValueError(f"{who}: {where} changed its input {'x' if not torch.equal(x, x_before) else 'u'} "
                                 "in place; step must leave x and u unchanged and return a new tensor (build the "
                                 "result with out-of-place ops, or start from x.clone())")
            if out is x or (out.numel() > 0 and out.untyped_storage().data_ptr() == x.untyped_storage().data_ptr()):
                raise ValueError(f"{who}: {where} returned x itself (or a view of it); step must return a new tensor "
                                 "(e.g. x.clone() when nothing moves)")
            if not bool(torch.isfinite(out).all()):
                break  # nothing to step on from there; the first probe checked the rules
            x = out
    _remember(system, key)
    return actions


def _probed(system: Any, key: tuple[torch.dtype, str]) -> bool:
    entry = _CHECKED.get(id(system))
    return entry is not None and entry[0]() is system and key in entry[1]


def _remember(system: Any, key: tuple[torch.dtype, str]) -> None:
    """Note that ``system`` passed :func:`check_dynamics` for ``key`` (forgotten when the system is collected)."""
    ident = id(system)

    def forget(_ref: weakref.ref[Any]) -> None:
        _CHECKED.pop(ident, None)

    entry = _CHECKED.get(ident)
    if entry is None or entry[0]() is not system:
        try:
            entry = (weakref.ref(system, forget), set())
        except TypeError:  # not weakly referenceable (__slots__ without __weakref__): probed at every construction
            return
        _CHECKED[ident] = entry
    entry[1].add(key)


def _same_device(a: torch.device, b: torch.device) -> bool:
    """``cuda`` and ``cuda:0`` (the current device) are the same device here."""
    return a.type == b.type and (a.index is None or b.index is None or a.index == b.index)


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
