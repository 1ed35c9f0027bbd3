"""The compiled navigation cost (:class:`~cuniform_torch.envs.costs.NavigationCost` on a CPU; numba, imported when
first used; module-level, so numba's disk cache finds it in the next process).

Shapes: N rollouts, T horizon, d state dimensions (x, y first), C discs, R rectangles.

One call does what the torch path does in about twenty small tensor ops (each a dispatch and an allocation, the
cost call's fixed overhead at small N): the goal term, the arrival cut-off and the collision test of every state at
steps ``1..T``, in one pass over the rollouts. The arithmetic is the torch path's in the states' dtype
(``dx * dx + dy * dy`` against the goal and the discs, the closed comparisons of the rectangles and bounds); only
the order of the goal term's float sum may differ (within float rounding).
"""

from __future__ import annotations

import math

import numpy as np

from cuniform_torch.common.compiled import njit

__all__ = ["navigation_cost"]


@njit(nogil=True, boundscheck=False)
def navigation_cost(states, gx, gy, tol2, circles, rects, bounds, has_bounds, per_state, stop_at_goal, penalty, out):
    """``out[i]``: rollout ``i``'s navigation cost (:class:`~cuniform_torch.envs.costs.NavigationCost`).

    ``states [N, T+1, d]``; ``gx, gy, tol2`` the goal and the squared tolerance, and ``circles [C, 3]`` (x, y,
    r^2), ``rects [R, 4]``, ``bounds [4]`` (used when ``has_bounds``), all in the states' dtype; ``penalty`` (float);
    ``out [N]`` in the states' dtype.

    The obstacles that cannot meet the bounding box of the finite points are dropped first (what
    ``Environment.in_collision``'s prefilter does, with its margin, in float64): a point inside one is inside that
    box."""
    n, t1 = states.shape[0], states.shape[1]
    lox, loy, hix, hiy = math.inf, math.inf, -math.inf, -math.inf
    for i in range(n):
        for t in range(1, t1):
            x, y = states[i, t, 0], states[i, t, 1]
            if math.isfinite(x) and math.isfinite(y):
                lox, hix = min(lox, x), max(hix, x)
                loy, hiy = min(loy, y), max(hiy, y)
    keep_c = np.empty(circles.shape[0], dtype=np.int64)  # the obstacles kept
    keep_r = np.empty(rects.shape[0], dtype=np.int64)
    nc = 0
    for k in range(circles.shape[0]):  # the box point nearest the centre within the radius (no finite point: none)
        cx, cy = float(circles[k, 0]), float(circles[k, 1])
        ex, ey = cx - min(max(cx, lox), hix), cy - min(max(cy, loy), hiy)
        if ex * ex + ey * ey <= float(circles[k, 2]) * (1 + 1e-4) + 1e-12:
            keep_c[nc] = k
            nc += 1
    nr = 0
    for k in range(rects.shape[0]):
        if rects[k, 0] <= hix and rects[k, 2] >= lox and rects[k, 1] <= hiy and rects[k, 3] >= loy:
            keep_r[nr] = k
            nr += 1
    zero = tol2 - tol2  # 0 in the states' dtype
    for i in range(n):
        cost = zero
        arrived = False
        hits = 0
        for t in range(1, t1):
            if stop_at_goal and arrived:  # nothing accrues after the first arrival (that step was counted)
                break
            x, y = states[i, t, 0], states[i, t, 1]
            dx, dy = x - gx, y - gy
            d2 = dx * dx + dy * dy
            if d2 <= tol2:
                arrived = True
            if not arrived:
                cost += d2
            if hits > 0 and not per_state:
                continue
            hit = not (math.isfinite(x) and math.isfinite(y))
            if not hit and has_bounds:
                hit = x < bounds[0] or x > bounds[2] or y < bounds[1] or y > bounds[3]
            if not hit:
                for j in range(nc):
                    k = keep_c[j]
                    ex, ey = x - circles[k, 0], y - circles[k, 1]
                    if ex * ex + ey * ey <= circles[k, 2]:
                        hit = True
                        break
            if not hit:
                for j in range(nr):
                    k = keep_r[j]
                    if x >= rects[k, 0] and x <= rects[k, 2] and y >= rects[k, 1] and y <= rects[k, 3]:
                        hit = True
                        break
            if hit:
                hits += 1
        out[i] = hits * penalty  # rounded once to the dtype, as torch's float(hits) * penalty is
        out[i] = cost + out[i]
