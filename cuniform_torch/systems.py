"""Systems: batched torch dynamics with a finite action set and a grid, plus a registry.

Shapes used in this module: N samples, d state dimensions, q action dimensions, A actions.

A *system* is anything that satisfies the :class:`System` protocol. One definition serves the offline
table builder (float64 on the CPU) and the runtime (float32 on any device): ``step`` only uses torch ops
and keeps the dtype and device of its inputs.

Built in:

* ``random_walk_1d``: ``x' = x + u dt`` with ``num_actions`` speeds evenly in ``[-max_speed, max_speed]``.
* ``dubins``: state ``(x, y, theta)``, fixed speed ``v``, action = angular velocity ``omega``; stepped as the
  paper's reference release does: ``theta' = wrap(theta + omega dt)`` first, then
  ``x' = x + v cos(theta') dt``, ``y' = y + v sin(theta') dt``.
* ``ks``: the kinematic single-track (bicycle) model, reference point on the rear axle: state
  ``(x, y, theta)``, fixed speed ``v``, action = steering angle ``delta``; yaw rate ``v tan(delta) / L``
  (wheelbase ``L``), stepped like ``dubins`` (heading first, then position with the new heading).
* ``ks_speed``: the same model with the speed as a fourth state: ``(x, y, theta, v)``, 2-D actions
  ``(delta, a)`` (steering angle x acceleration, a product grid); ``v' = clip(v + a dt, min_speed,
  max_speed)`` first, then the heading with ``v'``, then the position.

Your own robot: write a class (a frozen dataclass is simplest) with the attributes and methods of
:class:`System`, then ``register_system("my_robot", MyRobot)``. Tables record the factory as an importable
``"module:qualname"`` path in their system JSON (key ``factory``), but reading a table or checkpoint never
imports or calls it: :func:`system_from_json` rebuilds a system from the registry, or from a ``trust_factory``
the caller names (the file's string is only compared with it). In a fresh process, import the module that
registers the system first, or pass ``trust_factory="my_robots:MyRobot"``. :func:`check_system` says clearly
what a user system lacks; :func:`se2_invariance_gap` checks a claimed SE(2) invariance numerically.
"""

from __future__ import annotations

import dataclasses
import importlib
import inspect
import json
import math
from dataclasses import dataclass
from typing import Any, Callable, ClassVar, Protocol, runtime_checkable

import torch
from torch import Tensor

from .grid import Grid

__all__ = [
    "System",
    "RandomWalk1D",
    "Dubins",
    "KinematicSingleTrack",
    "KinematicSingleTrackSpeed",
    "UnknownSystemError",
    "register_system",
    "make_system",
    "known_systems",
    "system_to_json",
    "system_from_json",
    "wrap_angle",
    "check_system",
    "se2_invariance_gap",
    "resolve_system",
    "import_system_modules",
    "factory_path",
    "load_factory",
    "system_horizon",
    "DEFAULT_HORIZON",
    "MAX_ACTIONS",
    "MAX_HORIZON",
]

DEFAULT_HORIZON = 10
"""horizon (steps) of a build when neither the command line nor the system (``default_horizon``) sets one"""


@runtime_checkable
class System(Protocol):
    """What the table builder and the runtime need from a robot model.

    Attributes:
        name: registry name, so a table's system JSON can rebuild the system (``make_system(name, **params())``).
        dt: time step in seconds.
        cell_size: grid cell size per state dimension ``[d]`` (an angle dimension: ``2 pi / K`` for an integer K).
        periodic: which state dimensions are angles in ``[-pi, pi)`` (``step`` must wrap them there).
        cell_offset: grid offset per dimension, in cells (``|offset| < 0.5``); see :mod:`cuniform_torch.grid`.
            A small offset keeps states that move by exact half cells off the cell boundaries.
        se2_invariant: whether the dynamics commute with planar rigid motions, so one table built at the origin
            serves any start pose after a change of frame. The contract of ``True``: the state is
            ``(x, y, theta, *rest)`` with ``theta`` periodic, and the frame change
            (:func:`cuniform_torch.frames.se2_to_world`) rotates and translates ``(x, y)``, adds the pose's heading
            to ``theta`` and leaves ``rest`` (speeds, steering angles, ...) unchanged; ``step`` must commute with
            it (:func:`se2_invariance_gap` measures that). ``False``: tables are used with the states as they are.

    Optional attribute: ``default_horizon`` (int), the build's horizon when ``--horizon`` is not given
    (:data:`DEFAULT_HORIZON` otherwise).

    Methods: ``action_set`` (the finite actions ``[A, q]``), ``step`` (batched, differentiable torch ops; the
    dtype and device of its inputs), ``params`` (JSON-serializable constructor arguments). A table is built
    from the zero state, so the zero state must be a valid start.
    """

    name: ClassVar[str]
    dt: float
    cell_size: tuple[float, ...]
    periodic: ClassVar[tuple[bool, ...]]
    cell_offset: tuple[float, ...]
    se2_invariant: ClassVar[bool]

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


