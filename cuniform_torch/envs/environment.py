"""The environment: obstacles (anything with ``contains`` and ``appear_time``) and optional workspace bounds.

:meth:`Environment.in_collision` with ``time=None`` is the physical truth; with a time it is what the robot
knows then (an obstacle is sensed from its ``appear_time`` on).
"""

from __future__ import annotations

import bisect
import math
import operator
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from cuniform_torch.common.compiled import optional_loop
from cuniform_torch.envs.moving import MovingDiscs
from cuniform_torch.envs.shapes import Circle, Rect, _appear_time, _check_xy

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
    moving: MovingDiscs | None = None
    """discs at constant velocity, tested at the time a point is occupied (module docstring); None: none"""

    def __post_init__(self) -> None:
        if self.moving is not None and not isinstance(self.moving, MovingDiscs):
            raise ValueError(f"Environment: moving must be a MovingDiscs or None, got {type(self.moving).__name__}")
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

    def in_collision(self, xy: Tensor, time: float | None = None, at: float | Tensor | None = None) -> Tensor:
        """``xy [..., 2]`` -> ``bool [...]``: inside an obstacle sensed at ``time`` (all for None), inside a moving
        disc where it is at time ``at``, or outside ``bounds``. Non-finite points count as collisions.

        ``at``: the time (s) each point is occupied: a number, or a tensor broadcastable to ``[...]`` (a rollout's
        step times ``[T]`` for points ``[N, T, 2]``); needed when ``moving`` is set, unused otherwise."""
        _check_xy(xy, "Environment.in_collision")
        if self.moving is not None and at is None:
            raise ValueError("Environment.in_collision: this environment has moving discs; give at= the time (s) "
                             "each point is occupied (a number, or a tensor of step times)")
        circles, rects, others = self._visible_tables(time, torch.float64)  # sensed at time, walked once
        hit = ~torch.isfinite(xy).all(dim=-1)  # [...]
        if self.bounds is not None:
            xmin, ymin, xmax, ymax = self.bounds
            x, y = xy[..., 0], xy[..., 1]
            hit |= (x < xmin) | (x > xmax) | (y < ymin) | (y > ymax)
        if len(circles) or len(rects):
            if xy.device.type != "cpu":  # the tables on that device, in the points' dtype: copied once, not per call
                circles, rects = self._on_device(circles, rects, xy)
            hit |= _any_contains(xy, circles, rects)
        for obs in others:
            hit |= obs.contains(xy)
        if self.moving is not None and len(self.moving):
            assert at is not None  # refused above
            hit |= self.moving.contains(xy, at)
        return hit

    def snapshot(self, t: float) -> Environment:
        """The environment as it is at time ``t`` (s): the same obstacles and bounds, each moving disc a fixed
        :class:`Circle` where it is then (the last ones, in ``moving``'s order); the environment itself when nothing
        moves. For the static tools (:func:`~precompute.worlds.geometry.reachable`, rasters)."""
        if self.moving is None:
            return self
        circles = [Circle((x, y), r) for (x, y), r in zip(self.moving.centres(t).tolist(), self.moving.radius.tolist())]
        return Environment(list(self.obstacles) + circles, bounds=self.bounds)

    def _on_device(self, circles: Tensor, rects: Tensor, xy: Tensor) -> tuple[Tensor, Tensor]:
        """``circles``, ``rects`` (the CPU tables of :meth:`_visible_tables`) on ``xy``'s device in its dtype, cached per
        table, device and dtype (a copy to a GPU per call would wait for it)."""
        key = (id(circles), id(rects), xy.device, xy.dtype)
        cache = self.__dict__.setdefault("_device_tables", {})
        hit = cache.get(key)
        if hit is None or hit[0] is not circles or hit[1] is not rects:
            hit = cache[key] = (circles, rects, circles.to(device=xy.device, dtype=xy.dtype),
                                rects.to(device=xy.device, dtype=xy.dtype))
        return hit[2], hit[3]

    def _visible_tables(self, time: float | None, dtype: torch.dtype) -> tuple[Tensor, Tensor, list]:
        """The Circles ``[C, 3]`` (x, y, r^2) and Rects ``[R, 4]`` sensed at ``time`` (all for None) as CPU tables
        in ``dtype``, and the other obstacles sensed then: what :meth:`visible` gives, as tables, without a walk over
        the obstacles per call (the tables are sorted by ``appear_time`` once, so those sensed
        are a prefix). Cached while the obstacles are the same objects."""
        tables, others = self._visible(time, dtype)
        return tables[0], tables[1], others

    def _visible_arrays(self, time: float | None, dtype: torch.dtype) -> tuple[np.ndarray, np.ndarray, list]:
        """:meth:`_visible_tables` as numpy arrays (views of the same memory), for the compiled cost."""
        tables, others = self._visible(time, dtype)
        return tables[2], tables[3], others

    def _visible(self, time: float | None, dtype: torch.dtype) -> tuple[tuple, list]:
        """``((circles, rects, circles_np, rects_np), others)`` sensed at ``time`` in ``dtype`` (see
        :meth:`_visible_tables`); each prefix made once per dtype and count sensed."""
        obstacles = self.obstacles
        cached = self.__dict__.get("_sorted_cache")
        if cached is None or len(cached[0]) != len(obstacles) or not all(map(operator.is_, cached[0], obstacles)):
            circles = sorted(((o.appear_time, o.center[0], o.center[1], o.radius * o.radius) for o in obstacles
                              if type(o) is Circle), key=operator.itemgetter(0))
            rects = sorted(((o.appear_time, o.xmin, o.ymin, o.xmax, o.ymax) for o in obstacles if type(o) is Rect),
                           key=operator.itemgetter(0))
            tables = (torch.tensor([c[1:] for c in circles], dtype=torch.float64).reshape(-1, 3),
                      torch.tensor([r[1:] for r in rects], dtype=torch.float64).reshape(-1, 4))
            others = [o for o in obstacles if type(o) not in (Circle, Rect)]
            prefixes: dict[tuple[torch.dtype, tuple[int, int]], tuple] = {}  # (dtype, counts sensed) -> tables
            cached = (tuple(obstacles), [c[0] for c in circles], [r[0] for r in rects], tables, others, prefixes)
            self._sorted_cache: tuple = cached
        _, c_times, r_times, tables, others, prefixes = cached
        if time is None:
            counts = (len(c_times), len(r_times))
        else:
            if isinstance(time, bool) or not isinstance(time, (int, float)) or math.isnan(time):
                raise ValueError(f"Environment: time must be a number or None, got {time!r}")
            counts = (bisect.bisect_right(c_times, time), bisect.bisect_right(r_times, time))
            others = [o for o in others if o.appear_time <= time] if others else others
        key = (dtype, counts)
        hit = prefixes.get(key)
        if hit is None:
            c, r = tables[0][:counts[0]].to(dtype).contiguous(), tables[1][:counts[1]].to(dtype).contiguous()
            hit = prefixes[key] = (c, r, c.numpy(), r.numpy())
        return hit, others


