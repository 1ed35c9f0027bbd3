"""2-D obstacles: circles, rectangles and polygons, with batched containment and signed distance, any device.

Shapes used in this module: ``...`` any batch shape (e.g. ``[N, T]``), V polygon vertices (= edges).
The occupancy grid is :mod:`.occupancy`'s, the environment that holds obstacles :mod:`.environment`'s, the
paper's U-shaped trap :mod:`.scenes`'.

Every obstacle has ``contains(xy [..., 2]) -> bool [...]`` and an ``appear_time`` (s): an obstacle is
physically present from the start, but the robot only *senses* it from ``appear_time`` on (the paper's
suddenly-appearing obstacle). :meth:`Environment.in_collision` with ``time=None`` is the physical truth; with a
time it is what the robot knows then. Circles, rectangles and polygons also have
``signed_distance(xy [..., 2]) -> [...]`` (Euclidean, negative inside).

Queries are pure tensor ops in the dtype and on the device of ``xy``: geometry given as Python numbers is
used as scalars, and polygon vertices are copied once per (dtype, device) and cached.

Boundaries: circles and rectangles are closed (a point on the boundary is inside). A polygon uses the
even-odd crossing rule, which is half-open: a point exactly on a polygon edge may go either way.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import torch
from torch import Tensor

__all__ = ["Obstacle", "Circle", "Rect", "Polygon"]


@runtime_checkable
class Obstacle(Protocol):
    """What an :class:`Environment` needs from an obstacle."""

    appear_time: float
    """time (s) from which the robot senses the obstacle; it is physically there from the start"""

    def contains(self, xy: Tensor) -> Tensor:
        """``xy [..., 2]`` (floating point) -> ``bool [...]``."""
        ...


# ------------------------------------------------------------------------------------------------ checks

def _check_xy(xy: Any, who: str) -> None:
    if not isinstance(xy, torch.Tensor):
        raise ValueError(f"{who}: xy must be a torch.Tensor of shape [..., 2], got {type(xy).__name__}")
    if not xy.is_floating_point():
        raise ValueError(f"{who}: xy must be a floating-point tensor, got dtype {xy.dtype}")
    if xy.ndim < 1 or xy.shape[-1] != 2:
        raise ValueError(f"{who}: xy must have shape [..., 2], got {list(xy.shape)}")


def _number(value: Any, what: str, who: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ValueError(f"{who}: {what} must be a finite number, got {value!r}")
    return float(value)


def _point(value: Any, what: str, who: str) -> tuple[float, float]:
    try:
        out = tuple(float(v) for v in value)
    except (TypeError, ValueError):
        raise ValueError(f"{who}: {what} must be a pair of numbers (x, y), got {value!r}") from None
    if len(out) != 2 or not all(math.isfinite(v) for v in out):
        raise ValueError(f"{who}: {what} must be a pair of finite numbers (x, y), got {value!r}")
    return out  # type: ignore[return-value]


def _appear_time(value: Any, who: str) -> float:
    """``appear_time`` is a number >= 0; ``math.inf`` means never sensed."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or math.isnan(value) or value < 0:
        raise ValueError(f"{who}: appear_time must be a number >= 0 (inf: never sensed), got {value!r}")
    return float(value)


# ------------------------------------------------------------------------------------------------ shapes

@dataclass(frozen=True)
class Circle:
    """A disc of ``radius`` around ``center``."""

    center: tuple[float, float]
    """(x, y) in m"""
    radius: float
    """m, > 0"""
    appear_time: float = 0.0
    """time (s) from which the robot senses it"""

    def __post_init__(self) -> None:
        object.__setattr__(self, "center", _point(self.center, "center", "Circle"))
        r = _number(self.radius, "radius", "Circle")
        if r <= 0:
            raise ValueError(f"Circle: radius must be > 0, got {self.radius!r}")
        object.__setattr__(self, "radius", r)
        object.__setattr__(self, "appear_time", _appear_time(self.appear_time, "Circle"))

    def signed_distance(self, xy: Tensor) -> Tensor:
        """``xy [..., 2]`` -> ``[...]``: distance to the circle, negative inside."""
        _check_xy(xy, "Circle.signed_distance")
        return torch.hypot(xy[..., 0] - self.center[0], xy[..., 1] - self.center[1]) - self.radius

    def contains(self, xy: Tensor) -> Tensor:
        """``xy [..., 2]`` -> ``bool [...]`` (closed disc)."""
        _check_xy(xy, "Circle.contains")
        dx = xy[..., 0] - self.center[0]
        dy = xy[..., 1] - self.center[1]
        return dx * dx + dy * dy <= self.radius * self.radius