def wrap_angle(theta: Tensor) -> Tensor:
    """Wrap angles to ``[-pi, pi)``, elementwise, keeping dtype and device."""
    return torch.remainder(theta + math.pi, 2.0 * math.pi) - math.pi


def _as_float_tuple(value: Any, length: int, field: str, system: str) -> tuple[float, ...]:
    try:
        out = tuple(float(v) for v in value)
    except (TypeError, ValueError):
        raise ValueError(f"{system}: {field} must be a sequence of {length} numbers, got {value!r}") from None
    if len(out) != length:
        raise ValueError(f"{system}: {field} needs {length} value(s) (one per state dimension), got {len(out)}: {out}")
    if not all(math.isfinite(v) for v in out):
        raise ValueError(f"{system}: {field} must be finite, got {out}")
    return out


def _check_grid(system: Any) -> None:
    """Validate and normalize ``cell_size`` / ``cell_offset`` of a frozen dataclass system in place."""
    d = len(system.periodic)
    name = system.name
    cell_size = _as_float_tuple(system.cell_size, d, "cell_size", name)
    offset = _as_float_tuple(system.cell_offset, d, "cell_offset", name)
    if any(c <= 0 for c in cell_size):
        raise ValueError(f"{name}: cell_size must be positive in every dimension, got {cell_size}")
    if any(abs(o) >= 0.5 for o in offset):
        raise ValueError(f"{name}: cell_offset is in cells and must satisfy |offset| < 0.5, got {offset}")
    sizes = list(cell_size)
    for i, periodic in enumerate(system.periodic):
        if periodic:
            k = round(2.0 * math.pi / cell_size[i])
            if k < 1 or abs(k * cell_size[i] - 2.0 * math.pi) > 1e-3 * 2.0 * math.pi:
                raise ValueError(
                    f"{name}: the angle cell size must divide 2*pi (2*pi/K for an integer K); "
                    f"got {cell_size[i]} (2*pi/{2.0 * math.pi / cell_size[i]:.4f})"
                )
            sizes[i] = 2.0 * math.pi / k  # exact 2 pi / K, so a rounded CLI value like 0.1571 means K = 40
    object.__setattr__(system, "cell_size", tuple(sizes))
    object.__setattr__(system, "cell_offset", offset)


def _positive(name: str, **values: float) -> None:
    for key, value in values.items():
        if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
            raise ValueError(f"{name}: {key} must be a positive number, got {value!r}")


MAX_ACTIONS = 65536
"""the most actions a system may have: every table row holds one probability per action"""

MAX_HORIZON = 10000
"""the longest horizon (steps) a table or checkpoint may declare"""


def _check_num_actions(name: str, num_actions: Any) -> None:
    if isinstance(num_actions, bool) or not isinstance(num_actions, int) or not 1 <= num_actions <= MAX_ACTIONS:
        raise ValueError(f"{name}: num_actions must be a positive integer (at most {MAX_ACTIONS}), got {num_actions!r}")


def _check_step_inputs(system: Any, x: Tensor, u: Tensor, q: int) -> None:
    d = len(system.periodic)
    if x.ndim != 2 or x.shape[1] != d:
        raise ValueError(f"{system.name}.step: x must have shape [N, {d}], got {list(x.shape)}")
    if u.ndim != 2 or u.shape[1] != q or u.shape[0] != x.shape[0]:
        raise ValueError(f"{system.name}.step: u must have shape [{x.shape[0]}, {q}], got {list(u.shape)}")


@dataclass(frozen=True)
class RandomWalk1D:
    """The paper's 1-D random walk ``x' = x + u dt``.

    Defaults give levels of 1, 5, 9, ... cells, and the step L_1 -> L_2 is the paper's Figure 2 (n=5, m=9).
    """

    dt: float = 1.0
    """time step (s)"""
    max_speed: float = 1.0
    """actions are ``num_actions`` speeds evenly spaced in ``[-max_speed, max_speed]``"""
    num_actions: int = 5
    """number of actions (2k+1 in the paper)"""
    cell_size: tuple[float, ...] = (0.5,)
    """grid cell size"""
    cell_offset: tuple[float, ...] = (0.0,)
    """grid offset in cells (|offset| < 0.5)"""

    name: ClassVar[str] = "random_walk_1d"
    periodic: ClassVar[tuple[bool, ...]] = (False,)
    se2_invariant: ClassVar[bool] = False

    def __post_init__(self) -> None:
        _positive(self.name, dt=self.dt, max_speed=self.max_speed)
        _check_num_actions(self.name, self.num_actions)
        _check_grid(self)

    @property
    def state_dim(self) -> int:
        return 1

    def action_set(self, dtype: torch.dtype = torch.float32, device: torch.device | str | None = None) -> Tensor:
        """``[A, 1]`` speeds, evenly in ``[-max_speed, max_speed]`` (computed in float64, then cast)."""
        return _evenly(-self.max_speed, self.max_speed, self.num_actions).to(dtype=dtype, device=device).unsqueeze(1)

    def step(self, x: Tensor, u: Tensor) -> Tensor:
        """``x [N, 1]``, ``u [N, 1]`` -> ``[N, 1]``."""
        _check_step_inputs(self, x, u, 1)
        return x + u * self.dt

    def params(self) -> dict[str, Any]:
        return _params(self)


