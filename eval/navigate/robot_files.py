"""The C-Uniform files of the navigation benchmark's robot: shipped with the package, else built on first use and
cached.

The built-in robot (:data:`NAV_ROBOT`) is a differential-drive base driven as a unicycle: a cruise speed of
0.5 m/s and 7 turn rates evenly in [-1.5, 1.5] rad/s (the library's ``dubins`` system with those parameters),
dt = 0.2 s, a disc of radius 0.2 m (BARN's narrowest passages are about 0.6-0.7 m wide between cylinder
surfaces), a controller horizon of 15 steps (3 s, 1.5 m ahead), cells of 0.05 m x 0.05 m x 10 degrees. Its
max-flow table (81 329 cells) and its coverage table (47 514 cells) ship as package data
(:data:`SHIPPED_DIR`, 1.5 MB and 1.3 MB without the flow graph no policy reads), checked against their manifest
(size, sha256) before use (:func:`shipped_table`); ``python -m eval.navigate robot-files --ship`` rebuilds them
(about 7 s and 27 s on the project's 2-core machine, :data:`BUILD_SECONDS`) and ``--check`` rebuilds and compares.
The ``narrow`` suite's faster robot (:data:`~precompute.worlds.robot.FAST_ROBOT`, the same lattice scaled by two:
as many cells) ships its two tables beside them (:data:`SHIPPED_ROBOTS`); ``--ship`` and ``--check`` do both robots.

Any registered system can drive the suites instead (:class:`RobotPreset` with another ``system`` name and
``params``, or another horizon); it needs ``(x, y, heading, ...)`` states. The files a method needs are built by
:func:`precompute.one_table.build_table_file` (and :func:`training.distill.distill` for the MLP) into a cache folder, named by a
hash of everything that defines them, so a changed preset builds new files and an unchanged one reuses them; each
build says what it builds and how long it takes before it starts (:func:`announce`).
"""

from __future__ import annotations

import hashlib
import json
import os
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cuniform_torch
from cuniform_torch.common.fileio import FileLockedError, open_regular, read_capped_text, write_json
from precompute.cli import ArgumentParser, CLIError, cli_main, horizon_arg
from precompute.worlds.robot import FAST_ROBOT, NAV_ROBOT, RobotPreset, preset_dict

if TYPE_CHECKING:
    from precompute.one_table import TableJob

__all__ = ["table_file", "policy_file", "ensure_table", "ensure_policy", "expected_time", "announce", "BUILD_SECONDS",
           "DISTILL_EPOCHS", "SHIPPED_DIR", "SHIPPED_FORMAT", "SHIPPED_ROBOTS", "ShippedTableError", "shipped_table",
           "ship_tables", "main"]

BUILD_SECONDS: dict[tuple[str, int], float] = {
    ("maxflow", 15): 7, ("coverage", 15): 27, ("policy", 15): 230,
    ("maxflow", 10): 0.6, ("coverage", 10): 2.6,
    ("maxflow", 6): 0.1, ("coverage", 6): 1.8,
}
"""seconds to build the built-in robot's files (:data:`NAV_ROBOT`'s system and parameters) by ``(method, horizon)``
(``policy``: the MLP of :func:`ensure_policy`), one torch thread, on the project's 2-core machine when idle: the
tables' CPU seconds printed by ``python -m eval.navigate robot-files --time`` (each build written and read back;
the first coverage build of a process loads the compiled loops), measured at load 4.6-5 (other jobs running: the
wall-clock times were 0.2 / 3.7 / 1.4 / 4.5 / 14.3 / 46.1 s); at load 1.2-1.3 the 15-step tables took 6.3 s
and 25.7 s of wall time (``--time --horizons 15``). The coverage table's first build took 57 s of CPU
before its passes were compiled (issue 37), 26 s now. The policy (:data:`DISTILL_EPOCHS` = 84 epochs on the
81,329-cell table, one thread): 501 s of wall time at load 9-13 (other jobs running) for 225 s of CPU time
(``time``: user 203 s + sys 22 s), so about 230 s on an idle machine; KL 0.113 at the cell centres, coverage
1.035x / 1.023x the table's at N = 1000 / 10000. The 15-step tables themselves ship (:func:`shipped_table`):
these times are what ``--ship`` and another robot's builds take."""

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


SHIPPED_DIR = Path(cuniform_torch.__file__).parent / "maps" / "robot_tables"
"""``cuniform_torch/maps/robot_tables/``: the built-in robot's tables shipped as package data, beside the pretrained
map policies (``maps/weights/``), with their manifest (:data:`MANIFEST`)"""
SHIPPED_ROBOTS = (NAV_ROBOT, FAST_ROBOT)
"""the robots whose 15-step tables ship: the built-in robot and the ``narrow`` suite's faster one"""

