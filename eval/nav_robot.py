"""The navigation benchmark's robot, and its C-Uniform files built on first use and cached.

The built-in robot (:data:`NAV_ROBOT`) is a differential-drive base driven as a unicycle: a cruise speed of
0.5 m/s and 7 turn rates evenly in [-1.5, 1.5] rad/s (the library's ``dubins`` system with those parameters),
dt = 0.2 s, a disc of radius 0.2 m (BARN's narrowest passages are about 0.6-0.7 m wide between cylinder
surfaces), a controller horizon of 15 steps (3 s, 1.5 m ahead), cells of 0.05 m x 0.05 m x 10 degrees. Its
max-flow table (81 329 cells) builds in about 8 s on a laptop CPU.

Any registered system can drive the suites instead (:class:`RobotPreset` with another ``system`` name and
``params``); it needs ``(x, y, heading, ...)`` states. The files a method needs are built by
``python -m precompute.build`` (and ``python -m training.distill`` for the MLP) into a cache folder, named by a
hash of everything that defines them, so a changed preset builds new files and an unchanged one reuses them.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from cuniform_torch.systems import make_system

__all__ = ["RobotPreset", "NAV_ROBOT", "table_file", "policy_file", "ensure_table", "ensure_policy",
           "DISTILL_EPOCHS"]

DISTILL_EPOCHS = 300
"""epochs of the MLP distilled on first use (``training.distill``'s default is 1500; this keeps the first
``cu_mlp`` run to a few minutes on a CPU)"""


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
"""the built-in robot of :mod:`eval.navigate` (module docstring)"""


def table_file(robot: RobotPreset, cache: Path, method: str = "maxflow") -> Path:
    """Where ``robot``'s table of ``method`` (``maxflow`` or ``coverage``) is cached: a file, or a set's folder."""
    stem = f"{robot.system}-{robot.fingerprint(method)}-{method}"
    return Path(cache) / (f"{stem}-set" if robot.starts is not None else f"{stem}.npz")


def policy_file(robot: RobotPreset, cache: Path) -> Path:
    """Where the MLP distilled from ``robot``'s max-flow table is cached."""
    return Path(cache) / f"{robot.system}-{robot.fingerprint('maxflow')}-e{DISTILL_EPOCHS}.policy.pt"


def _build_args(robot: RobotPreset) -> list[str]:
    args = ["--system", robot.system, "--horizon", str(robot.horizon), "--no-report"]
    for key, value in robot.params.items():
        args += ["--param", f"{key}={json.dumps(value)}"]
    return args


def ensure_table(robot: RobotPreset, cache: Path, method: str = "maxflow", quiet: bool = False) -> Path:
    """``robot``'s table of ``method``, built by ``python -m precompute.build`` when not cached yet."""
    path = table_file(robot, cache, method)
    done = path / "tables.json" if robot.starts is not None else path
    if done.exists():
        return path
    from precompute.build import main as build_main

    path.parent.mkdir(parents=True, exist_ok=True)
    what = f"table set (starts {robot.starts})" if robot.starts is not None else "table"
    print(f"building the {method} {what} of the navigation robot into {path} (once; cached)")
    # the coverage ascent of this 15-step robot stops early (--tol 1e-3: about 105 of 300 steps; within 0.3% of
    # the full ascent's coverage at N = 1000 and 10 000), which keeps its first build to about 80 s
    approx = ["--tol", "1e-3"] if method == "coverage" else []
    starts = ["--starts", robot.starts] if robot.starts is not None else []
    args = [*_build_args(robot), "--method", method, *approx, *starts, "--out", str(path),
            *(["--quiet"] if quiet else [])]
    code = build_main(args)
    if code != 0 or not done.exists():
        raise RuntimeError(f"building {path} failed (python -m precompute.build {' '.join(args)}; exit {code})")
    return path


def ensure_policy(robot: RobotPreset, cache: Path, quiet: bool = False) -> Path:
    """The MLP distilled from ``robot``'s max-flow table (:data:`DISTILL_EPOCHS` epochs), trained when not cached."""
    if robot.starts is not None:
        raise ValueError("cu_mlp with --starts: give a policy distilled from the set (--policy FILE)")
    path = policy_file(robot, cache)
    if path.exists():
        return path
    from training.distill import main as distill_main

    table = ensure_table(robot, cache, quiet=quiet)
    print(f"distilling the navigation robot's table into {path} (once; cached)")
    args = ["--tables", str(table), "--out", str(path), "--epochs", str(DISTILL_EPOCHS),
            "--logdir", str(Path(cache) / "runs" / path.stem), *(["--quiet"] if quiet else [])]
    code = distill_main(args)
    if code != 0 or not path.exists():
        raise RuntimeError(f"distilling {path} failed (python -m training.distill {' '.join(args)}; exit {code})")
    return path


def preset_dict(robot: RobotPreset) -> dict[str, Any]:
    """The preset as JSON types, for the benchmark's config record (``starts`` only when set, so the records of
    one-table runs stay as they were)."""
    out = asdict(robot)
    if out["starts"] is None:
        del out["starts"]
    return out
