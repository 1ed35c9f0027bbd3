"""Plane geometry of the navigation suites: exact inflation by the robot's disc, signed distances, sensing by
range, and the certified flood fill that says whether a goal is reachable.

Shapes used in this module: M discs, W wall rectangles, P points, K obstacles, H x G flood-fill grid cells.

Inflation (:func:`inflate`) is exact: a disc grows to a disc of radius ``radius + robot_radius``; a rectangle
becomes its Minkowski sum with the robot disc (a rounded rectangle), stored as two :class:`Rect` s and four
corner :class:`Circle` s; the outer box shrinks by ``robot_radius`` on every side.

Reachability (:func:`reachable`) is a *certified* flood fill: a grid cell of side ``resolution`` h is free when
its centre's clearance (signed distance to every inflated obstacle and to the bounds) exceeds h / sqrt(2); two
4-neighbouring free cells are then joined by a collision-free segment, and the start and goal by a segment to
their nearest cell centre. So "reachable" means a collision-free polyline exists for the centre; a passage
narrower than about 1.4 h may be missed.
"""

from __future__ import annotations

import math

import numpy as np
import scipy.ndimage
import torch

from cuniform_torch.envs import Circle, Environment, Rect

__all__ = ["SuiteError", "inflate", "clearance", "obstacle_tables", "sensed", "reachable"]


class SuiteError(ValueError):
    """A suite that cannot be made: bad parameters or geometry, a start or goal in collision, an unreachable
    goal (raised here and by :mod:`precompute.worlds.suites`)."""