SHIPPED_FORMAT = "cuniform-shipped-tables/1"
MANIFEST = "manifest.json"
SHIP_COMMAND = "python -m eval.navigate robot-files --ship"
"""rebuilds the shipped tables and their manifest (about :data:`BUILD_SECONDS` of both 15-step tables)"""
_MAX_MANIFEST_BYTES = 1 << 20


class ShippedTableError(ValueError):
    """A shipped table that does not match its manifest (damaged or replaced), or a manifest that cannot be read."""


def _file_digest(path: Path) -> tuple[int, str]:
    """Size and sha256 of a regular file (a FIFO or a device is refused, never opened for reading)."""
    with open_regular(path, "a shipped table") as fh:
        size = os.fstat(fh.fileno()).st_size
        digest = hashlib.sha256()
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return size, digest.hexdigest()


def _manifest(folder: Path) -> dict[str, Any] | None:
    """The manifest of the shipped tables in ``folder``; None when there is none (nothing shipped)."""
    path = folder / MANIFEST
    if not path.exists():
        return None
    fix = f"reinstall the package or rebuild the tables ({SHIP_COMMAND})"
    try:
        manifest = json.loads(read_capped_text(path, _MAX_MANIFEST_BYTES, "the shipped tables' manifest"))
    except (OSError, ValueError, RecursionError) as exc:
        raise ShippedTableError(f"{path}: not a readable manifest ({exc}); {fix}") from None
    keys = {"file": str, "method": str, "fingerprint": str, "bytes": int, "file_sha256": str}
    entries = manifest.get("tables") if isinstance(manifest, dict) else None
    if not isinstance(manifest, dict) or manifest.get("format") != SHIPPED_FORMAT or not isinstance(entries, list) \
            or not all(isinstance(e, dict) and all(isinstance(e.get(k), t) for k, t in keys.items())
                       and Path(e["file"]).name == e["file"] for e in entries):
        raise ShippedTableError(f"{path}: not a {SHIPPED_FORMAT!r} manifest (format; tables: file, method, "
                                f"fingerprint, bytes, file_sha256); {fix}")
    return manifest


def shipped_table(robot: RobotPreset, method: str = "maxflow", folder: Path = SHIPPED_DIR) -> Path | None:
    """The shipped table of ``method`` for ``robot`` (the manifest's entry of the robot's fingerprint), after checking
    the file's size and sha256 against the manifest (:class:`ShippedTableError`); None when none is shipped."""
    if robot.starts is not None:
        return None
    manifest = _manifest(Path(folder))
    fingerprint = robot.fingerprint(method)
    entry = None if manifest is None else next(
        (e for e in manifest["tables"] if e["method"] == method and e["fingerprint"] == fingerprint), None)
    if entry is None:
        return None
    path = Path(folder) / entry["file"]
    fix = f"a damaged or replaced file; reinstall the package or rebuild the tables ({SHIP_COMMAND})"
    if not path.exists():
        raise ShippedTableError(f"the shipped {method} table {path} is missing ({fix.split('; ', 1)[1]})")
    size, sha = _file_digest(path)
    if size != entry["bytes"] or sha != entry["file_sha256"]:
        raise ShippedTableError(f"{path} does not match its manifest ({size} bytes, sha256 {sha[:12]}...; the "
                                f"manifest says {entry['bytes']} bytes, {entry['file_sha256'][:12]}...): {fix}")
    return path


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


