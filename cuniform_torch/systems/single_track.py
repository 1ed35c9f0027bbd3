"""The built-in kinematic single-track (bicycle) models, reference point on the rear axle.

* ``ks``: state ``(x, y, theta)``, fixed speed ``v``, action = steering angle ``delta``; yaw rate
  ``v tan(delta) / L`` (wheelbase ``L``), stepped like ``dubins`` (heading first, then position with the new heading).
* ``ks_speed``: the same model with the speed as a fourth state: ``(x, y, theta, v)``, 2-D actions
  ``(delta, a)`` (steering angle x acceleration, a product grid); ``v' = clip(v + a dt, min_speed,
  max_speed)`` first, then the heading with ``v'``, then the position.

Shapes: N samples, d state dimensions, q action dimensions, A actions.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, ClassVar

import torch
from torch import Tensor

from cuniform_torch.common.checks import finite, non_negative, positive, positive_int, wrap_angle
from cuniform_torch.systems.models import _advance, _check_grid, _check_steer, _check_step_inputs, _evenly, _params
from cuniform_torch.systems.protocol import MAX_ACTIONS

__all__ = ["KinematicSingleTrack", "KinematicSingleTrackSpeed"]


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
    column_major_ok: ClassVar[bool] = True  # step indexes columns: rollout may pass column-major states
    default_horizon: ClassVar[int] = 15

    def __post_init__(self) -> None:
        positive(self.name, wheelbase=self.wheelbase, speed=self.speed, dt=self.dt)
        _check_steer(self.name, self.max_steer)
        positive_int(self.name, "num_actions", self.num_actions, at_most=MAX_ACTIONS)
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
    column_major_ok: ClassVar[bool] = True  # step indexes columns: rollout may pass column-major states
    default_horizon: ClassVar[int] = 10

    def __post_init__(self) -> None:
        positive(self.name, wheelbase=self.wheelbase, dt=self.dt)
        _check_steer(self.name, self.max_steer)
        non_negative(self.name, max_accel=self.max_accel)
        positive_int(self.name, "num_steer", self.num_steer, at_most=MAX_ACTIONS)
        positive_int(self.name, "num_accel", self.num_accel, at_most=MAX_ACTIONS)
        positive_int(self.name, "num_steer * num_accel", self.num_steer * self.num_accel, at_most=MAX_ACTIONS)
        finite(self.name, min_speed=self.min_speed, max_speed=self.max_speed)
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