@dataclass(frozen=True)
class Dubins:
    """Dubins car ``(x, y, theta)`` at fixed speed; action = angular velocity.

    Defaults reproduce the paper's reference release: v = 1 m/s, dt = 0.2 s, 5 angular velocities evenly in
    [-pi/4, pi/4] rad/s, cells 0.05 m x 0.05 m x 2pi/40 rad. Every heading increment of the default preset is
    0, 1/2 or 1 angle cell, so the default grid is shifted by 1% of a cell on the angle dimension
    (``cell_offset``): headings then never sit on a cell boundary, and float32 and float64 agree.
    """

    speed: float = 1.0
    """forward speed v (m/s)"""
    dt: float = 0.2
    """time step (s)"""
    max_omega: float = math.pi / 4
    """actions are ``num_actions`` angular velocities evenly spaced in ``[-max_omega, max_omega]`` (rad/s)"""
    num_actions: int = 5
    """number of angular velocities"""
    cell_size: tuple[float, ...] = (0.05, 0.05, 2.0 * math.pi / 40)
    """grid cell size (m, m, rad); the angle size must be 2*pi/K"""
    cell_offset: tuple[float, ...] = (0.0, 0.0, 0.01)
    """grid offset in cells (|offset| < 0.5)"""

    name: ClassVar[str] = "dubins"
    periodic: ClassVar[tuple[bool, ...]] = (False, False, True)
    se2_invariant: ClassVar[bool] = True

    def __post_init__(self) -> None:
        _positive(self.name, speed=self.speed, dt=self.dt)
        _non_negative(self.name, max_omega=self.max_omega)
        _check_num_actions(self.name, self.num_actions)
        _check_grid(self)

    @property
    def state_dim(self) -> int:
        return 3

    def action_set(self, dtype: torch.dtype = torch.float32, device: torch.device | str | None = None) -> Tensor:
        """``[A, 1]`` angular velocities, evenly in ``[-max_omega, max_omega]``."""
        return _evenly(-self.max_omega, self.max_omega, self.num_actions).to(dtype=dtype, device=device).unsqueeze(1)

    def step(self, x: Tensor, u: Tensor) -> Tensor:
        """``x [N, 3]``, ``u [N, 1]`` -> ``[N, 3]``: heading first, then position with the new heading."""
        _check_step_inputs(self, x, u, 1)
        theta = wrap_angle(x[:, 2] + u[:, 0] * self.dt)  # [N]
        return _advance(x, theta, self.speed * torch.cos(theta) * self.dt, self.speed * torch.sin(theta) * self.dt)

    def params(self) -> dict[str, Any]:
        return _params(self)


def _advance(x: Tensor, theta: Tensor, dx: Tensor, dy: Tensor, *rest: Tensor) -> Tensor:
    """The next planar state ``[N, 3 + len(rest)]``: ``(x + dx, y + dy, theta, *rest)`` from ``[N]`` columns.

    Written column by column into one new tensor: on a CPU, ``torch.stack`` of ``[N]`` columns along dim 1 costs
    about as much as the rest of a Dubins step. The values are those of ``torch.stack((x[:, 0] + dx, ...))``.
    The new state keeps the layout of ``x``: a column-major ``x`` (what :func:`~cuniform_torch.rollout.rollout`
    steps, so that every column is contiguous) gives a column-major state.
    """
    d = 3 + len(rest)
    if x.shape[1] == d and x.stride(0) == 1 and x.shape[0] > 1:  # column-major: [d, N] storage
        out = theta.new_empty((d, x.shape[0])).T
    else:
        out = theta.new_empty((x.shape[0], d))  # the dtype of the new heading (x and u promoted)
    torch.add(x[:, 0], dx, out=out[:, 0])
    torch.add(x[:, 1], dy, out=out[:, 1])
    out[:, 2] = theta
    for i, column in enumerate(rest):
        out[:, 3 + i] = column
    return out


