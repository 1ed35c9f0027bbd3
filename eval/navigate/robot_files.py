"""The C-Uniform files of the navigation benchmark's robot, built on first use and cached.

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

import json
from pathlib import Path

from cuniform_torch.envs.worlds.robot import RobotPreset

__all__ = ["table_file", "policy_file", "ensure_table", "ensure_policy", "DISTILL_EPOCHS"]

DISTILL_EPOCHS = 300
"""epochs of the MLP distilled on first use (``training.distill``'s default is 1500; this keeps the first
``cu_mlp`` run to a few minutes on a CPU)"""


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
