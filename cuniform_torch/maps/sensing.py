"""Local-map sensing: the robot-frame patch a map-conditioned policy reads, cropped from a world occupancy grid.

Shapes: B poses, H x W patch cells.

:func:`sense_patch` turns each patch cell's centre (robot frame, :class:`~cuniform_torch.maps.encoder.PatchSpec`)
into world coordinates by the pose's rigid transform and reads the world grid there: one vectorised gather for
all cells (and all poses), no loop. Like a costmap it is range-limited: a cell whose centre lies farther than
``max_range`` from the robot reads free, and so does everything outside the world grid (the
:class:`~cuniform_torch.envs.OccupancyGrid` convention). :func:`local_map` wraps one pose's patch as a robot-frame
``OccupancyGrid``, the type :meth:`MapPolicy.set_map <cuniform_torch.maps.policy.MapPolicy.set_map>` takes.

The world may also be an :class:`~cuniform_torch.envs.Environment` (shapes): a cell is then occupied when its
centre is inside an obstacle sensed at ``time`` or outside the bounds (``Environment.in_collision``, the map
farm's rule for its patches), at one ``contains`` per obstacle instead of one gather.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable

import torch
from torch import Tensor

from cuniform_torch.common.compiled import optional_loop
from cuniform_torch.envs.environment import Environment
from cuniform_torch.envs.occupancy import OccupancyGrid
from cuniform_torch.envs.shapes import Circle
from cuniform_torch.maps.encoder import PatchSpec

__all__ = ["patch_centres", "sense_patch", "local_map", "warm_up"]


_CENTRES: dict[tuple, Tensor] = {}
"""patch centres per (patch, dtype, device): made once (a copy to a GPU per command would wait for it, and could not
run inside a CUDA graph)"""


def patch_centres(spec: PatchSpec, dtype: torch.dtype = torch.float32,
                  device: torch.device | str | None = None) -> Tensor:
    """The robot-frame (x, y) of every patch cell's centre: ``[H, W, 2]`` (cached: do not write into it)."""
    key = (tuple(spec.shape), spec.resolution, tuple(spec.origin), dtype, torch.device(device or "cpu"))
    centres = _CENTRES.get(key)
    if centres is None:
        centres = _CENTRES[key] = _patch_centres(spec, dtype, device)
    return centres


def _patch_centres(spec: PatchSpec, dtype: torch.dtype, device: torch.device | str | None) -> Tensor:
    H, W = spec.shape
    r = spec.resolution
    xs = spec.origin[0] + (torch.arange(W, dtype=torch.float64) + 0.5) * r  # [W]
    ys = spec.origin[1] + (torch.arange(H, dtype=torch.float64) + 0.5) * r  # [H]
    grid = torch.stack((xs.expand(H, W), ys.unsqueeze(1).expand(H, W)), dim=-1)  # [H, W, 2]
    return grid.to(dtype=dtype, device=device)


def sense_patch(world: OccupancyGrid | Environment, pose: Tensor, spec: PatchSpec, max_range: float | None = None,
                time: float | None = None, compiled: bool = True) -> Tensor:
    """``pose [3]`` (or ``[B, 3]``: world x, y, heading) -> ``bool [H, W]`` (or ``[B, H, W]``) occupancy of the
    patch in that pose's frame. A grid ``world`` must be on the pose's device; ``max_range`` (m) limits what is
    seen; ``time`` (s) selects an Environment's obstacles sensed by then (None: all). ``compiled``: an Environment
    of discs and rectangles on a CPU is sensed by one compiled loop (:mod:`~cuniform_torch.maps.sensing_loops`,
    the same cells to the last bit) where numba is installed; False: always the torch path."""
    if not isinstance(world, (OccupancyGrid, Environment)):
        raise ValueError(f"world must be an OccupancyGrid or an Environment, got {type(world).__name__}")
    if not isinstance(pose, Tensor) or not pose.is_floating_point() or pose.shape[-1:] != (3,) or pose.ndim > 2:
        raise ValueError(f"pose must be a floating-point [3] or [B, 3] tensor (x, y, heading), got "
                         f"{list(pose.shape) if isinstance(pose, Tensor) else type(pose).__name__}")
    if max_range is not None and (isinstance(max_range, bool) or not isinstance(max_range, (int, float))
                                  or not max_range > 0 or math.isnan(max_range)):
        raise ValueError(f"max_range must be a positive number (m) or None, got {max_range!r}")
    if isinstance(world, OccupancyGrid) and world.occupied.device != pose.device:
        raise ValueError(f"pose is on {pose.device} but the world grid is on {world.occupied.device}; "
                         f"use world.to({str(pose.device)!r})")
    poses = pose.reshape(-1, 3)  # [B, 3]
    local = patch_centres(spec, pose.dtype, pose.device)  # [H, W, 2]
    lx, ly = local[..., 0], local[..., 1]  # [H, W]
    seen = _sense_compiled(world, poses, local, time) if compiled else None  # [B, H, W]
    if seen is None:
        c, s = torch.cos(poses[:, 2]).view(-1, 1, 1), torch.sin(poses[:, 2]).view(-1, 1, 1)  # [B, 1, 1]
        wx = poses[:, 0].view(-1, 1, 1) + c * lx - s * ly  # [B, H, W]
        wy = poses[:, 1].view(-1, 1, 1) + s * lx + c * ly
        xy = torch.stack((wx, wy), dim=-1)  # [B, H, W, 2]
        seen = world.contains(xy) if isinstance(world, OccupancyGrid) else world.in_collision(xy, time)
    if max_range is not None:
        seen = seen & (lx.square() + ly.square() <= max_range * max_range)
    return seen if pose.ndim == 2 else seen[0]