def _evenly(low: float, high: float, num: int) -> Tensor:
    """``num`` values evenly in ``[low, high]`` (float64; one value: their midpoint)."""
    if num == 1:
        return torch.tensor([(low + high) / 2.0], dtype=torch.float64)
    return torch.linspace(low, high, num, dtype=torch.float64)


def _non_negative(name: str, **values: float) -> None:
    for key, value in values.items():
        if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
            raise ValueError(f"{name}: {key} must be a non-negative number, got {value!r}")


def _check_steer(name: str, max_steer: Any) -> None:
    _non_negative(name, max_steer=max_steer)
    if max_steer >= math.pi / 2:
        raise ValueError(f"{name}: max_steer must be below pi/2 (tan diverges), got {max_steer!r}")


@dataclass(frozen=True)
class KinematicSingleTrack:
    """Kinematic single-track (bicycle) model at fixed speed: state ``(x, y, theta)``, action = steering angle.

    Reference point on the rear axle, yaw rate ``v tan(delta) / L``. Stepped like :class:`Dubins` (and the
    paper's reference release): ``theta' = wrap(theta + v tan(delta) / L dt)`` first, then
    ``x' = x + v cos(theta') dt``, ``y' = y + v sin(theta') dt``.

    Defaults (the preset ``ks``, as in the CU-MPPI and C-Free-Uniform follow-ups): wheelbase 0.324 m, v = 1 m/s,
    dt = 0.2 s, 13 steering angles evenly in [-pi/6, pi/6] (steps of 5 deg; the largest turns 20.4 deg per
    step, a 0.56 m turning radius), cells 0.03 m x 0.03 m x 6 deg (2 pi / 60), horizon 15
    (``default_horizon``). A build of the full preset is large; see the README ("Your own robot") for its
    measured size and time.
    """

    wheelbase: float = 0.324
    """distance L between the axles (m)"""
    speed: float = 1.0
    """forward speed v (m/s)"""
    dt: float = 0.2
    """time step (s)"""
    max_steer: float = math.pi / 6
    """actions are ``num_actions`` steering angles evenly spaced in ``[-max_steer, max_steer]`` (rad, < pi/2)"""
    num_actions: int = 13
    """number of steering angles"""
    cell_size: tuple[float, ...] = (0.03, 0.03, 2.0 * math.pi / 60)
    """grid cell size (m, m, rad); the angle size must be 2*pi/K"""
    cell_offset: tuple[float, ...] = (0.0, 0.0, 0.01)
    """grid offset in cells (|offset| < 0.5); 1% of an angle cell, as for Dubins"""

    name: ClassVar[str] = "ks"
    periodic: ClassVar[tuple[bool, ...]] = (False, False, True)
    se2_invariant: ClassVar[bool] = True
    default_horizon: ClassVar[int] = 15

    def __post_init__(self) -> None:
        _positive(self.name, wheelbase=self.wheelbase, speed=self.speed, dt=self.dt)
        _check_steer(self.name, self.max_steer)
        _check_num_actions(self.name, self.num_actions)
        _check_grid(self)

    @property
    def state_dim(self) -> int:
        return 3

    def action_set(self, dtype: torch.dtype = torch.float32, device: torch.device | str | None = None) -> Tensor:
        """``[A, 1]`` steering angles, evenly in ``[-max_steer, max_steer]``."""
        return _evenly(-self.max_steer, self.max_steer, self.num_actions).to(dtype=dtype, device=device).unsqueeze(1)

    def step(self, x: Tensor, u: Tensor) -> Tensor:
        """``x [N, 3]``, ``u [N, 1]`` -> ``[N, 3]``: heading first, then position with the new heading."""
        _check_step_inputs(self, x, u, 1)
        yaw_rate = self.speed * torch.tan(u[:, 0]) / self.wheelbase  # [N]
        theta = wrap_angle(x[:, 2] + yaw_rate * self.dt)
        return _advance(x, theta, self.speed * torch.cos(theta) * self.dt, self.speed * torch.sin(theta) * self.dt)

    def params(self) -> dict[str, Any]:
        return _params(self)