@dataclass(frozen=True)
class Rect:
    """An axis-aligned rectangle ``[xmin, xmax] x [ymin, ymax]`` (closed)."""

    xmin: float
    ymin: float
    xmax: float
    ymax: float
    appear_time: float = 0.0
    """time (s) from which the robot senses it"""

    def __post_init__(self) -> None:
        for name in ("xmin", "ymin", "xmax", "ymax"):
            object.__setattr__(self, name, _number(getattr(self, name), name, "Rect"))
        if not self.xmin < self.xmax:
            raise ValueError(f"Rect: need xmin < xmax, got xmin={self.xmin}, xmax={self.xmax}")
        if not self.ymin < self.ymax:
            raise ValueError(f"Rect: need ymin < ymax, got ymin={self.ymin}, ymax={self.ymax}")
        object.__setattr__(self, "appear_time", _appear_time(self.appear_time, "Rect"))

    def signed_distance(self, xy: Tensor) -> Tensor:
        """``xy [..., 2]`` -> ``[...]``: exact Euclidean distance to the rectangle, negative inside."""
        _check_xy(xy, "Rect.signed_distance")
        cx, cy = 0.5 * (self.xmin + self.xmax), 0.5 * (self.ymin + self.ymax)
        hx, hy = 0.5 * (self.xmax - self.xmin), 0.5 * (self.ymax - self.ymin)
        qx = (xy[..., 0] - cx).abs() - hx  # [...] > 0 outside the slab |x - cx| <= hx
        qy = (xy[..., 1] - cy).abs() - hy
        outside = torch.hypot(qx.clamp(min=0), qy.clamp(min=0))
        inside = torch.maximum(qx, qy).clamp(max=0)
        return outside + inside

    def contains(self, xy: Tensor) -> Tensor:
        """``xy [..., 2]`` -> ``bool [...]`` (closed rectangle)."""
        _check_xy(xy, "Rect.contains")
        x, y = xy[..., 0], xy[..., 1]
        return (x >= self.xmin) & (x <= self.xmax) & (y >= self.ymin) & (y <= self.ymax)


def _orient(a: Tensor, b: Tensor, c: Tensor) -> Tensor:
    """Twice the signed area of (a, b, c): ``[..., 2]`` x3 -> ``[...]`` (> 0 counter-clockwise)."""
    return (b[..., 0] - a[..., 0]) * (c[..., 1] - a[..., 1]) - (b[..., 1] - a[..., 1]) * (c[..., 0] - a[..., 0])


def _on_segment(a: Tensor, b: Tensor, p: Tensor) -> Tensor:
    """Whether collinear point ``p`` lies within the bounding box of segment ``ab`` (all ``[..., 2]``)."""
    lo, hi = torch.minimum(a, b), torch.maximum(a, b)
    return ((p >= lo) & (p <= hi)).all(dim=-1)


def _first_crossing(v: Tensor, chunk: int = 256) -> tuple[int, int] | None:
    """The first pair of non-adjacent edges of the closed polygon ``v [V, 2]`` (float64) that touch, if any."""
    V = v.shape[0]
    a, b = v, torch.roll(v, -1, dims=0)  # [V, 2] edge i runs a[i] -> b[i]
    idx = torch.arange(V)
    for start in range(0, V, chunk):
        i = idx[start:start + chunk, None]  # [c, 1]
        ai, bi = a[start:start + chunk, None], b[start:start + chunk, None]  # [c, 1, 2]
        aj, bj = a[None], b[None]  # [1, V, 2]
        o1, o2 = _orient(ai, bi, aj), _orient(ai, bi, bj)  # [c, V]
        o3, o4 = _orient(aj, bj, ai), _orient(aj, bj, bi)
        hit = (o1 * o2 < 0) & (o3 * o4 < 0)  # [c, V] proper crossing
        hit |= (o1 == 0) & _on_segment(ai, bi, aj)  # an endpoint of one edge lies on the other
        hit |= (o2 == 0) & _on_segment(ai, bi, bj)
        hit |= (o3 == 0) & _on_segment(aj, bj, ai)
        hit |= (o4 == 0) & _on_segment(aj, bj, bi)
        gap = torch.remainder(idx[None] - i, V)  # [c, V]
        hit &= (gap > 1) & (gap < V - 1)  # not the same edge, not neighbours (they share a vertex)
        if bool(hit.any()):
            k, j = (int(t) for t in hit.nonzero()[0])
            return start + k, j
    return None


