"""Discs that move at constant velocity: positions a pure function of time.

Shapes used in this module: M discs, ``...`` any batch shape of query points (e.g. ``[N, T]``).

Disc ``m`` is at ``start[m] + velocity[m] * t`` at time ``t`` (s), for every ``t`` (negative ones too): no bounces,
no stops. Because the position is a pure function of time, the simulator's collision check at a step's time and a
cost's prediction along a rollout's steps use the same numbers (:class:`~cuniform_torch.envs.Environment` holds
the discs in its ``moving`` field and tests them at the time each point is occupied).

A constant-velocity prediction made at time ``t`` from a disc's position and velocity then is the disc's true
path, so a cost that evaluates these discs at its rollout's step times predicts them exactly; :meth:`MovingDiscs.held`
gives the other model, each disc held still where it is at ``t``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor

__all__ = ["MovingDiscs"]


def _table(value: Any, cols: int | None, what: str) -> Tensor:
    """A finite float64 CPU table ``[M, cols]`` (``[M]`` for ``cols=None``) from ``value``, or one ValueError."""
    try:
        t = torch.as_tensor(value, dtype=torch.float64).detach().cpu()
    except (TypeError, ValueError, RuntimeError):
        raise ValueError(f"MovingDiscs: {what} must be numbers, got {type(value).__name__}") from None
    want = "[M]" if cols is None else f"[M, {cols}]"
    if (cols is None and t.ndim != 1) or (cols is not None and (t.ndim != 2 or t.shape[1] != cols)):
        raise ValueError(f"MovingDiscs: {what} must have shape {want}, got {list(t.shape)}")
    if not bool(torch.isfinite(t).all()):
        raise ValueError(f"MovingDiscs: {what} must be finite, got {t.tolist()}")
    return t.clone()


@dataclass(frozen=True, eq=False)
class MovingDiscs:
    """``M`` closed discs, disc ``m`` centred at ``start[m] + velocity[m] * t`` at time ``t`` (module docstring).

    :param start: ``[M, 2]`` centres at ``t = 0`` (m)
    :param velocity: ``[M, 2]`` velocities (m/s)
    :param radius: ``[M]`` radii (m, > 0)
    """

    start: Tensor
    """float64 ``[M, 2]``: centres at ``t = 0`` (m)"""
    velocity: Tensor
    """float64 ``[M, 2]``: velocities (m/s)"""
    radius: Tensor
    """float64 ``[M]``: radii (m)"""
    _device: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        start = _table(self.start, 2, "start")
        velocity = _table(self.velocity, 2, "velocity")
        radius = _table(self.radius, None, "radius")
        if not start.shape[0] == velocity.shape[0] == radius.shape[0]:
            raise ValueError(f"MovingDiscs: start, velocity and radius must hold one row per disc, got "
                             f"{start.shape[0]}, {velocity.shape[0]} and {radius.shape[0]}")
        if bool((radius <= 0).any()):
            raise ValueError(f"MovingDiscs: every radius must be > 0 (like a Circle's), got {radius.tolist()}")
        object.__setattr__(self, "start", start)
        object.__setattr__(self, "velocity", velocity)
        object.__setattr__(self, "radius", radius)

    def __len__(self) -> int:
        return int(self.start.shape[0])

    def centres(self, t: float | Tensor) -> Tensor:
        """Centres at time ``t``: a number -> float64 ``[M, 2]``; a tensor ``[...]`` -> ``[..., M, 2]`` in its dtype
        and on its device."""
        if isinstance(t, Tensor):
            start, velocity, _ = self._on(t)
            return start + velocity * t[..., None, None]  # [..., M, 2]
        return self.start + self.velocity * _time(t, "MovingDiscs.centres")

    def contains(self, xy: Tensor, t: float | Tensor) -> Tensor:
        """``xy [..., 2]`` occupied at times ``t`` (a number, or a tensor broadcastable to ``[...]``) -> ``bool
        [...]``: inside some disc at that time (closed discs, like :class:`~cuniform_torch.envs.Circle`). Pure
        tensor ops in ``xy``'s dtype and on its device."""
        start, velocity, radius = self._on(xy)
        if start.shape[0] == 0:
            return torch.zeros(xy.shape[:-1], dtype=torch.bool, device=xy.device)
        if isinstance(t, Tensor):
            t = t.to(dtype=xy.dtype)
            tt: Tensor | float = torch.broadcast_to(t, torch.broadcast_shapes(t.shape, xy.shape[:-1]))[..., None]
        else:  # a Python number stays a scalar: no tensor made from it (a copy to the device per call)
            tt = _time(t, "MovingDiscs.contains")
        dx = xy[..., 0, None] - (start[:, 0] + velocity[:, 0] * tt)  # [..., M]
        dy = xy[..., 1, None] - (start[:, 1] + velocity[:, 1] * tt)  # [..., M]
        return (dx * dx + dy * dy <= radius * radius).any(dim=-1)

    def held(self, t: float) -> MovingDiscs:
        """The discs as sensed at time ``t`` and held still there: the same radii, centres :meth:`centres` (t),
        velocity zero (the model that ignores motion)."""
        return MovingDiscs(self.centres(t), torch.zeros_like(self.velocity), self.radius)

    def inflated(self, by: float) -> MovingDiscs:
        """The same motion with every radius grown by ``by`` (m): the discs a point robot of radius ``by`` must
        keep its centre out of."""
        if isinstance(by, bool) or not isinstance(by, (int, float)) or not math.isfinite(by) or by < 0:
            raise ValueError(f"MovingDiscs.inflated: by must be a finite number >= 0, got {by!r}")
        return MovingDiscs(self.start, self.velocity, self.radius + float(by))

    def _on(self, like: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """``start``, ``velocity``, ``radius`` in ``like``'s dtype and on its device, copied once per pair (a copy to
        a GPU per call would wait for it)."""
        key = (like.device, like.dtype)
        hit = self._device.get(key)
        if hit is None:
            hit = self._device[key] = tuple(v.to(device=like.device, dtype=like.dtype)
                                            for v in (self.start, self.velocity, self.radius))
        return hit


def _time(t: Any, who: str) -> float:
    if isinstance(t, bool) or not isinstance(t, (int, float)) or not math.isfinite(t):
        raise ValueError(f"{who}: t must be a finite number (s) or a tensor, got {t!r}")
    return float(t)
