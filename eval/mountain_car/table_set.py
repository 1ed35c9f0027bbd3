"""The start-aware table set of ``eval.mountain_car.run``: a grid of starts over the env's (position, velocity) box,
built on first use by :func:`precompute.table_set.ensure_table_set` into a cache folder named by a hash of its
parameters (a rerun reuses it; an interrupted build resumes per table)."""

from __future__ import annotations

import hashlib
import json
import re
from pathlib import Path
from typing import Any

from cuniform_torch.common.fileio import write_json
from cuniform_torch.systems.classic import MOUNTAIN_CAR, MountainCar
from precompute.cli import CLIError

__all__ = ["parse_grid", "set_spec", "set_folder", "ensure_set"]

_GRID = re.compile(r"^(\d+)x(\d+)$")


def parse_grid(text: str) -> tuple[int, int]:
    """``"PxV"`` -> ``(P, V)``: P positions times V velocities, each at least 2 (the box's edges are starts)."""
    m = _GRID.match(text.strip()) if isinstance(text, str) else None
    if m is None or int(m[1]) < 2 or int(m[2]) < 2:
        raise CLIError(f"--set-grid must be PxV with P, V >= 2 (positions x velocities), e.g. 13x9; got {text!r}")
    return int(m[1]), int(m[2])


def set_spec(repeat: int, horizon: int, grid: tuple[int, int]) -> dict[str, Any]:
    """What the set is built from (its hash names the cache folder)."""
    c = MOUNTAIN_CAR
    starts = (f"0={c['min_position']}:{c['max_position']}:{grid[0]} "
              f"1={-c['max_speed']}:{c['max_speed']}:{grid[1]}")
    return {"system": MountainCar.name, "params": MountainCar(repeat=repeat).params(), "horizon": horizon,
            "starts": starts, "method": "maxflow"}


def set_folder(cache: Path, spec: dict[str, Any]) -> Path:
    digest = hashlib.sha256(json.dumps(spec, sort_keys=True).encode()).hexdigest()[:12]
    return Path(cache) / f"mountain_car_{digest}"


def ensure_set(cache: Path, repeat: int, horizon: int, grid: tuple[int, int], workers: int = 1,
               quiet: bool = False) -> Path:
    """The set's folder, built first when it is not complete (:func:`precompute.table_set.ensure_table_set`)."""
    from precompute.flow.builder import BuildConfig
    from precompute.one_table import TableJob
    from precompute.table_set import ensure_table_set, parse_starts, set_complete

    spec = set_spec(repeat, horizon, grid)
    folder = set_folder(cache, spec)
    system = MountainCar(repeat=repeat)
    starts = parse_starts(spec["starts"], system)
    if not set_complete(folder, len(starts)) and not quiet:
        print(f"building the table set ({grid[0]} x {grid[1]} starts, horizon {horizon}) into {folder}", flush=True)
    template = TableJob(system=system, out=folder / "start_0000.npz", build=BuildConfig(horizon=horizon),
                        report=False, quiet=quiet)
    try:
        ensure_table_set(template, starts, folder, workers=workers)
    except RuntimeError as exc:
        raise CLIError(str(exc)) from None
    write_json(folder / "spec.json", spec)
    return folder
