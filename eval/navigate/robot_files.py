"""The C-Uniform files of the navigation benchmark's robot, built on first use and cached.

The built-in robot (:data:`NAV_ROBOT`) is a differential-drive base driven as a unicycle: a cruise speed of
0.5 m/s and 7 turn rates evenly in [-1.5, 1.5] rad/s (the library's ``dubins`` system with those parameters),
dt = 0.2 s, a disc of radius 0.2 m (BARN's narrowest passages are about 0.6-0.7 m wide between cylinder
surfaces), a controller horizon of 15 steps (3 s, 1.5 m ahead), cells of 0.05 m x 0.05 m x 10 degrees. Its
max-flow table (81 329 cells) builds in about 8 s on the project's 2-core machine, its coverage table in about
85 s (:data:`BUILD_SECONDS`); each build says so before it starts (:func:`announce`).

Any registered system can drive the suites instead (:class:`RobotPreset` with another ``system`` name and
``params``); it needs ``(x, y, heading, ...)`` states. The files a method needs are built by
:func:`precompute.one_table.build_table_file` (and :func:`training.distill.distill` for the MLP) into a cache folder, named by a
hash of everything that defines them, so a changed preset builds new files and an unchanged one reuses them.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

from cuniform_torch.common.fileio import FileLockedError
from precompute.worlds.robot import NAV_ROBOT, RobotPreset

__all__ = ["table_file", "policy_file", "ensure_table", "ensure_policy", "expected_time", "announce", "BUILD_SECONDS",
           "DISTILL_EPOCHS"]

BUILD_SECONDS: dict[tuple[str, int], float] = {
    ("maxflow", 15): 8, ("coverage", 15): 85, ("policy", 15): 230,
    ("maxflow", 10): 0.4, ("coverage", 10): 4,
    ("maxflow", 6): 0.1, ("coverage", 6): 0.1,
}
"""seconds to build the built-in robot's files (:data:`NAV_ROBOT`'s system and parameters) by ``(method, horizon)``
(``policy``: the MLP of :func:`ensure_policy`), one torch thread, on the project's 2-core machine (issue 37): the
tables measured at load about 5 (other jobs running) by ``python -c`` calls of :func:`ensure_table` on an empty
cache (the 15-step coverage table again at load 2.2-2.5: 57.2 s, against 81.4 s with torch's two threads, the
code before); the policy (:data:`DISTILL_EPOCHS` = 84 epochs on the 81,329-cell table, one thread): 501 s of wall
time at load 9-13 (other jobs running) for 225 s of CPU time (``time``: user 203 s + sys 22 s), so about 230 s on
an idle machine; KL 0.113 at the cell centres, coverage 1.035x / 1.023x the table's at N = 1000 / 10000. The 15-step tables are 12.5 MB
(max-flow) and 11 MB (coverage): too big to ship as package data beside the map policy, so they are built once,
announced with these times."""

DISTILL_EPOCHS = 84
"""epochs of the MLP distilled on first use: what ``training.distill``'s default gives the built-in robot's
81,329-cell table (100 epochs, capped at 6.8 million cell passes), fixed here so the cached file's name says it"""


def table_file(robot: RobotPreset, cache: Path, method: str = "maxflow") -> Path:
    """Where ``robot``'s table of ``method`` (``maxflow`` or ``coverage``) is cached: a file, or a set's folder."""
    stem = f"{robot.system}-{robot.fingerprint(method)}-{method}"
    return Path(cache) / (f"{stem}-set" if robot.starts is not None else f"{stem}.npz")


def policy_file(robot: RobotPreset, cache: Path) -> Path:
    """Where the MLP distilled from ``robot``'s max-flow table is cached."""
    return Path(cache) / f"{robot.system}-{robot.fingerprint('maxflow')}-e{DISTILL_EPOCHS}.policy.pt"


def expected_time(robot: RobotPreset, method: str = "maxflow") -> str:
    """How long building ``robot``'s file of ``method`` (``maxflow``, ``coverage`` or ``policy``) takes, in words:
    the measured time (:data:`BUILD_SECONDS`) for the built-in robot's system at a measured horizon, else that it is
    not measured, with the 15-step table's time as a scale."""
    known = (robot.system == NAV_ROBOT.system and robot.params == NAV_ROBOT.params and robot.starts is None)
    seconds = BUILD_SECONDS.get((method, robot.horizon)) if known else None
    if seconds is not None:
        if seconds >= 120:
            return f"about {seconds / 60:.0f} minutes on a 2-core CPU"
        return f"about {seconds:.0f} s on a 2-core CPU" if seconds >= 1 else "about a second"
    scale = BUILD_SECONDS[(method, NAV_ROBOT.horizon)]
    return (f"time not measured for this robot; the built-in robot's {NAV_ROBOT.horizon}-step {method} "
            f"takes about {scale:.0f} s on a 2-core CPU")