@dataclass(frozen=True)
class KinematicSingleTrackSpeed:
    """Kinematic single-track model with the speed as a state: ``(x, y, theta, v)``, actions ``(delta, a)``.

    The action set is the product grid of ``num_steer`` steering angles evenly in ``[-max_steer, max_steer]``
    and ``num_accel`` accelerations evenly in ``[-max_accel, max_accel]``: ``A = num_steer * num_accel`` rows
    ``(delta, a)``, steering-major (row ``i * num_accel + j`` is steering i, acceleration j). Stepped speed
    first: ``v' = clip(v + a dt, min_speed, max_speed)``, ``theta' = wrap(theta + v' tan(delta) / L dt)``,
    ``x' = x + v' cos(theta') dt``, ``y' = y + v' sin(theta') dt``. SE(2)-invariant: a change of frame moves
    ``(x, y, theta)`` and leaves ``v`` as it is.

    Tables are built from the zero state, so a ``ks_speed`` table describes trajectories that start at rest.

    Defaults (the preset ``ks_speed``, a deliberately small resolution so that a 4-D table builds in seconds):
    wheelbase 0.324 m, dt = 0.2 s, 5 steering angles in [-pi/6, pi/6], 3 accelerations in [-1, 1] m/s^2 (15
    actions), speed in [0, 1] m/s, cells 0.1 m x 0.1 m x 10 deg (2 pi / 36) x 0.2 m/s, horizon 10. Speeds move
    by whole multiples of 0.2 m/s, so they stay at the centres of the speed cells.
    """

    wheelbase: float = 0.324
    """distance L between the axles (m)"""
    dt: float = 0.2
    """time step (s)"""
    max_steer: float = math.pi / 6
    """steering angles are ``num_steer`` values evenly in ``[-max_steer, max_steer]`` (rad, < pi/2)"""
    num_steer: int = 5
    """number of steering angles"""
    max_accel: float = 1.0
    """accelerations are ``num_accel`` values evenly in ``[-max_accel, max_accel]`` (m/s^2)"""
    num_accel: int = 3
    """number of accelerations"""
    min_speed: float = 0.0
    """the speed is clipped to ``[min_speed, max_speed]`` (m/s); 0 means no reversing"""
    max_speed: float = 1.0
    """largest speed (m/s)"""
    cell_size: tuple[float, ...] = (0.1, 0.1, 2.0 * math.pi / 36, 0.2)
    """grid cell size (m, m, rad, m/s); the angle size must be 2*pi/K"""
    cell_offset: tuple[float, ...] = (0.0, 0.0, 0.01, 0.0)
    """grid offset in cells (|offset| < 0.5)"""

    name: ClassVar[str] = "ks_speed"
    periodic: ClassVar[tuple[bool, ...]] = (False, False, True, False)
    se2_invariant: ClassVar[bool] = True
    default_horizon: ClassVar[int] = 10

    def __post_init__(self) -> None:
        _positive(self.name, wheelbase=self.wheelbase, dt=self.dt)
        _check_steer(self.name, self.max_steer)
        _non_negative(self.name, max_accel=self.max_accel)
        _check_num_actions(self.name, self.num_steer)
        _check_num_actions(self.name, self.num_accel)
        _check_num_actions(self.name, self.num_steer * self.num_accel)
        for key in ("min_speed", "max_speed"):
            value = getattr(self, key)
            if not (isinstance(value, (int, float)) and math.isfinite(value)):
                raise ValueError(f"{self.name}: {key} must be a finite number, got {value!r}")
        if not self.min_speed <= 0.0 <= self.max_speed or self.min_speed == self.max_speed:
            raise ValueError(f"{self.name}: need min_speed <= 0 <= max_speed (tables start at rest) and "
                             f"min_speed < max_speed, got [{self.min_speed}, {self.max_speed}]")
        _check_grid(self)

    @property
    def state_dim(self) -> int:
        return 4

    def action_set(self, dtype: torch.dtype = torch.float32, device: torch.device | str | None = None) -> Tensor:
        """``[num_steer * num_accel, 2]`` rows ``(steering angle, acceleration)``, steering-major."""
        steer = _evenly(-self.max_steer, self.max_steer, self.num_steer)
        accel = _evenly(-self.max_accel, self.max_accel, self.num_accel)
        grid = torch.stack(torch.meshgrid(steer, accel, indexing="ij"), dim=-1).reshape(-1, 2)  # [A, 2]
        return grid.to(dtype=dtype, device=device)

    def step(self, x: Tensor, u: Tensor) -> Tensor:
        """``x [N, 4]``, ``u [N, 2]`` -> ``[N, 4]``: speed, then heading, then position."""
        _check_step_inputs(self, x, u, 2)
        v = torch.clamp(x[:, 3] + u[:, 1] * self.dt, self.min_speed, self.max_speed)  # [N]
        theta = wrap_angle(x[:, 2] + v * torch.tan(u[:, 0]) / self.wheelbase * self.dt)
        return _advance(x, theta, v * torch.cos(theta) * self.dt, v * torch.sin(theta) * self.dt, v)

    def params(self) -> dict[str, Any]:
        return _params(self)