def _positive(value, what: str, who: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
        raise SuiteError(f"{who}: {what} must be a finite number > 0, got {value!r}")
    return float(value)


def inflate(discs: np.ndarray, walls: np.ndarray, bounds: tuple[float, float, float, float],
            robot_radius: float) -> Environment:
    """Raw ``discs [M, 3]``, ``walls [W, 4]`` and ``bounds`` -> an :class:`Environment` for the robot's centre
    (exact Minkowski sums with the robot disc; see the module docstring). Obstacle order: discs, then per wall
    its x-grown rect, its y-grown rect and its four corner circles (the last five only for ``robot_radius > 0``)."""
    r = float(robot_radius)
    obstacles: list = [Circle((float(x), float(y)), float(rad) + r) for x, y, rad in discs.tolist()]
    for x0, y0, x1, y1 in walls.tolist():
        if r == 0:
            obstacles.append(Rect(x0, y0, x1, y1))
            continue
        obstacles += [Rect(x0 - r, y0, x1 + r, y1), Rect(x0, y0 - r, x1, y1 + r)]
        obstacles += [Circle((cx, cy), r) for cx in (x0, x1) for cy in (y0, y1)]
    xmin, ymin, xmax, ymax = bounds
    if not (xmax - xmin > 2 * r and ymax - ymin > 2 * r):
        raise SuiteError(f"inflate: bounds {bounds} leave no room for a robot of radius {r}")
    return Environment(obstacles, bounds=(xmin + r, ymin + r, xmax - r, ymax - r))


def obstacle_tables(environment: Environment) -> tuple[np.ndarray, np.ndarray]:
    """The circles ``[C, 3]`` (x, y, r) and rects ``[R, 4]`` of ``environment``; any other obstacle raises."""
    circles, rects = [], []
    for k, obs in enumerate(environment.obstacles):
        if isinstance(obs, Circle):
            circles.append((*obs.center, obs.radius))
        elif isinstance(obs, Rect):
            rects.append((obs.xmin, obs.ymin, obs.xmax, obs.ymax))
        else:
            raise SuiteError(f"obstacle {k} is a {type(obs).__name__}; suites use only Circle and Rect")
    return np.asarray(circles, dtype=np.float64).reshape(-1, 3), np.asarray(rects, dtype=np.float64).reshape(-1, 4)


def _distances(environment: Environment, xy: np.ndarray) -> np.ndarray:
    """``xy [P, 2]`` -> ``[P, K]``: signed distance (negative inside) from each point to each obstacle (a
    transposed view of a ``[K, P]`` array: filling whole rows per obstacle kind is what keeps this fast)."""
    circles, rects = obstacle_tables(environment)
    is_circle = np.array([isinstance(o, Circle) for o in environment.obstacles], dtype=bool)
    out = np.empty((len(environment.obstacles), xy.shape[0]))  # [K, P]
    # torch's cdist without the matrix-product shortcut: exact to an ulp and ~10x numpy's broadcast hypot
    centre_dist = torch.cdist(torch.from_numpy(circles[:, :2]), torch.from_numpy(xy),
                              compute_mode="donot_use_mm_for_euclid_dist").numpy()  # [C, P]
    centre_dist -= circles[:, 2:3]
    if is_circle.all():
        out = centre_dist
    else:
        out[is_circle] = centre_dist
        c = 0.5 * (rects[:, :2] + rects[:, 2:])  # [R, 2] centres
        h = 0.5 * (rects[:, 2:] - rects[:, :2])  # [R, 2] half sizes
        q = np.abs(xy[None, :, :] - c[:, None]) - h[:, None]  # [R, P, 2]
        outside = np.hypot(*np.clip(q, 0, None).transpose(2, 0, 1))
        inside = np.clip(q.max(axis=-1), None, 0)
        out[~is_circle] = outside + inside
    return out.T


def clearance(environment: Environment, xy: np.ndarray) -> np.ndarray:
    """``xy [P, 2]`` -> ``[P]``: distance from each point to the nearest obstacle or bound of ``environment``
    (negative inside an obstacle or outside the bounds; + inf with neither)."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    best = np.full(xy.shape[0], np.inf)
    if environment.obstacles:
        best = _distances(environment, xy).min(axis=1)
    if environment.bounds is not None:
        xmin, ymin, xmax, ymax = environment.bounds
        inner = np.minimum.reduce([xy[:, 0] - xmin, xmax - xy[:, 0], xy[:, 1] - ymin, ymax - xy[:, 1]])
        best = np.minimum(best, inner)
    return best


def sensed(environment: Environment, xy: torch.Tensor, sensing_range: float) -> Environment:
    """The obstacles of ``environment`` whose nearest point is within ``sensing_range`` of ``xy [2]`` (those
    containing ``xy`` included), in their original order, with the same bounds and the same moving discs (all of
    them: they are sensed as they are, whatever the range).

    Pure; one vectorized distance computation over all obstacles (Circle and Rect only). The runner calls it
    once per control cycle; on a :class:`NavTask` use :meth:`NavTask.sensed_environment`, which corrects the
    range for the inflation."""
    if isinstance(sensing_range, bool) or not isinstance(sensing_range, (int, float)) or math.isnan(sensing_range):
        raise SuiteError(f"sensed: sensing_range must be a number, got {sensing_range!r}")
    p = torch.as_tensor(xy, dtype=torch.float64).detach().cpu().reshape(-1)
    if p.shape != (2,) or not bool(torch.isfinite(p).all()):
        raise SuiteError(f"sensed: xy must be a finite point (x, y), got {xy!r}")
    if not environment.obstacles:
        return Environment([], bounds=environment.bounds, moving=environment.moving)
    near = _distances(environment, p.numpy()[None])[0] <= sensing_range  # [K]
    return Environment([o for o, keep in zip(environment.obstacles, near.tolist()) if keep], bounds=environment.bounds,
                       moving=environment.moving)


def reachable(environment: Environment, start: tuple[float, float], goal: tuple[float, float],
              resolution: float = 0.1) -> bool:
    """Whether a certified flood fill (module docstring) over ``environment.bounds`` joins ``start`` and
    ``goal``; grid ``[H, G]`` of cells of side ``resolution``."""
    if environment.bounds is None:
        raise SuiteError("reachable: the environment needs bounds to flood-fill")
    h = _positive(resolution, "resolution", "reachable")
    xmin, ymin, xmax, ymax = environment.bounds
    xs = np.arange(xmin + h / 2, xmax, h)  # [G] cell centres
    ys = np.arange(ymin + h / 2, ymax, h)  # [H]
    if xs.size == 0 or ys.size == 0:
        return False
    gx, gy = np.meshgrid(xs, ys)  # [H, G]
    free = (clearance(environment, np.stack((gx.ravel(), gy.ravel()), axis=1)) > h / math.sqrt(2)).reshape(gx.shape)
    labels, _ = scipy.ndimage.label(free)  # 4-connected components

    def cell(p: tuple[float, float]) -> int:
        j = int(np.clip(np.rint((p[0] - xs[0]) / h), 0, xs.size - 1))
        i = int(np.clip(np.rint((p[1] - ys[0]) / h), 0, ys.size - 1))
        near = math.hypot(p[0] - xs[j], p[1] - ys[i]) <= h / math.sqrt(2) + 1e-12
        return int(labels[i, j]) if near else 0

    a, b = cell(start[:2]), cell(goal[:2])
    return a != 0 and a == b


