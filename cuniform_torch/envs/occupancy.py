"""A boolean occupancy grid as an obstacle (a costmap): one gather per query, any batch shape.

Shapes used in this module: ``...`` any batch shape, H x W grid cells. The grid keeps the user's tensor and
requires ``xy`` on its device (see :meth:`OccupancyGrid.to`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from cuniform_torch.envs.shapes import _appear_time, _check_xy, _number, _point

__all__ = ["OccupancyGrid"]


@dataclass(frozen=True, eq=False)
class OccupancyGrid:
    """A boolean occupancy grid: cell ``(i, j)`` (row i, column j) covers
    ``x in [x0 + j res, x0 + (j+1) res)`` and ``y in [y0 + i res, y0 + (i+1) res)``. Points outside are free.

    ``contains`` needs ``xy`` on the device of ``occupied``; use :meth:`to` for a copy on another device.
    """

    occupied: Tensor
    """``bool [H, W]``; row index i is y, column index j is x"""
    origin: tuple[float, float] = (0.0, 0.0)
    """(x0, y0): the lower-left corner of cell (0, 0), m"""
    resolution: float = 1.0
    """cell side, m, > 0"""
    appear_time: float = 0.0
    """time (s) from which the robot senses it"""

    def __post_init__(self) -> None:
        occ = self.occupied
        if not isinstance(occ, torch.Tensor):
            raise ValueError(f"OccupancyGrid: occupied must be a bool torch.Tensor [H, W], got {type(occ).__name__}")
        if occ.dtype != torch.bool:
            raise ValueError(f"OccupancyGrid: occupied must have dtype torch.bool, got {occ.dtype}")
        if occ.ndim != 2 or occ.shape[0] < 1 or occ.shape[1] < 1:
            raise ValueError(f"OccupancyGrid: occupied must have shape [H, W] with H, W >= 1, got {list(occ.shape)}")
        object.__setattr__(self, "origin", _point(self.origin, "origin", "OccupancyGrid"))
        res = _number(self.resolution, "resolution", "OccupancyGrid")
        if res <= 0:
            raise ValueError(f"OccupancyGrid: resolution must be > 0, got {self.resolution!r}")
        object.__setattr__(self, "resolution", res)
        object.__setattr__(self, "appear_time", _appear_time(self.appear_time, "OccupancyGrid"))

    def to(self, device: torch.device | str) -> OccupancyGrid:
        """The same grid with ``occupied`` on ``device``."""
        return OccupancyGrid(self.occupied.to(device), self.origin, self.resolution, self.appear_time)

    def cell_index(self, xy: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """``xy [..., 2]`` -> ``(i, j, inside)``: int64 row and column ``[...]`` (0 outside), ``bool [...]``."""
        _check_xy(xy, "OccupancyGrid.cell_index")
        H, W = self.occupied.shape
        fx = (xy[..., 0] - self.origin[0]) / self.resolution  # [...] column coordinate
        fy = (xy[..., 1] - self.origin[1]) / self.resolution  # [...] row coordinate
        inside = (fx >= 0) & (fx < W) & (fy >= 0) & (fy < H)  # NaN -> outside
        j = torch.where(inside, fx, torch.zeros_like(fx)).floor().long().clamp(0, W - 1)
        i = torch.where(inside, fy, torch.zeros_like(fy)).floor().long().clamp(0, H - 1)
        return i, j, inside

    def contains(self, xy: Tensor) -> Tensor:
        """``xy [..., 2]`` -> ``bool [...]``: whether the cell under each point is occupied."""
        _check_xy(xy, "OccupancyGrid.contains")
        if xy.device != self.occupied.device:
            raise ValueError(
                f"OccupancyGrid.contains: xy is on {xy.device} but the grid is on {self.occupied.device}; "
                f"use grid.to({str(xy.device)!r})"
            )
        i, j, inside = self.cell_index(xy)
        W = self.occupied.shape[1]
        return self.occupied.reshape(-1)[i * W + j] & inside
