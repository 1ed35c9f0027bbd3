"""A table set: independent tables of one system built from many starts (``python -m precompute.build --starts``).

``--starts SPEC`` names the starts over the state dimensions that matter (others are 0):

* a grid: ``DIM=LO:HI:N`` items, separated by spaces, e.g. ``"3=0:1:5"`` (speed 0, 0.25, ..., 1) or
  ``"0=-1:1:3 1=-1:1:3"`` (a 3 x 3 grid over dimensions 0 and 1);
* a seeded sample: ``random:N`` then ``DIM=LO:HI`` items, e.g. ``"random:20 3=0:1"`` (20 speeds uniform in
  [0, 1], numpy's generator seeded with ``--seed``).

For an SE(2)-invariant system x, y, theta (dimensions 0-2) cannot be given: one table serves every pose.
Every table is built by the same command as a single table, with ``--start`` added and ``--out
DIR/start_0000.npz``, ... (so each is byte-identical to a table built alone), in parallel over ``--workers N``
processes or Ray tasks (``--ray [ADDRESS]``), and skipped when it is already there with the same start (resumable
per table). ``DIR/tables.json`` describes the set: format ``cuniform-table-set/1``, the system, the method, and
per table its file and start.
"""

from __future__ import annotations

import json
import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from cuniform_torch.common.fileio import write_json
from cuniform_torch.common.parallel import run_jobs
from cuniform_torch.systems import System
from cuniform_torch.tables.file import TableError, read_table

__all__ = ["SET_FORMAT", "parse_starts", "build_set", "set_complete", "INDEX"]

SET_FORMAT = "cuniform-table-set/1"
INDEX = "tables.json"
_ITEM = re.compile(r"^(\d+)=([^:]+):([^:]+)(?::(\d+))?$")
_SET_ONLY = {"--starts": 1, "--workers": 1, "--out": 1}  # flag -> number of values it takes


def parse_starts(spec: str, system: System, seed: int = 0) -> np.ndarray:
    """The starts ``[S, d]`` float64 that ``spec`` names (module docstring); a clear ValueError otherwise."""
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
    if sample is None:
        axes = [np.linspace(ranges[k][0], ranges[k][1], ranges[k][2]) for k in dims]
        values = np.stack([a.ravel() for a in np.meshgrid(*axes, indexing="ij")], axis=1)  # [S, len(dims)]
    else:
        rng = np.random.default_rng(seed)
        values = rng.uniform([ranges[k][0] for k in dims], [ranges[k][1] for k in dims], size=(sample, len(dims)))
    starts = np.zeros((len(values), d))
    starts[:, dims] = values
    return np.round(starts, 12)  # 0.25, not 0.25000000000000006: the starts are printed and compared


def _table_argv(argv: Sequence[str], start: np.ndarray, out: Path) -> list[str]:
    """The single-table command of one start: ``argv`` less the set's own flags, plus ``--start`` and ``--out``."""
    kept, skip = [], 0
    for word in argv:
        if skip:
            skip -= 1
            continue
        flag = word.split("=", 1)[0]
        if flag in _SET_ONLY or flag == "--ray":
            skip = 0 if "=" in word or flag == "--ray" else _SET_ONLY[flag]
            continue
        kept.append(word)
    return [*kept, "--quiet", "--no-report", "--start", *[repr(float(v)) for v in start], "--out", str(out)]


def _build_one(argv: list[str]) -> int:
    from precompute.one_table import main_one

    return main_one(argv)


def _done(path: Path, start: np.ndarray) -> bool:
    """Whether ``path`` holds a readable table built from ``start``."""
    if not path.exists():
        return False
    try:
        table = read_table(path, graph=False)
    except TableError:
        return False
    return table.start is not None and np.array_equal(table.start, start)


def build_set(argv: Sequence[str], system: System, starts: np.ndarray, out: Path, workers: int = 1,
              ray_address: str | None = None, method: str = "maxflow", quiet: bool = False) -> int:
    """Build every start's table under ``out`` (module docstring); 0, or the first failing build's exit code."""
    out.mkdir(parents=True, exist_ok=True)
    files = [out / f"start_{i:04d}.npz" for i in range(len(starts))]
    todo = [(i, _table_argv(argv, s, f)) for i, (s, f) in enumerate(zip(starts, files)) if not _done(f, s)]
    say = (lambda *a: None) if quiet else print
    say(f"table set: {len(starts)} starts, {len(starts) - len(todo)} already built in {out}; building {len(todo)} "
        f"({'Ray' if ray_address else f'{workers} worker(s)'})")
    from tqdm.auto import tqdm

    with tqdm(total=len(todo), desc="tables", unit="table", disable=quiet) as bar:
        codes = run_jobs(_build_one, [(a,) for _, a in todo], workers, ray_address, lambda i, code: bar.update())
    failed = [(i, c) for (i, _), c in zip(todo, codes) if c != 0]
    if failed:
        i, code = failed[0]
        print(f"error: the table of start {starts[i].tolist()} failed (exit {code}); rerun to resume")
        return code
    write_json(out / INDEX, {
        "format": SET_FORMAT, "system": system.name, "params": json.loads(json.dumps(system.params(), default=list)),
        "method": method, "tables": [{"file": f.name, "start": s.tolist()} for f, s in zip(files, starts)],
    })
    say(f"wrote {len(starts)} tables and {out / INDEX}")
    return 0


def set_complete(folder: Path, count: int | None = None) -> bool:
    """Whether ``folder`` holds a finished set (its index lists ``count`` tables, when given, and every file)."""
    try:
        index = json.loads((Path(folder) / INDEX).read_text())
    except (OSError, ValueError):
        return False
    tables = index.get("tables") if isinstance(index, dict) else None
    return isinstance(tables, list) and (count is None or len(tables) == count) and all(
        isinstance(t, dict) and (Path(folder) / str(t.get("file"))).is_file() for t in tables)