def _job(robot: RobotPreset, method: str, path: Path, quiet: bool) -> TableJob:
    """The build of ``robot``'s table of ``method`` into ``path`` (a :class:`precompute.one_table.TableJob`)."""
    from precompute.coverage.method import CoverageConfig
    from precompute.flow.builder import BuildConfig
    from precompute.one_table import TableJob

    # the coverage ascent of this 15-step robot stops early (tol 1e-3: about 105 of 300 steps; within 0.3% of
    # the full ascent's coverage at N = 1000 and 10 000)
    coverage = CoverageConfig(horizon=robot.horizon, tol=1e-3) if method == "coverage" else None
    return TableJob(system=_system(robot), out=path, build=BuildConfig(horizon=robot.horizon), coverage=coverage,
                    report=False, quiet=quiet)


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
    robot has ``starts``): the shipped one (:func:`shipped_table`), else the cached one, else built (announced)."""
    from precompute.build import with_threads
    from precompute.one_table import build_table_file
    from precompute.table_set import build_table_set, parse_starts

    shipped = shipped_table(robot, method)
    if shipped is not None:  # the built-in robot's tables ship with the package: nothing to build
        return shipped
    path = table_file(robot, cache, method)
    done = path / "tables.json" if robot.starts is not None else path
    if done.exists():
        return path
    path.parent.mkdir(parents=True, exist_ok=True)
    what = f"table set (starts {robot.starts})" if robot.starts is not None else "table"
    announce(robot, method, f"building the {method} {what} of the navigation robot", path)
    job = _job(robot, method, path, quiet)
    # one torch thread, as `python -m precompute.build` (--threads 1): two threads on 2 busy cores are 5-10x slower
    if robot.starts is not None:
        starts = parse_starts(robot.starts, job.system)
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


METHODS = ("maxflow", "coverage")
"""the methods whose tables are shipped"""


def build_policy_table(robot: RobotPreset, method: str, quiet: bool = True) -> tuple[Any, float, float]:
    """Build ``robot``'s table of ``method`` as :func:`ensure_table` does (one torch thread, the file written and
    read back) and keep what a policy reads (the flow graph, audit data no policy reads, left out:
    :func:`cuniform_torch.tables.file.read_table` with ``graph=False``); returns the
    :class:`~cuniform_torch.tables.file.Table` and the build's wall-clock and CPU seconds (on a busy machine the
    CPU time is what an idle one takes)."""
    from cuniform_torch.tables.file import read_table
    from precompute.build import with_threads
    from precompute.one_table import build_table_file

    with tempfile.TemporaryDirectory(prefix="robot-table-") as tmp:
        full = Path(tmp) / "table.npz"
        start, cpu = time.perf_counter(), time.process_time()
        with_threads(1, lambda: build_table_file(_job(robot, method, full, quiet)))
        return read_table(full, graph=False), time.perf_counter() - start, time.process_time() - cpu


def ship_tables(robot: RobotPreset = NAV_ROBOT, folder: Path = SHIPPED_DIR, methods: Sequence[str] = METHODS,
                quiet: bool = True) -> dict[str, Any]:
    """Build ``robot``'s tables of ``methods`` (:func:`build_policy_table`), write them into ``folder`` with their
    manifest (:data:`MANIFEST`: file, size, sha256, content digest, the robot, the build's wall-clock and CPU
    seconds and the 1-minute load) and return the manifest. The older manifest's entries of ``robot`` (any method)
    are replaced, their files removed when no longer named; the entries of other robots are kept."""
    from cuniform_torch.tables.file import NOGRAPH_DIGEST_KEY, table_digests, write_table

    if robot.starts is not None:
        raise ValueError("a robot with starts has table sets, which are not shipped")
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    old = _manifest(folder) or {"tables": []}
    entries = []
    for method in methods:
        print(f"building the {method} table of the navigation robot to ship ({expected_time(robot, method)})",
              flush=True)
        table, seconds, cpu = build_policy_table(robot, method, quiet)
        path = table_file(robot, folder, method)
        write_table(path, table)
        size, sha = _file_digest(path)
        entries.append({"file": path.name, "method": method, "fingerprint": robot.fingerprint(method),
                        "robot": preset_dict(robot), "bytes": size, "file_sha256": sha,
                        "content_sha256_nograph": str(table_digests(table.to_arrays())[NOGRAPH_DIGEST_KEY]),
                        "cells": int(table.level_offsets[-1]), "build_seconds": round(seconds, 1),
                        "build_cpu_seconds": round(cpu, 1), "load": round(os.getloadavg()[0], 1)})
    mine = {robot.fingerprint(m) for m in METHODS}  # this robot's entries, of every method, are replaced
    others = [e for e in old["tables"] if e["fingerprint"] not in mine]
    entries = others + entries
    kept = {e["file"] for e in entries}
    for entry in old["tables"]:
        if entry["file"] not in kept and (folder / entry["file"]).is_file():
            (folder / entry["file"]).unlink()
    manifest = {"format": SHIPPED_FORMAT, "rebuild": SHIP_COMMAND, "tables": entries}
    write_json(folder / MANIFEST, manifest)
    return manifest


def compare_tables(a: Any, b: Any) -> dict[str, Any]:
    """How two tables differ in what a policy reads: equal level sets and cells, and the largest absolute
    differences of ``action_probs`` and ``cell_probs`` (inf when the cells differ)."""
    import numpy as np

    same = bool(np.array_equal(a.level_offsets, b.level_offsets) and np.array_equal(a.cells, b.cells))
    inf = float("inf")
    return {"same_cells": same,
            "action_probs": float(np.abs(a.action_probs - b.action_probs).max()) if same else inf,
            "cell_probs": float(np.abs(a.cell_probs - b.cell_probs).max()) if same else inf}


CHECK_TOLERANCE = 0.05
"""``--check``: the largest difference of action probabilities between a rebuild and the shipped table that
passes. On one machine and library versions a rebuild is the same to the bit; elsewhere the coverage ascent's
float32 sums may round differently, and Adam turns that noise in near-zero gradients into small moves: the
compiled passes against the torch ones they replaced moved 271 of the 332 598 coverage probabilities by more
than 1e-3, at most by 0.011, for the same coverage (6306 / 15816 cells at N = 1000 / 10000 against 6306 /
15817; CHANGELOG)"""


def make_parser() -> ArgumentParser:
    parser = ArgumentParser(
        prog="python -m eval.navigate robot-files",
        description="The navigation robots' shipped tables (cuniform_torch/maps/robot_tables/: the built-in "
                    "robot's and the narrow suite's faster robot's): rebuild them "
                    f"(--ship, about {BUILD_SECONDS[('maxflow', 15)] + BUILD_SECONDS[('coverage', 15)]:.0f} s per "
                    "robot on a 2-core CPU), rebuild and compare them with the shipped ones (--check), or time the builds "
                    "(--time: the measurements of BUILD_SECONDS).")
    mode = parser.add_mutually_exclusive_group(required=True)
    mode.add_argument("--ship", action="store_true", help="build the tables and write them with their manifest")
    mode.add_argument("--check", action="store_true",
                      help=f"build the tables and compare them with the shipped ones (exit 1 when the cells differ "
                           f"or an action probability differs by more than {CHECK_TOLERANCE:g})")
    mode.add_argument("--time", action="store_true",
                      help="build the tables at --horizons (into a temporary folder) and print their wall-clock and "
                           "CPU seconds and the 1-minute load")
    parser.add_argument("--out", type=Path, help=f"--ship: the folder to write (default: {SHIPPED_DIR})")
    parser.add_argument("--horizons", type=horizon_arg, nargs="+", help="--time: the horizons (default: 6 10 15)")
    parser.add_argument("--methods", nargs="+", choices=METHODS, default=list(METHODS), help="the tables")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    return parser


@cli_main()
def main(argv: Sequence[str] | None = None) -> int:
    from cuniform_torch.tables.file import read_table

    args = make_parser().parse_args(sys.argv[1:] if argv is None else list(argv))
    if args.out is not None and not args.ship:
        raise CLIError("--out applies to --ship (--check compares with the package's shipped tables)")
    if args.horizons is not None and not args.time:
        raise CLIError("--horizons applies to --time (--ship and --check build the navigation robot's 15 steps)")
    if args.ship:
        out = args.out or SHIPPED_DIR
        manifest: dict[str, Any] = {}
        for robot in SHIPPED_ROBOTS:
            manifest = ship_tables(robot, out, args.methods, args.quiet)
        for e in manifest["tables"]:
            print(f"wrote {out / e['file']} ({e['bytes']} bytes, {e['cells']} cells, built in "
                  f"{e['build_seconds']} s, {e['build_cpu_seconds']} s of CPU, load {e['load']})")
        print(f"wrote {out / MANIFEST}")
        return 0
    if args.time:
        for horizon in args.horizons or (6, 10, 15):
            robot = replace(NAV_ROBOT, horizon=horizon)
            for method in args.methods:
                _, seconds, cpu = build_policy_table(robot, method, args.quiet)
                print(f"{method} {horizon} steps: {seconds:.1f} s, {cpu:.1f} s of CPU, load "
                      f"{os.getloadavg()[0]:.1f}", flush=True)
        return 0
    failed = False
    for robot, method in ((robot, method) for robot in SHIPPED_ROBOTS for method in args.methods):
        path = shipped_table(robot, method)
        if path is None:
            raise CLIError(f"no shipped {method} table of the navigation robot {robot.fingerprint(method)} in "
                           f"{SHIPPED_DIR} (build them: {SHIP_COMMAND})")
        print(f"rebuilding the {method} table to compare with {path} ({expected_time(robot, method)})",
              flush=True)
        built, seconds, cpu = build_policy_table(robot, method, args.quiet)
        diff = compare_tables(built, read_table(path, graph=False))
        ok = diff["same_cells"] and diff["action_probs"] <= CHECK_TOLERANCE
        failed |= not ok
        print(f"{method}: built in {seconds:.1f} s ({cpu:.1f} s of CPU, load {os.getloadavg()[0]:.1f}); same cells "
              f"{diff['same_cells']}; max |action_probs diff| {diff['action_probs']:.3g}, max |cell_probs diff| "
              f"{diff['cell_probs']:.3g}: {'ok' if ok else 'DIFFERS'}")
    return 1 if failed else 0