def announce(robot: RobotPreset, method: str, what: str, path: Path) -> None:
    """Say, before it starts, what is built, how long it takes (:func:`expected_time`) and where it is cached."""
    print(f"{what} ({expected_time(robot, method)}; once, cached in {path})", flush=True)


def _system(robot: RobotPreset):
    """The robot's system, its list parameters as tuples (as the build's flags give them)."""
    from cuniform_torch.systems import make_system

    params = {k: tuple(v) if isinstance(v, list) else v for k, v in robot.params.items()}
    return make_system(robot.system, **params)


WAIT_POLL_S = 2.0
"""seconds between looks at a cached file another run is building"""


def _build_once(path: Path, done: Path, build: Callable[[], object]) -> None:
    """``build()`` unless ``done`` exists; while another run (sharing the cache) holds the lock of ``path``, wait for
    it (said once) and use what it built: two benchmarks on one cold ``--cache`` serialize."""
    said = False
    while not done.exists():
        try:
            build()
            return
        except FileLockedError as exc:
            if not said:
                print(f"{path} is being built by another run ({str(exc).split(' (lock file')[0]}); waiting for it",
                      flush=True)
                said = True
            time.sleep(WAIT_POLL_S)


def ensure_table(robot: RobotPreset, cache: Path, method: str = "maxflow", quiet: bool = False) -> Path:
    """``robot``'s table of ``method`` (:func:`precompute.one_table.build_table_file`, or a table set when the
    robot has ``starts``), built when not cached yet."""
    from precompute.build import with_threads
    from precompute.coverage.method import CoverageConfig
    from precompute.flow.builder import BuildConfig
    from precompute.one_table import TableJob, build_table_file
    from precompute.table_set import build_table_set, parse_starts

    path = table_file(robot, cache, method)
    done = path / "tables.json" if robot.starts is not None else path
    if done.exists():
        return path
    path.parent.mkdir(parents=True, exist_ok=True)
    what = f"table set (starts {robot.starts})" if robot.starts is not None else "table"
    announce(robot, method, f"building the {method} {what} of the navigation robot", path)
    system = _system(robot)
    # the coverage ascent of this 15-step robot stops early (tol 1e-3: about 105 of 300 steps; within 0.3% of
    # the full ascent's coverage at N = 1000 and 10 000), which keeps its first build to about 80 s
    coverage = CoverageConfig(horizon=robot.horizon, tol=1e-3) if method == "coverage" else None
    job = TableJob(system=system, out=path, build=BuildConfig(horizon=robot.horizon), coverage=coverage,
                   report=False, quiet=quiet)
    # one torch thread, as `python -m precompute.build` (--threads 1): two threads on 2 busy cores are 5-10x slower
    if robot.starts is not None:
        starts = parse_starts(robot.starts, system)
        _build_once(path, done, lambda: with_threads(1, lambda: build_table_set(job, starts, path)))
    else:
        _build_once(path, done, lambda: with_threads(1, lambda: build_table_file(job)))
    if not done.exists():
        raise RuntimeError(f"building {path} left no {done.name}")
    return path


def ensure_policy(robot: RobotPreset, cache: Path, quiet: bool = False) -> Path:
    """The MLP distilled from ``robot``'s max-flow table (:data:`DISTILL_EPOCHS` epochs), trained when not cached."""
    if robot.starts is not None:
        raise ValueError("cu_mlp with --starts: give a policy distilled from the set (--policy FILE)")
    path = policy_file(robot, cache)
    if path.exists():
        return path
    from training.distill import distill
    from training.tables.config import DistillConfig

    table = ensure_table(robot, cache, quiet=quiet)
    announce(robot, "policy", f"distilling the navigation robot's table into an MLP ({DISTILL_EPOCHS} epochs)", path)
    _build_once(path, path, lambda: distill(DistillConfig(tables=[str(table)], out=str(path), epochs=DISTILL_EPOCHS,
                                                         logdir=str(Path(cache) / "runs" / path.stem), quiet=quiet)))
    if not path.exists():
        raise RuntimeError(f"distilling {path} wrote no checkpoint")
    return path
