"""Classic control systems that are not SE(2)-invariant (frozen dataclasses satisfying
:class:`~cuniform_torch.systems.System`); a table of one serves one start, a table set serves many.

Shapes: N samples, d = 2 state dimensions, q = 1 action dimension, A actions.

* ``double_integrator``: the 1-D-axis double integrator, state ``(position, velocity)``, action an acceleration
  from ``num_actions`` values evenly in ``[-max_accel, max_accel]``, held for ``dt`` and stepped exactly:
  ``p' = p + v dt + a dt^2 / 2``, ``v' = v + a dt``.
* ``mountain_car``: gymnasium's ``MountainCarContinuous-v0`` dynamics, ``repeat`` env steps per model step with
  the force held; state ``(position, velocity)``, action a force from ``num_actions`` values evenly in
  ``[-1, 1]`` (clipped to ``[-1, 1]`` as the env clips it).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import torch
from torch import Tensor

from cuniform_torch.common.checks import positive, positive_int
from cuniform_torch.systems.models import _check_grid, _check_step_inputs, _evenly, _params
from cuniform_torch.systems.protocol import MAX_ACTIONS

__all__ = ["DoubleIntegrator", "MountainCar", "MOUNTAIN_CAR"]

MOUNTAIN_CAR = {"power": 0.0015, "gravity": 0.0025, "max_speed": 0.07, "min_position": -1.2, "max_position": 0.6,
                "goal_position": 0.45, "max_force": 1.0}
"""the constants of gymnasium's ``Continuous_MountainCarEnv`` (gymnasium/envs/classic_control/continuous_mountain_car.py)"""


@dataclass(frozen=True)
class DoubleIntegrator:
    """The 1-D-axis double integrator: state ``(position, velocity)`` (d = 2), action an acceleration.

    Exact motion under an acceleration held for ``dt``: ``p' = p + v dt + a dt^2 / 2``, ``v' = v + a dt``; no
    limits, no angles, not SE(2)-invariant (tables hold from their build start; a set serves many starts).
    Defaults: dt = 0.2 s, 5 accelerations evenly in [-1, 1] m/s^2, cells 0.02 m x 0.05 m/s, horizon 10. From a
    start at a cell centre the velocities move by whole cells (a dt = 0.1 m/s is 2 cells) and the positions by
    multiples of half a cell, so the position grid is shifted by a quarter cell (``cell_offset``): no position
    sits on a cell boundary, and float32 and float64 agree.
    """

    dt: float = 0.2
    """time step (s)"""
    max_accel: float = 1.0
    """actions are ``num_actions`` accelerations evenly spaced in ``[-max_accel, max_accel]`` (m/s^2)"""
    num_actions: int = 5
    """number of accelerations"""
    cell_size: tuple[float, ...] = (0.02, 0.05)
    """grid cell size (m, m/s)"""
    cell_offset: tuple[float, ...] = (0.25, 0.0)
    """grid offset in cells (|offset| < 0.5)"""

    name: ClassVar[str] = "double_integrator"
    periodic: ClassVar[tuple[bool, ...]] = (False, False)
    se2_invariant: ClassVar[bool] = False
    column_major_ok: ClassVar[bool] = True  # step indexes columns: rollout may pass column-major states
    default_horizon: ClassVar[int] = 10

    def __post_init__(self) -> None:
        positive(self.name, dt=self.dt, max_accel=self.max_accel)
        positive_int(self.name, "num_actions", self.num_actions, at_most=MAX_ACTIONS)
        _check_grid(self)

    @property
    def state_dim(self) -> int:
        return 2

    def action_set(self, dtype: torch.dtype = torch.float32, device: torch.device | str | None = None) -> Tensor:
        """``[A, 1]`` accelerations, evenly in ``[-max_accel, max_accel]`` (computed in float64, then cast)."""
        return _evenly(-self.max_accel, self.max_accel, self.num_actions).to(dtype=dtype, device=device).unsqueeze(1)

    def step(self, x: Tensor, u: Tensor) -> Tensor:
        """``x [N, 2]`` (position, velocity), ``u [N, 1]`` (acceleration) -> ``[N, 2]``."""
        _check_step_inputs(self, x, u, 1)
        p, v, a = x[:, 0], x[:, 1], u[:, 0]
        dt = self.dt
        return torch.stack((p + v * dt + a * (0.5 * dt * dt), v + a * dt), dim=1)

    def params(self) -> dict[str, Any]:
        return _params(self)


