"""The compiled loop of :func:`~cuniform_torch.maps.sensing.sense_patch` on an
:class:`~cuniform_torch.envs.Environment` of discs and rectangles (numba, imported when first used; module-level,
so numba's disk cache finds it in the next process).

Shapes: B poses, P = H x W patch cells, C discs, R rectangles.

Per pose: every cell centre to world coordinates, then each tested against the rectangles that can touch the
patch and the discs binned with it (a square grid over the patch's box: a point meets only its bin's few discs). The arithmetic is the torch path's, operation by operation in the points' dtype:
``(x + c lx) - s ly`` and ``(y + s lx) + c ly`` (no fused multiply-add: numba contracts only under fastmath),
``Environment.in_collision``'s non-finite, bounds, disc and rectangle tests (those of
:mod:`~cuniform_torch.envs.contains_loops`), so every cell reads what the torch path reads, to the last bit.
"""

from __future__ import annotations

import math

import numpy as np

from cuniform_torch.common.compiled import njit

__all__ = ["sense_poses"]


@njit(nogil=True, boundscheck=False)
def sense_poses(px, py, cos, sin, lx, ly, circles, rects, bounds, hit):
    """``hit [B, P]``: cell ``p`` of pose ``b`` (``px, py, cos, sin [B]``; robot-frame centres ``lx, ly [P]``) is
    non-finite, outside ``bounds [4]`` (xmin, ymin, xmax, ymax; empty: none), or inside a disc of ``circles [C, 3]``
    (x, y, r^2) or a rectangle of ``rects [R, 4]``."""
    n_cells = lx.shape[0]
    wx = np.empty(n_cells, dtype=lx.dtype)
    wy = np.empty(n_cells, dtype=lx.dtype)
    near_c = np.empty(circles.shape[0], dtype=np.int64)
    near_r = np.empty(rects.shape[0], dtype=np.int64)
    listed = np.empty(4 * circles.shape[0] + 1, dtype=np.int64)  # the binned discs' indices, bin by bin
    for b in range(px.shape[0]):
        lo_x, lo_y, hi_x, hi_y = math.inf, math.inf, -math.inf, -math.inf
        for p in range(n_cells):
            x = (px[b] + cos[b] * lx[p]) - sin[b] * ly[p]
            y = (py[b] + sin[b] * lx[p]) + cos[b] * ly[p]
            wx[p], wy[p] = x, y
            if math.isfinite(x) and math.isfinite(y):  # the box of the finite points (NaN ones are hits anyway)
                lo_x, hi_x = min(lo_x, float(x)), max(hi_x, float(x))
                lo_y, hi_y = min(lo_y, float(y)), max(hi_y, float(y))
        # the discs and rectangles that meet that box (as Environment's prefilter, in float64 with its margin): a
        # point inside one is inside the box, so the rest cannot contain one
        n_c = 0
        r_max = 0.0
        for k in range(circles.shape[0]):
            cx, cy = float(circles[k, 0]), float(circles[k, 1])
            gx = cx - min(max(cx, lo_x), hi_x)
            gy = cy - min(max(cy, lo_y), hi_y)
            if gx * gx + gy * gy <= float(circles[k, 2]) * (1 + 1e-4) + 1e-12:
                near_c[n_c] = k
                n_c += 1
                r_max = max(r_max, math.sqrt(float(circles[k, 2])))
        n_r = 0
        for k in range(rects.shape[0]):
            if rects[k, 0] <= hi_x and rects[k, 2] >= lo_x and rects[k, 1] <= hi_y and rects[k, 3] >= lo_y:
                near_r[n_r] = k
                n_r += 1
        # those discs binned by a square grid over the box: a point is tested against its bin's discs only, each
        # disc listed in every bin its bounding square (widened by a margin for the points' rounding) meets
        side = max(2.0 * r_max, (max(hi_x - lo_x, hi_y - lo_y) + 1e-9) / 64.0, 1e-9)  # at most 64 x 64 bins
        nx = min(64, int((hi_x - lo_x) / side) + 1) if n_c else 1
        ny = min(64, int((hi_y - lo_y) / side) + 1) if n_c else 1
        start = np.zeros(nx * ny + 1, dtype=np.int64)
        for j in range(2):  # pass 0 counts each bin's discs, pass 1 lists them
            fill = start[:-1].copy()
            for m in range(n_c):
                k = near_c[m]
                reach = math.sqrt(float(circles[k, 2])) * (1 + 1e-4) + 1e-9
                cx, cy = float(circles[k, 0]), float(circles[k, 1])
                i0 = max(0, int(math.floor((cx - reach - lo_x) / side)))
                i1 = min(nx - 1, int(math.floor((cx + reach - lo_x) / side)))
                j0 = max(0, int(math.floor((cy - reach - lo_y) / side)))
                j1 = min(ny - 1, int(math.floor((cy + reach - lo_y) / side)))
                for bj in range(j0, j1 + 1):
                    for bi in range(i0, i1 + 1):
                        cell = bj * nx + bi
                        if j == 0:
                            start[cell + 1] += 1
                        else:
                            listed[fill[cell]] = k
                            fill[cell] += 1
            if j == 0:
                for cell in range(nx * ny):
                    start[cell + 1] += start[cell]
                if listed.shape[0] < start[nx * ny]:
                    listed = np.empty(start[nx * ny], dtype=np.int64)
        for p in range(n_cells):
            x, y = wx[p], wy[p]
            found = not (math.isfinite(x) and math.isfinite(y))
            if not found and bounds.shape[0] == 4:
                found = x < bounds[0] or x > bounds[2] or y < bounds[1] or y > bounds[3]
            if not found and n_c:
                bi = min(nx - 1, max(0, int(math.floor((float(x) - lo_x) / side))))
                bj = min(ny - 1, max(0, int(math.floor((float(y) - lo_y) / side))))
                cell = bj * nx + bi
                for m in range(start[cell], start[cell + 1]):
                    k = listed[m]
                    dx, dy = x - circles[k, 0], y - circles[k, 1]
                    if dx * dx + dy * dy <= circles[k, 2]:
                        found = True
                        break
            if not found:
                for m in range(n_r):
                    k = near_r[m]
                    if x >= rects[k, 0] and x <= rects[k, 2] and y >= rects[k, 1] and y <= rects[k, 3]:
                        found = True
                        break
            hit[b, p] = found
