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
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from typing import Any, Callable, ClassVar, Protocol, runtime_checkable

import torch
from torch import Tensor

__all__ = [
    "System",
    "RandomWalk1D",
    "Dubins",
    "UnknownSystemError",
    "register_system",
    "make_system",
    "known_systems",
    "system_to_json",
    "system_from_json",
    "wrap_angle",
]


@runtime_checkable
class System(Protocol):
    """What the table builder and the runtime need from a robot model.

    Attributes:
        name: registry name, so a table's system JSON can rebuild the system.
        dt: time step in seconds.
        cell_size: grid cell size per state dimension ``[d]`` (an angle dimension: ``2 pi / K``).
        periodic: which state dimensions are angles in ``[-pi, pi)``.
        cell_offset: grid offset per dimension, in cells (``|offset| < 0.5``); see :mod:`cuniform_torch.grid`.
        se2_invariant: whether dynamics commute with planar rigid motions of ``(x, y, theta)``, so one table
            built at the origin serves any start pose after a change of frame.
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


def _check_num_actions(name: str, num_actions: Any) -> None:
    if isinstance(num_actions, bool) or not isinstance(num_actions, int) or num_actions < 1:
        raise ValueError(f"{name}: num_actions must be a positive integer, got {num_actions!r}")


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
        a = torch.linspace(-self.max_speed, self.max_speed, self.num_actions, dtype=torch.float64)
        if self.num_actions == 1:
            a = torch.zeros(1, dtype=torch.float64)
        return a.to(dtype=dtype, device=device).unsqueeze(1)

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
        if not (isinstance(self.max_omega, (int, float)) and math.isfinite(self.max_omega) and self.max_omega >= 0):
            raise ValueError(f"{self.name}: max_omega must be a non-negative number, got {self.max_omega!r}")
        _check_num_actions(self.name, self.num_actions)
        _check_grid(self)

    @property
    def state_dim(self) -> int:
        return 3

    def action_set(self, dtype: torch.dtype = torch.float32, device: torch.device | str | None = None) -> Tensor:
        """``[A, 1]`` angular velocities, evenly in ``[-max_omega, max_omega]``."""
        w = torch.linspace(-self.max_omega, self.max_omega, self.num_actions, dtype=torch.float64)
        if self.num_actions == 1:
            w = torch.zeros(1, dtype=torch.float64)
        return w.to(dtype=dtype, device=device).unsqueeze(1)

    def step(self, x: Tensor, u: Tensor) -> Tensor:
        """``x [N, 3]``, ``u [N, 1]`` -> ``[N, 3]``: heading first, then position with the new heading."""
        _check_step_inputs(self, x, u, 1)
        theta = wrap_angle(x[:, 2] + u[:, 0] * self.dt)  # [N]
        px = x[:, 0] + self.speed * torch.cos(theta) * self.dt
        py = x[:, 1] + self.speed * torch.sin(theta) * self.dt
        return torch.stack((px, py, theta), dim=1)

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
    """A system name that is not registered."""


_REGISTRY: dict[str, Callable[..., System]] = {}


def register_system(name: str, factory: Callable[..., System], *, overwrite: bool = False) -> None:
    """Register ``factory(**params) -> System`` under ``name`` (for ``--system NAME`` and table files)."""
    if not name or not isinstance(name, str):
        raise ValueError(f"a system name must be a non-empty string, got {name!r}")
    if name in _REGISTRY and not overwrite and _REGISTRY[name] is not factory:
        raise ValueError(f"a system named {name!r} is already registered; pass overwrite=True to replace it")
    _REGISTRY[name] = factory


def known_systems() -> list[str]:
    """Names of the registered systems, sorted."""
    return sorted(_REGISTRY)


def make_system(name: str, **params: Any) -> System:
    """Build a registered system by name; unknown names and parameters are clear errors."""
    if not isinstance(name, str) or name not in _REGISTRY:
        raise UnknownSystemError(f"unknown system {name!r}; known systems: {', '.join(known_systems())}")
    factory = _REGISTRY[name]
    if dataclasses.is_dataclass(factory):
        valid = {f.name for f in dataclasses.fields(factory)}
        unknown = sorted(set(params) - valid)
        if unknown:
            raise ValueError(
                f"system {name!r} has no parameter(s) {', '.join(unknown)}; its parameters: {', '.join(sorted(valid))}"
            )
    return factory(**params)


def system_to_json(system: System, horizon: int) -> str:
    """The table's system JSON: ``{"name", "params", "dt", "horizon"}`` (keys sorted, deterministic)."""
    return json.dumps(
        {"name": system.name, "params": system.params(), "dt": float(system.dt), "horizon": int(horizon)},
        sort_keys=True,
    )


def system_from_json(text: str) -> tuple[System, int]:
    """Rebuild ``(system, horizon)`` from a table's system JSON."""
    try:
        spec = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ValueError(f"system JSON does not parse: {exc}") from None
    if not isinstance(spec, dict) or not {"name", "params", "horizon"} <= set(spec):
        raise ValueError(f"system JSON must be an object with name, params and horizon; got {text[:200]!r}")
    if not isinstance(spec["name"], str):
        raise ValueError(f"system JSON: name must be a string, got {spec['name']!r}")
    if not isinstance(spec["params"], dict):
        raise ValueError(f"system JSON: params must be an object of constructor arguments, got {spec['params']!r}")
    system = make_system(spec["name"], **spec["params"])
    horizon = spec["horizon"]
    if isinstance(horizon, bool) or not isinstance(horizon, int) or horizon < 1:
        raise ValueError(f"system JSON: horizon must be a positive integer, got {horizon!r}")
    return system, horizon


register_system(RandomWalk1D.name, RandomWalk1D)
register_system(Dubins.name, Dubins)