@dataclass(frozen=True)
class MountainCar:
    """gymnasium's ``MountainCarContinuous-v0`` as a system: state ``(position, velocity)``, action a force.

    One model step is ``repeat`` env steps with the force held, each exactly the env's
    (:data:`MOUNTAIN_CAR`): ``f = clip(u, -1, 1)``; ``v <- clip(v + f 0.0015 - 0.0025 cos(3 p), -0.07, 0.07)``;
    ``p <- clip(p + v, -1.2, 0.6)``; ``v <- 0`` where ``p`` is at the left wall and ``v < 0``. The env has no
    seconds: ``dt`` is ``repeat`` (env steps per model step). Reaching the goal (``p >= 0.45``) does not stop the
    model; a cost sees it. Not SE(2)-invariant: a table holds from its build start; a table set over (position,
    velocity) serves any state.

    Defaults: ``repeat`` 5 (a horizon of 20 model steps sees 100 env steps), 5 forces evenly in [-1, 1], cells
    0.02 x 0.002 (90 x 70 cells over the env's state box), horizon 20.
    """

    repeat: int = 5
    """env steps per model step, the force held"""
    num_actions: int = 5
    """actions are ``num_actions`` forces evenly spaced in ``[-1, 1]``"""
    cell_size: tuple[float, ...] = (0.02, 0.002)
    """grid cell size (position, velocity)"""
    cell_offset: tuple[float, ...] = (0.0, 0.0)
    """grid offset in cells (|offset| < 0.5)"""

    name: ClassVar[str] = "mountain_car"
    periodic: ClassVar[tuple[bool, ...]] = (False, False)
    se2_invariant: ClassVar[bool] = False
    column_major_ok: ClassVar[bool] = True  # step indexes columns: rollout may pass column-major states
    default_horizon: ClassVar[int] = 20

    def __post_init__(self) -> None:
        positive_int(self.name, "repeat", self.repeat, at_most=1000)
        positive_int(self.name, "num_actions", self.num_actions, at_most=MAX_ACTIONS)
        _check_grid(self)

    @property
    def dt(self) -> float:
        """env steps per model step (the env's unit of time is one step)"""
        return float(self.repeat)

    @property
    def state_dim(self) -> int:
        return 2

    def action_set(self, dtype: torch.dtype = torch.float32, device: torch.device | str | None = None) -> Tensor:
        """``[A, 1]`` forces, evenly in ``[-1, 1]`` (computed in float64, then cast)."""
        top = MOUNTAIN_CAR["max_force"]
        return _evenly(-top, top, self.num_actions).to(dtype=dtype, device=device).unsqueeze(1)

    def step(self, x: Tensor, u: Tensor) -> Tensor:
        """``x [N, 2]`` (position, velocity), ``u [N, 1]`` (force) -> ``[N, 2]`` after ``repeat`` env steps."""
        _check_step_inputs(self, x, u, 1)
        c = MOUNTAIN_CAR
        push = u[:, 0].clamp(-c["max_force"], c["max_force"]) * c["power"]  # [N]
        p, v = x[:, 0], x[:, 1]
        for _ in range(self.repeat):  # a few env steps in sequence, each vectorized over the samples
            v = (v + push - c["gravity"] * torch.cos(3.0 * p)).clamp(-c["max_speed"], c["max_speed"])
            p = (p + v).clamp(c["min_position"], c["max_position"])
            v = torch.where((p <= c["min_position"]) & (v < 0), torch.zeros_like(v), v)  # inelastic left wall
        return torch.stack((p, v), dim=1)

    def params(self) -> dict[str, Any]:
        return _params(self)
