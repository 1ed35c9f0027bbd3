"""The compiled loop of :meth:`Environment.in_collision <cuniform_torch.envs.environment.Environment.in_collision>`
(numba, imported when first used; module-level, so numba's disk cache finds it in the next process).

One pass over the points, each tested against the discs and rectangles until one contains it, with the
arithmetic of :meth:`Circle.contains <cuniform_torch.envs.shapes.Circle.contains>` and ``Rect.contains`` in the
points' dtype: ``(x - cx) * (x - cx) + (y - cy) * (y - cy) <= r^2`` and the four closed comparisons (no fused
multiply-add: numba contracts only under fastmath), so every answer is the torch path's to the last bit.
"""

from __future__ import annotations

from cuniform_torch.common.compiled import njit

__all__ = ["any_contains"]


@njit(nogil=True, boundscheck=False)
def any_contains(pts, circles, rects, hit):
    """``hit[i] |= pts[i]`` inside any disc of ``circles [C, 3]`` (x, y, r^2) or rectangle of ``rects [R, 4]``."""
    for i in range(pts.shape[0]):
        if hit[i]:
            continue
        x, y = pts[i, 0], pts[i, 1]
        found = False
        for k in range(circles.shape[0]):
            dx, dy = x - circles[k, 0], y - circles[k, 1]
            if dx * dx + dy * dy <= circles[k, 2]:
                found = True
                break
        if not found:
            for k in range(rects.shape[0]):
                if x >= rects[k, 0] and x <= rects[k, 2] and y >= rects[k, 1] and y <= rects[k, 3]:
                    found = True
                    break
        hit[i] = found
