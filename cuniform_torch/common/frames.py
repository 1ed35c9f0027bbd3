"""Planar rigid-motion changes of frame for SE(2)-invariant systems (state = x, y, theta, then other dims).

Shapes: ``...`` any batch shape, d >= 3 state dimensions. Dimensions after the third pass through unchanged.
"""

from __future__ import annotations

import torch
from torch import Tensor

from cuniform_torch.common.checks import wrap_angle

__all__ = ["se2_to_world", "se2_to_local"]


def _check(states: Tensor, pose: Tensor) -> None:
    if states.shape[-1] < 3 or pose.shape[-1] != states.shape[-1]:
        raise ValueError(
            f"SE(2) frame change needs states and poses with the same last dimension >= 3 (x, y, theta, ...); "
            f"got {list(states.shape)} and {list(pose.shape)}"
        )


def se2_to_world(local: Tensor, pose: Tensor) -> Tensor:
    """States expressed relative to ``pose`` -> world states. ``local [..., d]``, ``pose`` broadcastable ``[..., d]``.

    One fused op per column (this runs on every start-relative rollout): ``x, y`` rotated by the pose's heading
    and translated, the heading added and wrapped to ``[-pi, pi)``, further dimensions unchanged.
    """
    _check(local, pose)
    theta = pose[..., 2]
    c, s = torch.cos(theta), torch.sin(theta)
    lx, ly = local[..., 0], local[..., 1]
    x = torch.addcmul(pose[..., 0], lx, c).addcmul_(ly, s, value=-1.0)
    y = torch.addcmul(pose[..., 1], lx, s).addcmul_(ly, c)
    heading = wrap_angle(local[..., 2] + theta)
    x, y, heading = torch.broadcast_tensors(x, y, heading)
    world = x.new_empty((*x.shape, local.shape[-1]))  # written column by column: cheaper than a stack on a CPU
    world[..., 0], world[..., 1], world[..., 2] = x, y, heading
    if local.shape[-1] > 3:
        world[..., 3:] = local[..., 3:]
    return world


def se2_to_local(world: Tensor, pose: Tensor) -> Tensor:
    """World states -> states relative to ``pose`` (inverse of :func:`se2_to_world`)."""
    _check(world, pose)
    c, s = torch.cos(pose[..., 2:3]), torch.sin(pose[..., 2:3])
    dx, dy = world[..., 0:1] - pose[..., 0:1], world[..., 1:2] - pose[..., 1:2]
    x = c * dx + s * dy
    y = -s * dx + c * dy
    th = wrap_angle(world[..., 2:3] - pose[..., 2:3])
    return torch.cat((x, y, th, world[..., 3:]), dim=-1)