@dataclass(frozen=True, eq=False)
class Polygon:
    """A simple (not self-intersecting), possibly non-convex polygon.

    ``vertices`` ``[V, 2]`` in order (either orientation), V >= 3, not closed (a repeated first vertex at the
    end is dropped). Checked at construction: finite, no repeated consecutive vertices, non-zero area, and no two
    non-adjacent edges touching. Containment is the even-odd crossing rule, vectorized over points and edges
    (memory ``[..., V]``).
    """

    vertices: Any
    """``[V, 2]`` sequence or tensor of (x, y); stored as a float64 CPU tensor"""
    appear_time: float = 0.0
    """time (s) from which the robot senses it"""
    _cache: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        try:
            v = torch.as_tensor(
                self.vertices.detach().cpu() if isinstance(self.vertices, Tensor) else self.vertices,
                dtype=torch.float64,
            )
        except (TypeError, ValueError, RuntimeError):
            raise ValueError(f"Polygon: vertices must be a [V, 2] sequence of numbers, got {self.vertices!r}") from None
        if v.ndim != 2 or v.shape[1] != 2:
            raise ValueError(f"Polygon: vertices must have shape [V, 2], got {list(v.shape)}")
        if not bool(torch.isfinite(v).all()):
            raise ValueError("Polygon: vertices must be finite")
        if v.shape[0] >= 2 and torch.equal(v[0], v[-1]):
            v = v[:-1]  # closed ring given: drop the repeated first vertex
        V = v.shape[0]
        if V < 3:
            raise ValueError(f"Polygon: needs at least 3 vertices, got {V}")
        nxt = torch.roll(v, -1, dims=0)
        repeated = (v == nxt).all(dim=1)
        if bool(repeated.any()):
            k = int(repeated.nonzero()[0])
            raise ValueError(f"Polygon: vertices {k} and {(k + 1) % V} are equal, {v[k].tolist()}")
        crossing = _first_crossing(v)
        if crossing is not None:
            raise ValueError(f"Polygon: not simple, edges {crossing[0]} and {crossing[1]} intersect")
        area2 = float((v[:, 0] * nxt[:, 1] - nxt[:, 0] * v[:, 1]).sum())
        scale = float((v - v.mean(dim=0)).abs().max()) ** 2
        if abs(area2) <= 1e-12 * scale:
            raise ValueError("Polygon: the vertices enclose zero area (all collinear?)")
        object.__setattr__(self, "vertices", v)
        object.__setattr__(self, "appear_time", _appear_time(self.appear_time, "Polygon"))

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Polygon):
            return NotImplemented
        return torch.equal(self.vertices, other.vertices) and self.appear_time == other.appear_time

    __hash__ = None  # type: ignore[assignment]

    @property
    def area(self) -> float:
        """Enclosed area (m^2)."""
        v, nxt = self.vertices, torch.roll(self.vertices, -1, dims=0)
        return 0.5 * abs(float((v[:, 0] * nxt[:, 1] - nxt[:, 0] * v[:, 1]).sum()))

    def _edges(self, like: Tensor) -> tuple[Tensor, Tensor]:
        """Edge starts and ends ``([V, 2], [V, 2])`` in the dtype and on the device of ``like`` (cached)."""
        key = (like.dtype, like.device)
        if key not in self._cache:
            a = self.vertices.to(dtype=like.dtype, device=like.device)
            self._cache[key] = (a, torch.roll(a, -1, dims=0))
        return self._cache[key]

    def contains(self, xy: Tensor) -> Tensor:
        """``xy [..., 2]`` -> ``bool [...]``: even-odd rule (a ray towards +x crosses an odd number of edges)."""
        _check_xy(xy, "Polygon.contains")
        a, b = self._edges(xy)  # [V, 2]
        px, py = xy[..., 0, None], xy[..., 1, None]  # [..., 1]
        ax, ay, bx, by = a[:, 0], a[:, 1], b[:, 0], b[:, 1]  # [V]
        straddles = (ay > py) != (by > py)  # [..., V] the edge spans the ray's height (half-open)
        dy = by - ay
        safe_dy = torch.where(dy == 0, torch.ones_like(dy), dy)  # horizontal edges never straddle
        x_cross = ax + (py - ay) * (bx - ax) / safe_dy  # [..., V]
        crossings = (straddles & (px < x_cross)).sum(dim=-1)  # [...]
        return (crossings % 2) == 1

    def boundary_distance(self, xy: Tensor) -> Tensor:
        """``xy [..., 2]`` -> ``[...]``: unsigned distance to the nearest edge."""
        _check_xy(xy, "Polygon.boundary_distance")
        a, b = self._edges(xy)  # [V, 2]
        ab = b - a  # [V, 2]
        ap = xy[..., None, :] - a  # [..., V, 2]
        s = ((ap * ab).sum(dim=-1) / (ab * ab).sum(dim=-1)).clamp(0.0, 1.0)  # [..., V] projection parameter
        closest = ap - s[..., None] * ab  # [..., V, 2] offset from the nearest point of each edge
        return torch.linalg.vector_norm(closest, dim=-1).amin(dim=-1)

    def signed_distance(self, xy: Tensor) -> Tensor:
        """``xy [..., 2]`` -> ``[...]``: distance to the boundary, negative inside (memory ``[..., V, 2]``)."""
        _check_xy(xy, "Polygon.signed_distance")
        dist = self.boundary_distance(xy)
        return torch.where(self.contains(xy), -dist, dist)