def _params(system: Any) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for f in dataclasses.fields(system):
        value = getattr(system, f.name)
        out[f.name] = list(value) if isinstance(value, tuple) else value
    return out


# ----------------------------------------------------------------------------------------------- registry

class UnknownSystemError(ValueError):
    """A system name that is not registered (a file's system is rebuilt only from the registry or a trusted factory)."""


_REGISTRY: dict[str, Callable[..., System]] = {}
_BUILTIN_MODULE = __name__


def register_system(name: str, factory: Callable[..., System], *, overwrite: bool = False) -> None:
    """Register ``factory(**params) -> System`` under ``name`` (for ``--system NAME`` and table files).

    ``factory`` is usually the system's class (a dataclass: its fields become the build's flags) or a function
    with keyword arguments. Define it at the top level of an importable module, so tables can name it
    (``"module:qualname"``) and be read in a fresh process. Registering another factory under a taken name is
    an error unless ``overwrite=True``, or unless it comes from the same definition (same module and qualified
    name: a re-run script or notebook cell, a reloaded module), which replaces the old one.
    """
    if not name or not isinstance(name, str):
        raise ValueError(f"a system name must be a non-empty string, got {name!r}")
    if ":" in name:
        raise ValueError(f"a system name must not contain ':' (that marks a module:factory path), got {name!r}")
    if not callable(factory):
        raise ValueError(f"the factory of system {name!r} must be callable, got {type(factory).__name__}")
    old = _REGISTRY.get(name)
    if old is not None and not overwrite and old is not factory and not _same_definition(old, factory):
        raise ValueError(f"a system named {name!r} is already registered; pass overwrite=True to replace it")
    _REGISTRY[name] = factory


def _same_definition(a: Any, b: Any) -> bool:
    """Two objects from the same definition (a re-run notebook cell or script, a reloaded module)."""
    key = lambda f: (getattr(f, "__module__", None), getattr(f, "__qualname__", None))  # noqa: E731
    return key(a) == key(b) and key(a)[1] is not None


def known_systems() -> list[str]:
    """Names of the registered systems, sorted."""
    return sorted(_REGISTRY)


def make_system(name: str, **params: Any) -> System:
    """Build a registered system by name and check it (:func:`check_system`); unknown names and parameters
    are clear errors."""
    if not isinstance(name, str) or name not in _REGISTRY:
        raise UnknownSystemError(f"unknown system {name!r}; known systems: {', '.join(known_systems())}")
    return _build(name, _REGISTRY[name], params)


def _check_params(name: str, factory: Callable[..., Any], params: dict[str, Any]) -> None:
    """Refuse ``params`` that ``factory`` does not take, before it is called (ValueError naming them)."""
    if dataclasses.is_dataclass(factory):
        valid = {f.name for f in dataclasses.fields(factory) if f.init}
        unknown = sorted(set(params) - valid)
        if unknown:
            raise ValueError(
                f"system {name!r} has no parameter(s) {', '.join(unknown)}; its parameters: {', '.join(sorted(valid))}"
            )
    try:
        signature = inspect.signature(factory)
    except (TypeError, ValueError):  # a builtin without a signature: nothing to bind against
        raise ValueError(f"system {name!r}: its factory {factory!r} has no inspectable signature") from None
    try:
        signature.bind(**params)
    except TypeError as exc:
        raise ValueError(f"system {name!r}: its factory does not accept {sorted(params)} ({exc})") from None


def _build(name: str, factory: Callable[..., Any], params: dict[str, Any]) -> System:
    """``factory(**params)`` once the parameters bind, checked to be a valid System named ``name``."""
    _check_params(name, factory, params)
    try:
        system = factory(**params)
    except TypeError as exc:  # a function factory that rejects a value's type
        raise ValueError(f"system {name!r}: its factory does not accept {sorted(params)} ({exc})") from None
    check_system(system)
    if system.name != name:
        raise ValueError(f"the factory registered as {name!r} built a system named {system.name!r}; "
                         "register it under the system's own name")
    return system


def system_horizon(system: Any) -> int:
    """The system's ``default_horizon`` when it has one, else :data:`DEFAULT_HORIZON`."""
    horizon = getattr(system, "default_horizon", None)
    if horizon is None:
        return DEFAULT_HORIZON
    if isinstance(horizon, bool) or not isinstance(horizon, int) or horizon < 1:
        raise ValueError(f"{getattr(system, 'name', system)!r}: default_horizon must be a positive integer, got {horizon!r}")
    return horizon


# -------------------------------------------------------------------------------------- checking a system

