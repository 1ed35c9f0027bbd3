"""The paper's scenes built from obstacles: the U-shaped trap (:func:`u_shape`) and which way it opens."""

from __future__ import annotations

from collections.abc import Sequence

from cuniform_torch.common.options import Option, option_label
from cuniform_torch.envs.shapes import Polygon, _number, _point

__all__ = ["Opening", "u_shape"]


@option_label('opening')
class Opening(Option):
    """Which way the pocket of a :func:`u_shape` opens."""

    POS_X = "+x"
    NEG_X = "-x"
    POS_Y = "+y"
    NEG_Y = "-y"



def u_shape(
    center: Sequence[float],
    width: float,
    depth: float,
    thickness: float,
    opening: str | Opening = "+x",
    appear_time: float = 0.0,
) -> Polygon:
    """A U-shaped trap as one 8-vertex :class:`Polygon`.

    Geometry, for ``opening="+x"`` (the other openings are the same shape turned by 90, 180 or 270 degrees
    about ``center``): the outer outline is the ``depth`` (along x) by ``width`` (along y) rectangle centred at
    ``center = (cx, cy)``. Its base wall is the strip ``x in [cx - depth/2, cx - depth/2 + thickness]``; the two
    side walls are the strips ``y in [cy - width/2, cy - width/2 + thickness]`` and
    ``y in [cy + width/2 - thickness, cy + width/2]``, running the full depth. The free pocket is
    ``x in (cx - depth/2 + thickness, cx + depth/2]``, ``y in (cy - width/2 + thickness, cy + width/2 - thickness)``,
    open towards +x. A robot that approaches from the +x side and aims at a goal beyond the base (at -x) drives
    into the pocket: the paper's U-shaped trap.

    Needs ``width > 2 thickness`` and ``depth > thickness`` (so the pocket is not empty).
    """
    cx, cy = _point(center, "center", "u_shape")
    w = _number(width, "width", "u_shape")
    dpt = _number(depth, "depth", "u_shape")
    t = _number(thickness, "thickness", "u_shape")
    if w <= 0 or dpt <= 0 or t <= 0:
        raise ValueError(f"u_shape: width, depth and thickness must be > 0, got {width!r}, {depth!r}, {thickness!r}")
    if not w > 2 * t:
        raise ValueError(f"u_shape: width ({w}) must exceed twice the thickness ({t}) to leave a pocket")
    if not dpt > t:
        raise ValueError(f"u_shape: depth ({dpt}) must exceed the thickness ({t}) to leave a pocket")
    a, b = 0.5 * dpt, 0.5 * w
    local = [  # opening towards +x, counter-clockwise
        (a, b), (-a, b), (-a, -b), (a, -b),
        (a, -b + t), (-a + t, -b + t), (-a + t, b - t), (a, b - t),
    ]
    turn = {  # exact quarter turns of the local frame
        Opening.POS_X: lambda x, y: (x, y),
        Opening.POS_Y: lambda x, y: (-y, x),
        Opening.NEG_X: lambda x, y: (-x, -y),
        Opening.NEG_Y: lambda x, y: (y, -x),
    }[Opening.parse(opening)]
    verts = [(cx + px, cy + py) for px, py in (turn(x, y) for x, y in local)]
    return Polygon(verts, appear_time=appear_time)
