"""Local map features of a :class:`~cuniform_torch.maps.policy.MapPolicy` (``local_features = C > 0``): what the
patch looks like *at* the queried state and just ahead of it.

Shapes: B or U patches, C channels, H x W patch cells, N states, P probe points, d state dimensions.

:class:`LocalFeatures` is a stride-1 stack of three bias-free 3x3 convolutions over the occupancy patch
(1 -> C -> C -> C channels, SiLU between; the middle one dilated by 2, so each output sees 9 x 9 cells: 0.45 m at
0.05 m cells). Stride 1 keeps output cell (i, j) centred on patch cell (i, j); no biases and SiLU(0) = 0 make
the features of free space exactly 0, the same value ``grid_sample``'s zero padding reads outside the patch, so
off the patch is free. :meth:`LocalFeatures.sample` reads that map bilinearly at the :data:`PROBES` of each
state, placed in the state's own frame by its heading (dimensions 0, 1, 2 = x, y, heading, start frame as the
patch): the state itself, 0.25, 0.5 and 0.75 m straight ahead, and 0.5 m ahead 0.3 m to each side (which side
is blocked is what a turn needs). Cell (i, j)'s centre is at ``origin + (j + 0.5, i + 0.5) * resolution`` (row i
= y, column j = x), which is where ``grid_sample(align_corners=False)`` puts pixel (i, j) of a map spanning the
patch's outer edges.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from cuniform_torch.maps.encoder import PatchSpec

__all__ = ["PROBES", "LocalFeatures"]

PROBES: tuple[tuple[float, float], ...] = ((0.0, 0.0), (0.25, 0.0), (0.5, 0.0), (0.75, 0.0), (0.5, 0.3), (0.5, -0.3))
"""probe points (ahead, left) in metres in the state's frame; a lookup reads ``len(PROBES) * C`` features"""


class LocalFeatures(nn.Module):
    """``occupancy [B, H, W]`` -> feature map ``[B, C, H, W]``; :meth:`sample` reads it at states' probes."""

    probes: Tensor  # buffers, declared so they read back as Tensor
    _to_unit: Tensor
    _origin: Tensor

    def __init__(self, spec: PatchSpec, channels: int):
        super().__init__()
        c = channels
        self.spec, self.channels = spec, c
        self.conv = nn.Sequential(
            nn.Conv2d(1, c, 3, padding=1, bias=False), nn.SiLU(),
            nn.Conv2d(c, c, 3, padding=2, dilation=2, bias=False), nn.SiLU(),
            nn.Conv2d(c, c, 3, padding=1, bias=False),
        )
        self.register_buffer("probes", torch.tensor(PROBES, dtype=torch.float32), persistent=False)  # [P, 2]
        H, W = spec.shape
        # physical (x, y) -> grid_sample's normalised (u, v): the patch's outer edges are -1 and +1
        span = torch.tensor([W * spec.resolution, H * spec.resolution], dtype=torch.float64)
        self.register_buffer("_to_unit", (2.0 / span).float(), persistent=False)  # [2]
        self.register_buffer("_origin", torch.tensor(spec.origin, dtype=torch.float32), persistent=False)  # [2]

    @property
    def num_outputs(self) -> int:
        """Features per lookup: ``P * C``."""
        return len(PROBES) * self.channels

    def forward(self, occupancy: Tensor) -> Tensor:
        """``[B, H, W]`` float occupancy (0 / 1) -> ``[B, C, H, W]`` (0 wherever 9 x 9 cells around are free)."""
        return self.conv(occupancy.unsqueeze(1))

    def grid(self, xy: Tensor, cos: Tensor, sin: Tensor) -> Tensor:
        """States' ``xy [N, 2]`` and heading ``cos, sin [N]`` -> their probes in grid_sample units ``[N, P, 2]``."""
        ahead, left = self.probes[:, 0], self.probes[:, 1]  # [P]
        px = xy[:, :1] + cos[:, None] * ahead - sin[:, None] * left  # [N, P]
        py = xy[:, 1:2] + sin[:, None] * ahead + cos[:, None] * left
        pts = torch.stack((px, py), dim=-1)  # [N, P, 2] (x -> column, y -> row: grid_sample's (u, v) order)
        return (pts - self._origin) * self._to_unit - 1.0

    def sample(self, fmap: Tensor, x: Tensor, which: Tensor | None = None) -> Tensor:
        """Bilinear reads of ``fmap [U, C, H, W]`` at the probes of ``x [N, d]``; row n reads map ``which[n]``
        (``[N]`` int64; None: U must be 1) -> ``[N, P * C]`` (probe-major). One ``grid_sample`` call either way:
        with several maps, each map's rows are packed into its own batch slot (padded to the largest count)."""
        x = x.to(fmap.dtype)
        ang = x[:, 2]
        g = self.grid(x[:, :2], torch.cos(ang), torch.sin(ang)).to(fmap.dtype)  # [N, P, 2]
        return self.read(fmap, g, which)

    def read(self, fmap: Tensor, g: Tensor, which: Tensor | None = None) -> Tensor:
        """``fmap [U, C, H, W]`` at grid points ``g [N, P, 2]`` (see :meth:`sample`) -> ``[N, P * C]``."""
        N, P = g.shape[0], g.shape[1]
        if N == 0:
            return fmap.new_zeros(0, P * self.channels)
        if which is None:
            if fmap.shape[0] != 1:
                raise ValueError(f"{fmap.shape[0]} feature maps need `which`, the map of each state")
            out = F.grid_sample(fmap, g.unsqueeze(0), mode="bilinear", padding_mode="zeros", align_corners=False)
            return out[0].permute(1, 2, 0).reshape(N, P * self.channels)  # [C, N, P] -> [N, P * C]
        U = fmap.shape[0]
        counts = torch.bincount(which, minlength=U)  # [U]
        order = torch.argsort(which, stable=True)
        first = torch.cumsum(counts, 0) - counts  # [U] first packed row of each map
        slot = torch.empty_like(which)
        slot[order] = torch.arange(N, device=which.device) - first[which[order]]  # [N] row within its map's slot
        packed = g.new_zeros(U, int(counts.max()), P, 2)
        packed[which, slot] = g
        out = F.grid_sample(fmap, packed, mode="bilinear", padding_mode="zeros", align_corners=False)  # [U, C, n, P]
        return out[which, :, slot].transpose(1, 2).reshape(N, P * self.channels)  # [N, C, P] -> [N, P * C]