def check_system(system: Any) -> None:
    """Raise ValueError naming what a (user) system lacks or gets wrong; a no-op for a good one.

    Checks the attributes of :class:`System`, the grid (sizes, offsets, angle cells of ``2 pi / K``), the action
    set (a finite float ``[A, q]``), the SE(2) contract (``x, y, theta`` first, ``theta`` an angle), that ``step``
    maps ``[2, d]`` zeros to ``[2, d]`` in the same dtype, and that ``params()`` is JSON-serializable.
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
    _positive(who, dt=system.dt)
    try:
        sizes = _as_float_tuple(system.cell_size, d, "cell_size", who)
        offsets = _as_float_tuple(system.cell_offset, d, "cell_offset", who)
        Grid(sizes, periodic, offsets)
    except ValueError as exc:
        raise ValueError(f"{who}: bad grid: {exc}") from None
    for i, p in enumerate(periodic):
        if p:
            k = 2.0 * math.pi / sizes[i]
            if abs(k - round(k)) > 1e-6 * k:
                raise ValueError(f"{who}: the angle cell size of dimension {i} must be 2*pi/K for an integer K, "
                                 f"got {sizes[i]} (2*pi/{k:.4f})")
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
    SE(2)-invariant system; order 1 for one that is not.
    """
    from .frames import se2_to_world

    d = len(system.periodic)
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


# ---------------------------------------------------------------------------- factories by module path

def factory_path(factory: Any) -> str | None:
    """``"module:qualname"`` of a factory that a fresh process can import, else None (``__main__``, a lambda,
    a class defined inside a function, ...)."""
    module = getattr(factory, "__module__", None)
    qualname = getattr(factory, "__qualname__", None)
    if not module or not qualname or module in ("__main__", "builtins") or "<" in qualname:
        return None
    path = f"{module}:{qualname}"
    try:
        resolved = load_factory(path)
    except ValueError:
        return None
    return path if resolved is factory else None


def load_factory(path: str) -> Callable[..., System]:
    """Import ``"package.module:Name"`` (``Name`` may be dotted) and return the callable it names."""
    if not isinstance(path, str) or path.count(":") != 1:
        raise ValueError(f"a factory path must look like 'package.module:Name', got {path!r}")
    module_name, qualname = path.split(":")
    if not module_name or not qualname:
        raise ValueError(f"a factory path must look like 'package.module:Name', got {path!r}")
    try:
        obj: Any = importlib.import_module(module_name)
    except ImportError as exc:
        raise ValueError(f"cannot import module {module_name!r} of factory {path!r} ({type(exc).__name__}: {exc})") from None
    for part in qualname.split("."):
        if not hasattr(obj, part):
            raise ValueError(f"module {module_name!r} has no {qualname!r} (factory {path!r})")
        obj = getattr(obj, part)
    if not callable(obj):
        raise ValueError(f"factory {path!r} is not callable ({type(obj).__name__})")
    return obj


def import_system_modules(modules: list[str] | tuple[str, ...]) -> None:
    """Import each user module that registers systems (``--system-module``): the caller typed these names, so
    importing them is the caller's decision, never a file's. ValueError naming the module that fails."""
    for module in modules:
        if not isinstance(module, str) or not module or ":" in module:
            raise ValueError(f"--system-module {module!r}: give a module name such as my_robots")
        try:
            importlib.import_module(module)
        except ImportError as exc:
            raise ValueError(f"--system-module {module}: cannot import it ({type(exc).__name__}: {exc})") from None


def resolve_system(spec: str) -> str:
    """The registry name of ``spec``: a registered name, or ``"module:factory"`` that the caller typed (imported,
    built with its defaults and checked, then registered under the built system's name). Returns the name."""
    if not isinstance(spec, str) or not spec:
        raise UnknownSystemError(f"a system must be a name or 'module:factory', got {spec!r}")
    if ":" not in spec:
        if spec not in _REGISTRY:
            raise UnknownSystemError(f"unknown system {spec!r}; known systems: {', '.join(known_systems())} "
                                     "(a user system: --system-module MODULE, or --system module:factory)")
        return spec
    factory = load_factory(spec)
    name = _trusted_name(spec, factory)
    if _REGISTRY.get(name) is not factory:
        register_system(name, factory)
    return name


def _trusted_name(spec: str, factory: Callable[..., Any]) -> str:
    """The name of the system ``factory`` builds with its defaults; ValueError if it builds no valid System."""
    _check_params(spec, factory, {})
    try:
        system = factory()
    except Exception as exc:  # the caller named this factory; whatever it raises is theirs to see, in one line
        raise ValueError(f"factory {spec!r} did not build a system with its defaults ({type(exc).__name__}: {exc})") from None
    name = getattr(system, "name", None)
    if not isinstance(name, str):
        raise ValueError(f"factory {spec!r} built a {type(system).__name__}, not a System (it has no name; "
                         "see cuniform_torch.systems.System)")
    check_system(system)
    return name


