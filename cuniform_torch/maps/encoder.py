"""The local map a map-conditioned policy sees, and the small CNN that embeds it.

Shapes: B patches, H x W patch cells, E embedding size, c base channels.

A *patch* is an :class:`~cuniform_torch.envs.OccupancyGrid` in the robot's frame at the start of a rollout
(robot at (0, 0) heading +x; cell ``(i, j)`` covers ``x in [x0 + j r, x0 + (j+1) r)``, ``y in [y0 + i r, ...)``),
occupied = 1, *not* inflated by the robot's radius (the map-table data set's convention). :class:`PatchSpec`
is its shape, resolution and origin, fixed by a checkpoint; a patch of another spec is refused by name.

:class:`MapEncoder` reads the occupancy itself (one channel of 0 / 1; no signed distance: three stride-2 3x3
convolutions already see about 15 cells around each output, which is what the inflation by a robot radius of a
few cells needs) and gives one ``[E]`` embedding per patch.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from torch import Tensor, nn

__all__ = ["PatchSpec", "MapEncoder", "MAX_PATCH_CELLS"]

MAX_PATCH_CELLS = 1 << 20
"""largest H x W a patch spec may describe (a 1024 x 1024 map)"""


@dataclass(frozen=True)
class PatchSpec:
    """Shape ``(H, W)``, cell side ``resolution`` (m) and ``origin`` (x0, y0) (m, robot frame) of a local patch."""

    shape: tuple[int, int]
    resolution: float
    origin: tuple[float, float]

    def __post_init__(self) -> None:
        shape = tuple(self.shape) if isinstance(self.shape, (list, tuple)) else ()
        if len(shape) != 2 or any(isinstance(n, bool) or not isinstance(n, int) or n < 1 for n in shape) \
                or shape[0] * shape[1] > MAX_PATCH_CELLS:
            raise ValueError(f"patch shape must be two positive integers [H, W] (at most {MAX_PATCH_CELLS} cells), "
                             f"got {self.shape!r}")
        res = self.resolution
        if isinstance(res, bool) or not isinstance(res, (int, float)) or not (0 < res < math.inf):
            raise ValueError(f"patch resolution must be a positive finite number (m), got {res!r}")
        origin = tuple(self.origin) if isinstance(self.origin, (list, tuple)) else ()
        if len(origin) != 2 or any(isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v)
                                   for v in origin):
            raise ValueError(f"patch origin must be two finite numbers [x0, y0] (m), got {self.origin!r}")
        object.__setattr__(self, "shape", (int(shape[0]), int(shape[1])))
        object.__setattr__(self, "resolution", float(res))
        object.__setattr__(self, "origin", (float(origin[0]), float(origin[1])))

    @classmethod
    def from_dict(cls, value: Any) -> PatchSpec:
        """From ``{"shape": [H, W], "resolution": r, "origin": [x0, y0]}`` (the data set's and checkpoint's)."""
        if not isinstance(value, dict) or set(value) != {"shape", "resolution", "origin"}:
            raise ValueError(f"a patch spec must be a dict of shape, resolution and origin, got "
                             f"{sorted(value) if isinstance(value, dict) else type(value).__name__}")
        return cls(value["shape"], value["resolution"], value["origin"])

    def to_dict(self) -> dict[str, Any]:
        return {"shape": list(self.shape), "resolution": self.resolution, "origin": list(self.origin)}

    def check(self, patch: object, who: str = "patch") -> Tensor:
        """``patch`` (a robot-frame OccupancyGrid) -> its ``bool [H, W]`` cells; ValueError naming what differs."""
        occupied = getattr(patch, "occupied", None)
        if not isinstance(occupied, Tensor) or not hasattr(patch, "resolution") or not hasattr(patch, "origin"):
            raise ValueError(f"{who} must be an OccupancyGrid in the robot frame (see cuniform_torch.maps.sensing."
                             f"local_map), got {type(patch).__name__}")
        if tuple(occupied.shape) != self.shape:
            raise ValueError(f"{who} has {list(occupied.shape)} cells but the policy was trained on patches of "
                             f"{list(self.shape)}")
        if not math.isclose(float(patch.resolution), self.resolution, rel_tol=1e-6):
            raise ValueError(f"{who} has resolution {patch.resolution} m but the policy was trained at "
                             f"{self.resolution} m")
        tol = 1e-6 * max(1.0, self.resolution)
        if any(abs(float(a) - b) > tol for a, b in zip(patch.origin, self.origin)):
            raise ValueError(f"{who} has origin {tuple(patch.origin)} (robot frame) but the policy was trained with "
                             f"origin {self.origin}")
        return occupied


class MapEncoder(nn.Module):
    """``occupancy [B, H, W]`` (0 / 1) -> ``[B, E]``: three stride-2 3x3 convolutions (c, 2c, 2c channels, SiLU),
    flattened, then a linear layer. The flatten keeps where things are, which is what the policy needs."""

    def __init__(self, shape: tuple[int, int], embed: int = 32, channels: int = 8):
        super().__init__()
        c = channels
        self.conv = nn.Sequential(
            nn.Conv2d(1, c, 3, stride=2, padding=1), nn.SiLU(),
            nn.Conv2d(c, 2 * c, 3, stride=2, padding=1), nn.SiLU(),
            nn.Conv2d(2 * c, 2 * c, 3, stride=2, padding=1), nn.SiLU(),
        )
        h, w = shape
        for _ in range(3):  # output size of a stride-2, padding-1 3x3 convolution
            h, w = (h - 1) // 2 + 1, (w - 1) // 2 + 1
        self.out = nn.Linear(2 * c * h * w, embed)

    def forward(self, occupancy: Tensor) -> Tensor:
        """``[B, H, W]`` float occupancy -> ``[B, E]`` embeddings."""
        z = self.conv(occupancy.unsqueeze(1))  # [B, 2c, h, w]
        return self.out(z.flatten(1))  # [B, E]