def _loop() -> Callable[..., None] | None:
    """The compiled sensing loop, or None without numba."""
    return optional_loop("cuniform_torch.maps.sensing_loops", "sense_poses")


@functools.cache
def warm_up() -> None:
    """Compile (or load from numba's disk cache) the sensing loop now, for float32 poses: a controller calls this
    when it is made, so that no control cycle pays for the compilation (seconds). Nothing without numba."""
    world = Environment([Circle((0.0, 0.0), 0.1)], bounds=(-1.0, -1.0, 1.0, 1.0))
    _sense_compiled(world, torch.zeros((1, 3)), patch_centres(PatchSpec((2, 2), 0.1, (-0.1, -0.1))), None)


def _sense_compiled(world: OccupancyGrid | Environment, poses: Tensor, local: Tensor,
                    time: float | None) -> Tensor | None:
    """``bool [B, H, W]`` of the patch centres ``local [H, W, 2]`` at ``poses [B, 3]`` by the compiled loop, or None
    where it does not apply (a grid world, not a CPU, a dtype other than float32 / float64, an obstacle other than
    a Circle or Rect, no numba): the torch path then senses."""
    if not isinstance(world, Environment) or poses.device.type != "cpu" \
            or poses.dtype not in (torch.float32, torch.float64):
        return None
    # the Environment's own tables of its discs and rectangles (cached there while the obstacles are the same)
    circles, rects, others = world._visible_tables(time, torch.float64)
    loop = _loop() if not others else None
    if loop is None:
        return None
    h, w = local.shape[:2]
    lx, ly, circ, rect, bounds = _loop_tables(world, circles, rects, local)
    poses = poses.detach().contiguous()
    seen = torch.empty((poses.shape[0], h * w), dtype=torch.bool)
    loop(poses[:, 0].numpy(), poses[:, 1].numpy(), torch.cos(poses[:, 2]).numpy(), torch.sin(poses[:, 2]).numpy(),
         lx, ly, circ, rect, bounds, seen.numpy())
    return seen.view(-1, h, w)


_TABLES: dict[tuple, tuple] = {}
"""the loop's arrays per world's tables, patch centres and dtype (the last few: made once, not per command)"""


def _loop_tables(world: Environment, circles: Tensor, rects: Tensor, local: Tensor) -> tuple:
    """The loop's arrays in the points' dtype: the centres' ``lx, ly [P]``, ``circles [C, 3]``, ``rects [R, 4]``
    and the bounds ``[4]`` (empty: none; cast to the points' dtype, as the torch path's comparisons cast them),
    cached while the world's tables (the objects themselves), the centres and the bounds are the same."""
    key = (id(circles), id(rects), id(local), local.dtype, world.bounds)
    hit = _TABLES.get(key)
    if hit is not None and hit[0] is circles and hit[1] is rects and hit[2] is local:
        return hit[3]
    dtype = local.dtype
    bounds = torch.tensor(world.bounds, dtype=dtype) if world.bounds is not None else torch.zeros(0, dtype=dtype)
    arrays = (local[..., 0].reshape(-1).numpy(), local[..., 1].reshape(-1).numpy(), circles.to(dtype).numpy(),
              rects.to(dtype).numpy(), bounds.numpy())
    if len(_TABLES) >= 8:  # a few worlds at a time; an old one is dropped rather than kept alive
        _TABLES.pop(next(iter(_TABLES)))
    _TABLES[key] = (circles, rects, local, arrays)
    return arrays


def local_map(world: OccupancyGrid | Environment, pose: Tensor, spec: PatchSpec, max_range: float | None = None,
              time: float | None = None) -> OccupancyGrid:
    """The patch at ``pose [3]`` as a robot-frame OccupancyGrid (its origin and resolution are ``spec``'s)."""
    if isinstance(pose, Tensor) and pose.ndim != 1:
        raise ValueError(f"local_map takes one pose [3], got {list(pose.shape)}; sense_patch takes a batch")
    return OccupancyGrid(sense_patch(world, pose, spec, max_range, time), spec.origin, spec.resolution)