# ------------------------------------------------------------------------------------------- system JSON

def system_to_json(system: System, horizon: int) -> str:
    """The table's system JSON: ``{"name", "params", "dt", "horizon"}``, plus ``"factory"``
    (``"module:qualname"``) for a system defined outside this module whose factory a fresh process can import
    (keys sorted, deterministic)."""
    spec: dict[str, Any] = {"name": system.name, "params": system.params(), "dt": float(system.dt),
                            "horizon": int(horizon)}
    factory = _REGISTRY.get(system.name, type(system))
    if getattr(factory, "__module__", _BUILTIN_MODULE) != _BUILTIN_MODULE:
        path = factory_path(factory)
        if path is not None:
            spec["factory"] = path
    return json.dumps(spec, sort_keys=True)


_MAX_SYSTEM_JSON = 1 << 20  # characters; a system JSON is a few hundred


def system_from_json(text: str, *, trust_factory: str | Callable[..., Any] | None = None) -> tuple[System, int]:
    """Rebuild ``(system, horizon)`` from a table's or checkpoint's system JSON.

    Nothing the JSON names is imported or called: the system comes from the registry, or from ``trust_factory``
    (a ``"module:factory"`` path or the factory itself) that the caller names. The JSON's ``factory`` string is
    only compared with it. A trusted factory is registered under the system's name once it has built a valid
    system from the JSON's parameters. :class:`UnknownSystemError` says what to pass when the name is unknown.
    """
    if not isinstance(text, str) or len(text) > _MAX_SYSTEM_JSON:
        raise ValueError(f"system JSON must be a string of at most {_MAX_SYSTEM_JSON} characters")
    try:
        spec = json.loads(text)
    except (json.JSONDecodeError, RecursionError) as exc:
        raise ValueError(f"system JSON does not parse: {exc}") from None
    if not isinstance(spec, dict) or not {"name", "params", "horizon"} <= set(spec):
        raise ValueError(f"system JSON must be an object with name, params and horizon; got {text[:200]!r}")
    name, params, horizon = spec["name"], spec["params"], spec["horizon"]
    if not isinstance(name, str) or not name or ":" in name:
        raise ValueError(f"system JSON: name must be a system name (a non-empty string without ':'), got {name!r}")
    if not isinstance(params, dict):
        raise ValueError(f"system JSON: params must be an object of constructor arguments, got {params!r}")
    if isinstance(horizon, bool) or not isinstance(horizon, int) or not 1 <= horizon <= MAX_HORIZON:
        raise ValueError(f"system JSON: horizon must be a positive integer (at most {MAX_HORIZON}), got {horizon!r}")
    named = spec.get("factory")
    if named is not None and not isinstance(named, str):
        raise ValueError(f"system JSON: factory must be a 'module:factory' string, got {named!r}")
    if trust_factory is None:
        if name not in _REGISTRY:
            raise UnknownSystemError(_unknown_message(name, named))
        return make_system(name, **params), horizon
    factory = load_factory(trust_factory) if isinstance(trust_factory, str) else trust_factory
    if not callable(factory):
        raise ValueError(f"trust_factory must be a 'module:factory' path or a callable, got {trust_factory!r}")
    trusted = trust_factory if isinstance(trust_factory, str) else _definition_path(factory)
    if named is not None and trusted is not None and named != trusted:
        raise UnknownSystemError(f"system {name!r}: the file names factory {named!r}, not the trusted {trusted!r}")
    registered = _REGISTRY.get(name)
    if registered is not None and registered is not factory and not _same_definition(registered, factory):
        raise ValueError(f"system {name!r} is registered with another factory than the trusted {trusted or factory!r}")
    system = _build(name, factory, params)
    if registered is None:
        register_system(name, factory)
    return system, horizon


def _definition_path(factory: Any) -> str | None:
    module, qualname = getattr(factory, "__module__", None), getattr(factory, "__qualname__", None)
    return f"{module}:{qualname}" if module and qualname else None


def _unknown_message(name: str, named: str | None) -> str:
    module = named.split(":")[0] if named else "MODULE"
    where = f"; the file names factory {named!r}" if named else ""
    return (f"unknown system {name!r} (known: {', '.join(known_systems())}){where}. Reading a file never imports "
            f"code it names: register the system first (import the module that calls register_system({name!r}, "
            f"factory)), pass trust_factory={named or 'module:factory'!r}, or on the command line "
            f"--system-module {module}")


register_system(RandomWalk1D.name, RandomWalk1D)
register_system(Dubins.name, Dubins)
register_system(KinematicSingleTrack.name, KinematicSingleTrack)
register_system(KinematicSingleTrackSpeed.name, KinematicSingleTrackSpeed)
