"""The environment: obstacles (anything with ``contains`` and ``appear_time``) and optional workspace bounds.

:meth:`Environment.in_collision` with ``time=None`` is the physical truth; with a time it is what the robot
knows then (an obstacle is sensed from its ``appear_time`` on).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch
from torch import Tensor

from cuniform_torch.envs.shapes import _appear_time, _check_xy

__all__ = ["Environment"]


@dataclass
class Environment:
    """Obstacles and optional workspace bounds.

    ``bounds = (xmin, ymin, xmax, ymax)``: points outside (strictly) count as collisions.
    """

    obstacles: list = field(default_factory=list)
    """objects with ``contains(xy [..., 2]) -> bool [...]`` and ``appear_time`` (see :class:`Obstacle`)"""
    bounds: tuple[float, float, float, float] | None = None
    """(xmin, ymin, xmax, ymax) of the workspace, or None for an unbounded plane"""

    def __post_init__(self) -> None:
        if isinstance(self.obstacles, (str, bytes)) or not isinstance(self.obstacles, (list, tuple)):
            raise ValueError(f"Environment: obstacles must be a list, got {type(self.obstacles).__name__}")
        self.obstacles = list(self.obstacles)
        for k, obs in enumerate(self.obstacles):
            if not callable(getattr(obs, "contains", None)) or not hasattr(obs, "appear_time"):
                raise ValueError(
                    f"Environment: obstacle {k} ({type(obs).__name__}) needs a contains(xy) method and an appear_time"
                )
            _appear_time(obs.appear_time, f"Environment: obstacle {k}")
        if self.bounds is not None:
            try:
                b = tuple(float(v) for v in self.bounds)
            except (TypeError, ValueError):
                raise ValueError(f"Environment: bounds must be (xmin, ymin, xmax, ymax), got {self.bounds!r}") from None
            if len(b) != 4 or not all(math.isfinite(v) for v in b):
                raise ValueError(
                    f"Environment: bounds must be 4 finite numbers (xmin, ymin, xmax, ymax), got {self.bounds!r}"
                )
            if not (b[0] < b[2] and b[1] < b[3]):
                raise ValueError(f"Environment: bounds need xmin < xmax and ymin < ymax, got {b}")
            self.bounds = b  # type: ignore[assignment]

    def visible(self, time: float | None = None) -> list:
        """The obstacles sensed at ``time`` (``appear_time <= time``); all of them for ``time=None``."""
        if time is None:
            return list(self.obstacles)
        if isinstance(time, bool) or not isinstance(time, (int, float)) or math.isnan(time):
            raise ValueError(f"Environment: time must be a number or None, got {time!r}")
        return [obs for obs in self.obstacles if obs.appear_time <= time]

    def in_collision(self, xy: Tensor, time: float | None = None) -> Tensor:
        """``xy [..., 2]`` -> ``bool [...]``: inside an obstacle sensed at ``time`` (all for None), or outside
        ``bounds``. Non-finite points count as collisions."""
        _check_xy(xy, "Environment.in_collision")
        obstacles = self.visible(time)
        hit = ~torch.isfinite(xy).all(dim=-1)  # [...]
        if self.bounds is not None:
            xmin, ymin, xmax, ymax = self.bounds
            x, y = xy[..., 0], xy[..., 1]
            hit |= (x < xmin) | (x > xmax) | (y < ymin) | (y > ymax)
        for obs in obstacles:
            hit |= obs.contains(xy)
        return hit
