"""The navigation benchmark's robot: a registered system, its parameters, its body radius and its horizon.

The built-in robot (:data:`NAV_ROBOT`) is a differential-drive base driven as a unicycle: a cruise speed of
0.5 m/s and 7 turn rates evenly in [-1.5, 1.5] rad/s (the library's ``dubins`` system with those parameters),
dt = 0.2 s, a disc of radius 0.2 m (BARN's narrowest passages are about 0.6-0.7 m wide between cylinder
surfaces), a controller horizon of 15 steps (3 s, 1.5 m ahead), cells of 0.05 m x 0.05 m x 10 degrees.

The ``narrow`` suite is driven by a faster robot (:data:`FAST_ROBOT`, :func:`suite_robot`): the same unicycle at
1.0 m/s with cells of 0.1 m x 0.1 m x 10 degrees, the built-in lattice scaled by two in x and y (a step of 0.2 m
is two cells for both), the same turn rates (a 0.67 m turning radius instead of 0.33 m), body and horizon (3 s,
3 m ahead). A preset's speed is part of its tables (:meth:`RobotPreset.fingerprint`), so this robot has its own.

Any registered system can drive the suites instead (:class:`RobotPreset` with another ``system`` name and
``params``); it needs ``(x, y, heading, ...)`` states. The C-Uniform files a robot needs are built and cached by
:mod:`eval.navigate.robot_files`.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import asdict, dataclass, field
from typing import Any

from cuniform_torch.systems import make_system

__all__ = ["RobotPreset", "NAV_ROBOT", "FAST_ROBOT", "SUITE_ROBOTS", "suite_robot", "preset_dict"]


@dataclass(frozen=True)
class RobotPreset:
    """A robot for the navigation suites: a registered system, its parameters, its body radius, its horizon."""

    system: str = "dubins"
    """registered system name (``cuniform_torch.systems.known_systems()``)"""
    params: dict = field(default_factory=lambda: dict(speed=0.5, dt=0.2, max_omega=1.5, num_actions=7,
                                                      cell_size=[0.05, 0.05, 2 * math.pi / 36]))
    """the system's parameters (JSON types)"""
    radius: float = 0.2
    """m: the robot is a disc of this radius (obstacles are inflated by it)"""
    horizon: int = 15
    """controller horizon and table depth, steps"""
    starts: str | None = None
    """a table set over these starts (``precompute.build --starts SPEC``) instead of one table: a system whose
    state has more than a pose (a speed) needs tables from the starts it meets; each rollout uses the nearest"""

    def make_system(self):
        """The system these parameters describe."""
        return make_system(self.system, **self.params)

    def fingerprint(self, method: str = "maxflow") -> str:
        """A short hash of everything that defines this robot's table of ``method``."""
        record = dict(system=self.system, params=self.params, horizon=self.horizon, method=method)
        if self.starts is not None:  # absent otherwise, so the one-table robots keep their cached files
            record["starts"] = self.starts
        blob = json.dumps(record, sort_keys=True)
        return hashlib.sha256(blob.encode()).hexdigest()[:10]


NAV_ROBOT = RobotPreset()
"""the built-in robot of :mod:`eval.navigate.run` (module docstring)"""

FAST_ROBOT = RobotPreset(params=dict(speed=1.0, dt=0.2, max_omega=1.5, num_actions=7,
                                     cell_size=[0.1, 0.1, 2 * math.pi / 36]))
"""the ``narrow`` suite's robot: :data:`NAV_ROBOT` at 1.0 m/s on cells twice as wide (module docstring)"""

SUITE_ROBOTS: dict[str, RobotPreset] = {"narrow": FAST_ROBOT}
"""the suites driven by another robot than :data:`NAV_ROBOT`"""


def suite_robot(suite: str) -> RobotPreset:
    """The robot that drives ``suite`` when none is given: :data:`SUITE_ROBOTS`' entry, else :data:`NAV_ROBOT`."""
    return SUITE_ROBOTS.get(suite, NAV_ROBOT)


def preset_dict(robot: RobotPreset) -> dict[str, Any]:
    """The preset as JSON types, for the benchmark's config record (``starts`` only when set, so the records of
    one-table runs stay as they were)."""
    out = asdict(robot)
    if out["starts"] is None:
        del out["starts"]
    return out
