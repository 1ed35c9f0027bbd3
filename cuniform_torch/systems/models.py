"""The built-in planar systems (frozen dataclasses satisfying :class:`~cuniform_torch.systems.System`) and the
helpers every built-in shares; the single-track models are in :mod:`.single_track`, the classic control systems in
:mod:`.classic`.

Shapes: N samples, d state dimensions, q action dimensions, A actions.

* ``random_walk_1d``: ``x' = x + u dt`` with ``num_actions`` speeds evenly in ``[-max_speed, max_speed]``.
* ``dubins``: state ``(x, y, theta)``, fixed speed ``v``, action = angular velocity ``omega``; stepped as the
  paper's reference release does: ``theta' = wrap(theta + omega dt)`` first, then
  ``x' = x + v cos(theta') dt``, ``y' = y + v sin(theta') dt``.

Each model checks its arguments in ``__post_init__`` (:mod:`cuniform_torch.common.checks`) and normalizes its grid
(:func:`~cuniform_torch.grid.cells.check_grid`: an angle cell size typed as ``0.1571`` becomes exactly ``2 pi / 40``).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass
from typing import Any, ClassVar

import torch
from torch import Tensor

from cuniform_torch.common.checks import non_negative, positive, positive_int
from cuniform_torch.grid.cells import check_grid
from cuniform_torch.systems.protocol import MAX_ACTIONS

__all__ = ["RandomWalk1D", "Dubins"]


def _check_grid(system: Any) -> None:
    """Validate and normalize ``cell_size`` / ``cell_offset`` of a frozen dataclass system in place."""
    sizes, offsets = check_grid(system.cell_size, system.periodic, system.cell_offset, system.name)
    object.__setattr__(system, "cell_size", sizes)
    object.__setattr__(system, "cell_offset", offsets)


def _check_steer(name: str, max_steer: Any) -> None:
    non_negative(name, max_steer=max_steer)
    if max_steer >= math.pi / 2:
        raise ValueError(f"{name}: max_steer must be below pi/2 (tan diverges), got {max_steer!r}")


def _check_step_inputs(system: Any, x: Tensor, u: Tensor, q: int) -> None:
    d = len(system.periodic)
    if x.ndim != 2 or x.shape[1] != d:
        raise ValueError(f"{system.name}.step: x must have shape [N, {d}], got {list(x.shape)}")
    if u.ndim != 2 or u.shape[1] != q or u.shape[0] != x.shape[0]:
        raise ValueError(f"{system.name}.step: u must have shape [{x.shape[0]}, {q}], got {list(u.shape)}")


def _advance(x: Tensor, theta: Tensor, dx: Tensor, dy: Tensor, *rest: Tensor) -> Tensor:
    """The next planar state ``[N, 3 + len(rest)]``: ``(x + dx, y + dy, theta, *rest)`` from ``[N]`` columns.

    Written column by column into one new tensor: on a CPU, ``torch.stack`` of ``[N]`` columns along dim 1 costs
    about as much as the rest of a Dubins step. The values are those of ``torch.stack((x[:, 0] + dx, ...))``.
    The new state keeps the layout of ``x``: a column-major ``x`` (what :func:`~cuniform_torch.sampling.rollout.rollout`
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


@functools.lru_cache(maxsize=256)
def _scalars(dtype: torch.dtype, *values: float) -> tuple[Tensor | float, ...]:
    """``values`` as 0-d CPU tensors of ``dtype`` (float32 or float64; else the floats themselves).

    A Python float in a tensor op is wrapped into a new tensor and cast on every call (about 3 us a time on a CPU,
    more than the arithmetic of a 1000-state op); a 0-d CPU tensor of the op's dtype is read as the same scalar
    (the kernel rounds the float to the dtype either way: the results are bit-identical) and works on any device.
    Other dtypes keep the floats: a half op computes with the float scalar in float32, a 0-d half would round it.
    """
    if dtype not in (torch.float32, torch.float64):
        return values
    return tuple(torch.tensor(v, dtype=dtype) for v in values)


def _next_state(x: Tensor, u: Tensor, d: int, out: Tensor | None) -> tuple[Tensor, Tensor, bool]:
    """Where the next state ``[N, d]`` goes and where its new heading is computed.

    The state: ``out`` when given (checked: ``[N, d]``, the dtype of ``x`` and ``u`` promoted, their device), else
    a new one in that dtype and the layout of ``x`` (column-major when ``x`` is, as :func:`_advance` makes it).
    The heading: its column ``[N]`` when that is contiguous, else a new ``[N]`` (a strided heading would take
    torch's scalar cos/sin loop, which may round differently from the vectorized one); and whether it is apart."""
    dtype = torch.promote_types(x.dtype, u.dtype)
    n = x.shape[0]
    if out is not None:
        if out.shape != (n, d) or out.dtype != dtype or out.device != x.device:
            raise ValueError(f"step: out must be a [{n}, {d}] tensor of {dtype} on {x.device}, got "
                             f"{list(out.shape)} {out.dtype} on {out.device}")
    elif x.shape[1] == d and x.stride(0) == 1 and n > 1:  # column-major: [d, N] storage
        out = torch.empty((d, n), dtype=dtype, device=x.device).T
    else:
        out = torch.empty((n, d), dtype=dtype, device=x.device)
    heading = out[:, 2]
    if heading.is_contiguous():
        return out, heading, False
    return out, torch.empty(n, dtype=dtype, device=x.device), True


def _turn(x: Tensor, rate: Tensor, dt: float, theta: Tensor) -> Tensor:
    """The new heading ``wrap(theta + rate dt)`` (:func:`~cuniform_torch.common.checks.wrap_angle`'s arithmetic, in
    place): ``x [N, d]`` (heading in column 2), ``rate [N]`` -> ``theta [N]``, also returned."""
    c_dt, c_pi, c_two_pi = _scalars(theta.dtype, dt, math.pi, 2.0 * math.pi)
    torch.mul(rate, c_dt, out=theta)
    theta.add_(x[:, 2]).add_(c_pi)  # (theta + rate dt) + pi, as wrap_angle adds them
    return torch.remainder(theta, c_two_pi, out=theta).sub_(c_pi)


def _move(x: Tensor, theta: Tensor, speed: float | Tensor, dt: float, out: Tensor, apart: bool) -> Tensor:
    """``out[:, :2] = (x + (speed cos(theta)) dt, y + (speed sin(theta)) dt)``, the rest of ``out`` as it is
    (``speed`` a float or an ``[N]`` tensor): the products rounded as ``speed * torch.cos(theta) * dt`` rounds
    them (a speed of exactly 1 is skipped: multiplying by it is exact), both columns in each op; ``theta`` copied
    into ``out[:, 2]`` when it was computed ``apart`` (:func:`_next_state`). Returns ``out``."""
    trig = torch.empty((2, theta.shape[0]), dtype=out.dtype, device=out.device)  # [2, N]: cos, sin
    cos, sin = trig.unbind(0)
    torch.cos(theta, out=cos)
    torch.sin(theta, out=sin)
    if isinstance(speed, Tensor):
        trig.mul_(speed)  # speed [N] broadcast over both rows
    elif speed != 1.0:
        trig.mul_(_scalars(out.dtype, speed)[0])
    torch.add(x[:, :2], trig.mul_(_scalars(out.dtype, dt)[0]).T, out=out[:, :2])
    if apart:
        out[:, 2] = theta
    return out


def _evenly(low: float, high: float, num: int) -> Tensor:
    """``num`` values evenly in ``[low, high]`` (float64; one value: their midpoint)."""
    if num == 1:
        return torch.tensor([(low + high) / 2.0], dtype=torch.float64)
    return torch.linspace(low, high, num, dtype=torch.float64)


def _params(system: Any) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for f in dataclasses.fields(system):
        value = getattr(system, f.name)
        out[f.name] = list(value) if isinstance(value, tuple) else value
    return out



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
    column_major_ok: ClassVar[bool] = True  # step indexes columns: rollout may pass column-major states

    def __post_init__(self) -> None:
        positive(self.name, dt=self.dt, max_speed=self.max_speed)
        positive_int(self.name, "num_actions", self.num_actions, at_most=MAX_ACTIONS)
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
    column_major_ok: ClassVar[bool] = True  # step indexes columns: rollout may pass column-major states
    step_out: ClassVar[bool] = True
    """``step`` takes ``out=`` (a rollout steps into its preallocated states)"""

    def __post_init__(self) -> None:
        positive(self.name, speed=self.speed, dt=self.dt)
        non_negative(self.name, max_omega=self.max_omega)
        positive_int(self.name, "num_actions", self.num_actions, at_most=MAX_ACTIONS)
        _check_grid(self)

    @property
    def state_dim(self) -> int:
        return 3

    def action_set(self, dtype: torch.dtype = torch.float32, device: torch.device | str | None = None) -> Tensor:
        """``[A, 1]`` angular velocities, evenly in ``[-max_omega, max_omega]``."""
        return _evenly(-self.max_omega, self.max_omega, self.num_actions).to(dtype=dtype, device=device).unsqueeze(1)

    def step(self, x: Tensor, u: Tensor, out: Tensor | None = None) -> Tensor:
        """``x [N, 3]``, ``u [N, 1]`` -> ``[N, 3]``: heading first, then position with the new heading.

        ``out`` (optional, ``[N, 3]`` of the result's dtype and device, not overlapping ``x`` or ``u``): written and
        returned (what :func:`~cuniform_torch.sampling.rollout.rollout` passes: a row of its preallocated states)."""
        _check_step_inputs(self, x, u, 1)
        # wrap_angle(x[:, 2] + u[:, 0] * dt), then x + speed cos(theta') dt, ...: the same arithmetic in place into the
        # new state (a dozen ops, no Python float wrapped per op); the values of _advance(x, theta, ...)
        out, theta, apart = _next_state(x, u, 3, out)  # [N, 3], [N]
        return _move(x, _turn(x, u[:, 0], self.dt, theta), self.speed, self.dt, out, apart)

    def scan(self, start: Tensor, actions: Tensor) -> Tensor:
        """The states of ``step`` applied along open-loop ``actions [N, T, 1]`` from ``start [N, 3]``, in closed
        form: ``[N, T+1, 3]`` (start included), equal to the step loop's to float rounding.

        Headings are the running sum of ``rate dt`` (wrapped once, not per step) and positions the running sum of
        ``speed (cos, sin)(heading) dt``: about a dozen tensor ops for any horizon instead of nine per step, which
        is what a GPU, where every op is a kernel launch, needs (:func:`~cuniform_torch.sampling.rollout.open_loop`
        uses it off the CPU)."""
        c_dt, c_pi, c_two_pi = _scalars(actions.dtype, self.dt, math.pi, 2.0 * math.pi)
        heading = torch.cumsum(actions[:, :, 0] * c_dt, dim=1).add_(start[:, 2:3])  # [N, T], unwrapped
        heading = torch.remainder(heading.add_(c_pi), c_two_pi).sub_(c_pi)  # wrap_angle's arithmetic
        states = actions.new_empty((actions.shape[0], actions.shape[1] + 1, 3))  # [N, T+1, 3]
        states[:, 0] = start
        states[:, 1:, 2] = heading
        trig = torch.stack((torch.cos(heading), torch.sin(heading)), dim=2)  # [N, T, 2]
        trig.mul_(_scalars(actions.dtype, self.speed)[0]).mul_(c_dt)  # rounded as speed * cos * dt
        torch.cumsum(trig, dim=1, out=states[:, 1:, :2]).add_(start[:, None, :2])
        return states

    def params(self) -> dict[str, Any]:
        return _params(self)