_CONTAINS_CHUNK = 1 << 22
"""point-obstacle pairs tested at once (bounds the temporaries of a large batch of points)"""


_PREFILTER_PAIRS = 1 << 14
"""above this many point-obstacle pairs, obstacles that cannot touch the points' bounding box are dropped first"""


_COMPILED_PAIRS = 1 << 12
"""above this many point-obstacle pairs on a CPU, the compiled loop (:mod:`cuniform_torch.envs.contains_loops`)
tests them: one pass over the points, stopping at the first obstacle that contains each"""


def _compiled():
    """The compiled loop, or None without numba."""
    return optional_loop("cuniform_torch.envs.contains_loops", "any_contains")


def _near_box(pts: Tensor, circles: Tensor, rects: Tensor) -> tuple[Tensor, Tensor]:
    """The ``circles [C, 3]`` and ``rects [R, 4]`` that meet the bounding box of the finite points ``pts [P, 2]``:
    a point inside an obstacle is inside that box, so the rest cannot contain one (a sensed patch of 5184 points on
    a BARN map keeps the few dozen cylinders around the robot). A disc is kept when the box point nearest its
    centre is within its radius, with a relative margin of 1e-4 for the points' rounding; all are kept when no
    point is finite."""
    lo, hi = torch.aminmax(pts, dim=0)  # [2] the box (NaN when a point is NaN)
    if not bool(torch.isfinite(torch.cat((lo, hi))).all()):
        finite = pts[torch.isfinite(pts).all(dim=1)]
        if finite.shape[0] == 0:
            return circles, rects
        lo, hi = finite.amin(dim=0), finite.amax(dim=0)
    if len(circles):
        centre = circles[:, :2]
        gap = centre - torch.minimum(torch.maximum(centre, lo), hi)  # [C, 2] centre to the nearest box point
        circles = circles[gap.square().sum(dim=1) <= circles[:, 2] * (1 + 1e-4) + 1e-12]
    if len(rects):
        rects = rects[(rects[:, 0] <= hi[0]) & (rects[:, 2] >= lo[0]) & (rects[:, 1] <= hi[1]) & (rects[:, 3] >= lo[1])]
    return circles, rects


def _any_contains(xy: Tensor, circles: Tensor, rects: Tensor) -> Tensor:
    """``xy [..., 2]`` -> ``bool [...]``: inside any closed disc (``circles [C, 3]``: x, y, r^2) or closed
    rectangle (``rects [R, 4]``), with the arithmetic of :meth:`Circle.contains` / :meth:`Rect.contains` in the
    points' dtype (so the same answer to the last bit)."""
    flat = xy.reshape(-1, 2)  # [P, 2]
    pts = flat.unsqueeze(1)  # [P, 1, 2]
    hit = torch.zeros(pts.shape[0], dtype=torch.bool, device=xy.device)  # [P]
    c = circles.to(device=xy.device, dtype=xy.dtype)  # [C, 3]
    r = rects.to(device=xy.device, dtype=xy.dtype)  # [R, 4]
    # the prefilter's tables have data-dependent sizes (a host read): on a CPU only, where that read is free
    if xy.device.type == "cpu" and pts.shape[0] * (len(c) + len(r)) > _PREFILTER_PAIRS:
        c, r = _near_box(flat, c, r)
    loop = _compiled() if xy.device.type == "cpu" and pts.shape[0] * (len(c) + len(r)) > _COMPILED_PAIRS else None
    if loop is not None:
        loop(flat.contiguous().numpy(), c.contiguous().numpy(), r.contiguous().numpy(), hit.numpy())
        return hit.reshape(xy.shape[:-1])
    step = max(1, _CONTAINS_CHUNK // max(1, len(c) + len(r)))
    for lo in range(0, pts.shape[0], step):
        p = pts[lo:lo + step]  # [p, 1, 2]
        x, y = p[..., 0], p[..., 1]  # [p, 1]
        if len(c):
            dx, dy = x - c[:, 0], y - c[:, 1]  # [p, C]
            hit[lo:lo + step] |= (dx * dx + dy * dy <= c[:, 2]).any(dim=1)
        if len(r):
            hit[lo:lo + step] |= ((x >= r[:, 0]) & (x <= r[:, 2]) & (y >= r[:, 1]) & (y <= r[:, 3])).any(dim=1)
    return hit.reshape(xy.shape[:-1])
