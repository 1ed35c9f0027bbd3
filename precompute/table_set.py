"""A table set: independent tables of one system built from many starts (``python -m precompute.build set --starts``).

``--starts SPEC`` names the starts over the state dimensions that matter (others are 0):

* a grid: ``DIM=LO:HI:N`` items, separated by spaces, e.g. ``"3=0:1:5"`` (speed 0, 0.25, ..., 1) or
  ``"0=-1:1:3 1=-1:1:3"`` (a 3 x 3 grid over dimensions 0 and 1);
* a seeded sample: ``random:N`` then ``DIM=LO:HI`` items, e.g. ``"random:20 3=0:1"`` (20 speeds uniform in
  [0, 1], numpy's generator seeded with ``--seed``).

For an SE(2)-invariant system x, y, theta (dimensions 0-2) cannot be given: one table serves every pose.
The grid includes both ends (``np.linspace``): on an angle dimension ``K``, ``K=-3.14159:3.14159:9`` puts two
members at the same angle; grid ``LO:HI-step:N-1`` instead. Every table is built by :func:`build_table_set` as the same
:class:`~precompute.one_table.TableJob` as a single table from its start into ``DIR/start_0000.npz``, ... (so
each is byte-identical to a table built alone), in parallel over ``--workers N`` processes or Ray tasks
(``--ray [ADDRESS]``), and skipped when it is already there with the same start (resumable per table). ``DIR/tables.json`` describes the set: format ``cuniform-table-set/1``, the system, the method, and
per table its file and start.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path
from typing import Any

import numpy as np

from cuniform_torch.common.fileio import MAX_JSON_BYTES, exclusive_lock, read_capped_text, write_json
from cuniform_torch.systems import _REGISTRY, System, factory_path, is_builtin, load_factory, register_system
from cuniform_torch.tables.file import Table, TableError, read_table, system_to_json
from precompute.cli import CLIError
from precompute.one_table import TableJob, build_table_file
from precompute.parallel import run_jobs

__all__ = ["SET_FORMAT", "parse_starts", "build_table_set", "ensure_table_set", "set_complete", "INDEX",
           "MAX_SET_MEMBERS"]

SET_FORMAT = "cuniform-table-set/1"
INDEX = "tables.json"
MAX_SET_MEMBERS = 10_000
"""the most starts ``--starts`` may name (the members' four-digit names) unless ``--no-limit``: a grid's counts
multiply, and a million-member set wrote thousands of tables before anyone noticed"""
_ITEM = re.compile(r"^(\d+)=([^:]+):([^:]+)(?::(\d+))?$")


def parse_starts(spec: str, system: System, seed: int = 0, limit: int | None = MAX_SET_MEMBERS) -> np.ndarray:
    """The starts ``[S, d]`` float64 that ``spec`` names (module docstring); a clear ValueError otherwise, also
    when they are more than ``limit`` (None: no limit), checked from the counts before any start is made."""
    d = len(system.periodic)
    words = spec.split()
    if not words:
        raise ValueError("--starts is empty; e.g. --starts '3=0:1:5' (see precompute/table_set.py)")
    sample = None
    if words[0].startswith("random:"):
        try:
            sample = int(words[0].split(":", 1)[1])
        except ValueError:
            raise ValueError(f"--starts: {words[0]!r} must be random:N with an integer N") from None
        if sample < 1:
            raise ValueError(f"--starts: random:N needs N >= 1, got {sample}")
        words = words[1:]
    ranges: dict[int, tuple[float, float, int | None]] = {}
    for word in words:
        m = _ITEM.match(word)
        if m is None:
            raise ValueError(f"--starts: {word!r} is not DIM=LO:HI:N (grid) or DIM=LO:HI (after random:N)")
        dim, lo, hi, n = int(m[1]), float(m[2]), float(m[3]), None if m[4] is None else int(m[4])
        if dim >= d:
            raise ValueError(f"--starts: dimension {dim} does not exist; {system.name} has dimensions 0..{d - 1}")
        if getattr(system, "se2_invariant", False) and dim < 3:
            raise ValueError(f"--starts: {system.name} is SE(2)-invariant, so x, y, theta (dimensions 0-2) need no "
                             f"starts: one table serves every pose; give dimensions 3..{d - 1}")
        if not (np.isfinite(lo) and np.isfinite(hi) and lo <= hi):
            raise ValueError(f"--starts: {word!r} needs finite LO <= HI")
        if (sample is None) != (n is not None):
            raise ValueError(f"--starts: {word!r}: a grid item needs :N, a random item has none")
        if n is not None and n < 1:
            raise ValueError(f"--starts: {word!r} needs N >= 1")
        if dim in ranges:
            raise ValueError(f"--starts: dimension {dim} is given twice")
        ranges[dim] = (lo, hi, n)
    if not ranges:
        raise ValueError("--starts names no dimension; e.g. --starts '3=0:1:5'")
    dims = sorted(ranges)
    count = sample if sample is not None else math.prod(int(ranges[k][2] or 1) for k in dims)
    if limit is not None and count > limit:
        raise ValueError(f"--starts names {count:,} starts, more than the limit of {limit:,} tables in a set; give "
                         "fewer (grid counts multiply), or --no-limit to build them all")
    if sample is None:
        axes = [np.linspace(ranges[k][0], ranges[k][1], ranges[k][2]) for k in dims]
        values = np.stack([a.ravel() for a in np.meshgrid(*axes, indexing="ij")], axis=1)  # [S, len(dims)]
    else:
        rng = np.random.default_rng(seed)
        values = rng.uniform([ranges[k][0] for k in dims], [ranges[k][1] for k in dims], size=(sample, len(dims)))
    starts = np.zeros((len(values), d))
    starts[:, dims] = values
    return np.round(starts, 12)  # 0.25, not 0.25000000000000006: the starts are printed and compared


def _build_member(job: TableJob, factory: str | None = None) -> Path:
    """Build one member; ``factory`` (``"module:qualname"``) registers a user system first: a spawned worker or a
    Ray task starts with the built-in systems only, and writing a table rebuilds its system from the registry."""
    if factory is not None:
        register_system(job.system.name, load_factory(factory))  # the same definition: a no-op in this process
    return build_table_file(job)


def worker_factory(system: System, workers: int, ray_address: str | None) -> str | None:
    """The ``"module:qualname"`` of a user system's factory that the set's worker processes import and register
    (None: built in this process, or a built-in system); a clear ValueError when a worker could not rebuild it (a
    factory defined in ``__main__``, a notebook or a function)."""
    if workers <= 1 and ray_address is None:
        return None
    factory = _REGISTRY.get(system.name, type(system))
    if is_builtin(factory):
        return None
    path = factory_path(factory)
    if path is None:
        raise ValueError(f"system {system.name!r}: its factory {getattr(factory, '__qualname__', factory)!r} cannot be "
                         "imported by a worker process (defined in __main__, a notebook or a function); define it at "
                         "the top of an importable module (--system my_robots:Factory), or build with --workers 1")
    return path


_SETTINGS = {"maxflow": ("points", "ties", "points_per_cell", "seed", "map_rule"),
             "coverage": ("target_samples", "merge_resolution", "steps", "lr", "state_budget", "tol")}
"""the ``build_info`` entries of a member that its build settings decide (the rest are facts of the build)"""


def _settings_differ(table: Table, template: TableJob) -> str | None:
    """What differs between the member ``table`` and what ``template`` would build (the system and its parameters,
    the horizon, the method, the method's settings), or None."""
    want = system_to_json(template.system, template.build.horizon)
    if table.system != want:
        try:
            old, new = json.loads(table.system), json.loads(want)
            old = {**{k: v for k, v in old.items() if k != "params"}, **(old.get("params") or {})}
            new = {**{k: v for k, v in new.items() if k != "params"}, **(new.get("params") or {})}
            keys = sorted(k for k in set(old) | set(new) if old.get(k) != new.get(k))
            return "; ".join(f"{k}: {old.get(k)!r} there, {new.get(k)!r} now" for k in keys[:3]) or "the system"
        except (ValueError, AttributeError):
            return "the system"
    if (table.method or "maxflow") != template.method:
        return f"method: {table.method!r} there, {template.method!r} now"
    try:
        old_info = json.loads(table.build_info or "{}")
    except ValueError:
        return "build_info unreadable"
    cfg: Any = template.coverage if template.coverage is not None else template.build
    for key in _SETTINGS[template.method]:
        if key == "map_rule" or not hasattr(cfg, key):
            continue
        new_value = getattr(cfg, key)
        new_value = getattr(new_value, "value", new_value)
        if template.method == "maxflow" and key in ("points_per_cell", "seed") and cfg.points.value != "random":
            new_value = None
        if old_info.get(key) != new_value:
            return f"{key}: {old_info.get(key)!r} there, {new_value!r} now"
    return None


def _done(path: Path, start: np.ndarray, template: TableJob) -> bool:
    """Whether ``path`` holds a readable table built from ``start`` with ``template``'s settings; a ValueError when
    it holds a table built from ``start`` with other settings (a rerun never keeps a stale member silently)."""
    if not path.exists():
        return False
    try:
        table = read_table(path, graph=False)
    except TableError:
        return False
    if table.start is None or not np.array_equal(table.start, start):
        return False
    differ = _settings_differ(table, template)
    if differ is not None:
        raise ValueError(f"the table set {path.parent} was built with other settings ({path.name}: {differ}); "
                         f"use another --out, or delete {path.parent} to build it anew")
    return True


def build_table_set(template: TableJob, starts: np.ndarray, out: Path, workers: int = 1,
                    ray_address: str | None = None) -> Path:
    """Build one table per start ``[S, d]`` into the folder ``out`` (module docstring), each ``template`` built
    from that start (:meth:`TableJob.from_start`, so byte-identical to the table built alone); a member already
    there with its start is kept (resumable per table). Returns ``out``; a failing member raises, naming its start."""
    out = Path(out)
    if out.suffix == ".npz":
        raise ValueError(f"--out {out}: a table set is a folder (e.g. --out out/{template.system.name}_set)")
    starts = np.asarray(starts, dtype=np.float64)
    if starts.ndim != 2 or starts.shape[1] != len(template.system.periodic) or len(starts) == 0:
        raise ValueError(f"starts must be [S, {len(template.system.periodic)}] with S >= 1, got {starts.shape}")
    with exclusive_lock(out / ".lock", what=f"the table set {out}"):
        return _build_set(template, starts, out, workers, ray_address)


def _build_set(template: TableJob, starts: np.ndarray, out: Path, workers: int, ray_address: str | None) -> Path:
    factory = worker_factory(template.system, workers, ray_address)  # before any folder or table is made
    out.mkdir(parents=True, exist_ok=True)
    files = [out / f"start_{i:04d}.npz" for i in range(len(starts))]
    todo = [(i, template.from_start(tuple(float(v) for v in s), f))
            for i, (s, f) in enumerate(zip(starts, files)) if not _done(f, s, template)]
    say = (lambda *a: None) if template.quiet else print
    say(f"table set: {len(starts)} starts, {len(starts) - len(todo)} already built in {out}; building {len(todo)} "
        f"({'Ray' if ray_address else f'{workers} worker(s)'})")
    from tqdm.auto import tqdm

    done = 0
    with tqdm(total=len(todo), desc="tables", unit="table", disable=template.quiet) as bar:
        def finished(i: int, path: Path) -> None:
            nonlocal done
            done += 1
            bar.update()

        try:
            run_jobs(_build_member, [(job, factory) for _, job in todo], workers, ray_address, finished)
        except (ValueError, OSError, CLIError) as exc:
            raise ValueError(f"a table of the set failed ({exc}); {done} of {len(todo)} were written: rerun to "
                             "resume") from None
    write_json(out / INDEX, {
        "format": SET_FORMAT, "system": template.system.name,
        "params": json.loads(json.dumps(template.system.params(), default=list)),
        "method": template.method, "tables": [{"file": f.name, "start": s.tolist()} for f, s in zip(files, starts)],
    })
    say(f"wrote {len(starts)} tables and {out / INDEX}")
    return out


def _cached_set_differs(template: TableJob, starts: np.ndarray, folder: Path) -> str | None:
    """What makes the complete set in ``folder`` another set than ``template`` from ``starts`` would build (its
    index's system, parameters or method; a member's start, file or build settings, each checked as a rerun of
    :func:`build_table_set` checks it), or None."""
    index = json.loads(read_capped_text(folder / INDEX, MAX_JSON_BYTES, "the table-set index"))
    params = json.loads(json.dumps(template.system.params(), default=list))
    for key, want in (("system", template.system.name), ("method", template.method)):
        if index.get(key) != want:
            return f"{INDEX} {key}: {index.get(key)!r} there, {want!r} now"
    old = index.get("params") if isinstance(index.get("params"), dict) else {}
    keys = sorted(k for k in set(old) | set(params) if old.get(k) != params.get(k))
    if keys:
        return "; ".join(f"{INDEX} {k}: {old.get(k)!r} there, {params.get(k)!r} now" for k in keys[:3])
    for i, (entry, start) in enumerate(zip(index["tables"], np.asarray(starts, dtype=np.float64))):
        path = folder / f"start_{i:04d}.npz"
        if entry.get("file") != path.name:
            return f"{INDEX} member {i}: file {entry.get('file')!r} there, {path.name!r} now"
        if not np.array_equal(np.asarray(entry.get("start"), dtype=float), start):
            return f"{path.name}: start {entry.get('start')} there, {start.tolist()} now"
        try:
            table = read_table(path, graph=False)
        except (TableError, OSError) as exc:
            return f"{path.name} does not read: {exc}"
        if table.start is None or not np.array_equal(table.start, start):
            return f"{path.name}: start {None if table.start is None else table.start.tolist()} there, {start.tolist()} now"
        differ = _settings_differ(table, template)
        if differ is not None:
            return f"{path.name}: {differ}"
    return None


def ensure_table_set(template: TableJob, starts: np.ndarray, folder: Path, workers: int = 1,
                     ray_address: str | None = None) -> Path:
    """``folder``, built first by :func:`build_table_set` when it is not a complete set of ``len(starts)``. A
    complete set there is checked first as a rerun checks its members (its index's system, parameters and method;
    each member's start and build settings): one that another template or other starts built is a ValueError
    naming what differs, never used in their place."""
    if set_complete(folder, len(starts)):
        differ = _cached_set_differs(template, starts, Path(folder))
        if differ is not None:
            raise ValueError(f"the table set {folder} was built with other settings ({differ}); delete {folder} "
                             "to build it anew, or give another folder")
        return Path(folder)
    build_table_set(template, starts, folder, workers, ray_address)
    if not set_complete(folder, len(starts)):
        raise RuntimeError(f"building the table set {folder} left it incomplete")
    return Path(folder)


def set_complete(folder: Path, count: int | None = None) -> bool:
    """Whether ``folder`` holds a finished set (its index lists ``count`` tables, when given, and every file)."""
    try:
        index = json.loads(read_capped_text(Path(folder) / INDEX, MAX_JSON_BYTES, "the table-set index"))
    except (OSError, ValueError):
        return False
    tables = index.get("tables") if isinstance(index, dict) else None
    return isinstance(tables, list) and (count is None or len(tables) == count) and all(
        isinstance(t, dict) and (Path(folder) / str(t.get("file"))).is_file() for t in tables)
