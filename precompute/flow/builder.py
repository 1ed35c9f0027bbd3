"""Build a C-Uniform table level by level: level sets, flow networks, exact max-flow, probabilities.

Shapes: C cells over all levels, n / m cells of L_t / L_{t+1}, A actions, d state dimensions.

``build_table`` is the library entry point (``python -m precompute.build`` wraps it). Each finished step
t -> t+1 can be saved as a checkpoint file in ``checkpoint_dir``; a later call with ``resume=True`` loads the
finished steps (after checking that the build settings are the same) and continues, and the table it
writes is byte-identical to an uninterrupted build's. The folder also holds the build's settings, so that
:func:`check_resume` can refuse a resume with other settings (:class:`ResumeError` names the ones that changed).
"""

from __future__ import annotations

import hashlib
import json
import platform
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import scipy
import torch

from cuniform_torch.common.fileio import MAX_SMALL_JSON_BYTES, read_capped_text, write_json, write_npz
from cuniform_torch.grid.cells import Grid
from cuniform_torch.systems import System, system_to_json
from cuniform_torch.tables.file import Table, system_fields
from precompute.flow.maxflow import action_probs_from_flow, solve_maxflow, unique_arcs
from precompute.flow.size_guide import SizeGuide, available_memory_bytes, estimate_build_bytes, project_level_sizes
from precompute.levels.safe_map import LocalMap, MapError, SafeCells
from precompute.levels.sets import EmptyLevelError, LevelStep, PointMode, TieRule, next_level
from precompute.levels.start import check_start, start_array, start_state
from precompute.levels.viability import SAFE_RULE, step_generator, viable_keep, viable_levels

__all__ = ["BuildConfig", "MapError", "BuildStats", "ResumeError", "build_settings", "check_resume", "build_table", "propagate_cell_probs", "SizeGuide", "project_level_sizes",
           "estimate_build_bytes", "available_memory_bytes"]


@dataclass(frozen=True)
class BuildConfig:
    """Settings of a table build (everything that changes the table's bytes)."""

    horizon: int = 10
    points: PointMode = PointMode.CENTERS
    points_per_cell: int = 8
    seed: int = 0
    ties: TieRule = TieRule.SYMMETRIC
    """how a step onto a cell boundary is assigned: ``symmetric`` (away from its source cell, the authors' level
    sets) or ``grid`` (the state's own cell; the grid offset decides)"""
    start: tuple[float, ...] | None = None
    """the state the table is built from (default: the zero state); an SE(2)-invariant system's pose must be 0"""
    local_map: LocalMap | None = None
    """a local map in the start frame (:mod:`precompute.levels.safe_map`): safe level sets, the cells within ``radius``
    of its obstacles pruned from every level before the max-flow (None: the blind table)"""
    radius: float = 0.0
    """the robot's radius (m) the map's obstacles are inflated by"""

    def __post_init__(self) -> None:
        if isinstance(self.horizon, bool) or not isinstance(self.horizon, int) or self.horizon < 1:
            raise ValueError(f"horizon must be a positive integer (steps), got {self.horizon!r}")
        object.__setattr__(self, "points", PointMode.parse(self.points))
        object.__setattr__(self, "ties", TieRule.parse(self.ties))
        object.__setattr__(self, "start", check_start(self.start))
        if self.points is PointMode.RANDOM and self.points_per_cell < 1:
            raise ValueError(f"points_per_cell must be >= 1, got {self.points_per_cell}")


@dataclass
class StepResult:
    """Everything one step t -> t+1 contributes to the table (local row indices)."""

    next_cells: np.ndarray  # [m, d] int64
    probs: np.ndarray  # [n, A] float64
    src: np.ndarray  # [K] transitions
    act: np.ndarray
    dst: np.ndarray
    frac: np.ndarray
    arc_src: np.ndarray  # [E]
    arc_dst: np.ndarray
    arc_flow: np.ndarray
    flow_value: int
    zero_outflow: int
    kept_fraction: float

    _KEYS = ("next_cells", "probs", "src", "act", "dst", "frac", "arc_src", "arc_dst", "arc_flow")

    def save(self, path: Path, fingerprint: str) -> None:
        arrays = {k: getattr(self, k) for k in self._KEYS}
        arrays["scalars"] = np.array([self.flow_value, self.zero_outflow], dtype=np.int64)
        arrays["kept_fraction"] = np.array(self.kept_fraction)
        arrays["fingerprint"] = np.array(fingerprint)
        write_npz(path, arrays, compress=False)

    @classmethod
    def load(cls, path: Path, fingerprint: str) -> StepResult | None:
        try:
            with np.load(path, allow_pickle=False) as z:
                if str(z["fingerprint"][()]) != fingerprint:
                    return None
                arrays = {k: z[k] for k in cls._KEYS}
                flow_value, zero = (int(v) for v in z["scalars"])
                kept = float(z["kept_fraction"][()])
        except Exception:  # a damaged checkpoint is recomputed, never trusted
            return None
        return cls(**arrays, flow_value=flow_value, zero_outflow=zero, kept_fraction=kept)


@dataclass
class BuildStats:
    """Timings (seconds) and per-step facts of a build."""

    seconds: dict[str, float] = field(default_factory=lambda: {"levels": 0.0, "arcs": 0.0, "maxflow": 0.0, "probabilities": 0.0, "write": 0.0})
    resumed_steps: int = 0
    kept_fraction: list[float] = field(default_factory=list)
    zero_outflow: list[int] = field(default_factory=list)


def propagate_cell_probs(prev: np.ndarray, probs: np.ndarray, src, act, dst, frac, m: int) -> np.ndarray:
    """Exact next-level cell distribution: ``P'[j] = sum P[i] p(a|i) frac(i,a,j)`` -> ``[m]`` float64."""
    return np.bincount(dst, weights=prev[src] * probs[src, act] * frac, minlength=m)


def _fingerprint(system: System, config: BuildConfig) -> str:
    spec = {"system": system_to_json(system, config.horizon), "points": config.points.value,
            "points_per_cell": config.points_per_cell if config.points is PointMode.RANDOM else None,
            "seed": config.seed if config.points is PointMode.RANDOM else None, "ties": config.ties.value,
            **_map_settings(config)}
    return hashlib.sha256(json.dumps(spec, sort_keys=True).encode()).hexdigest()


class ResumeError(ValueError):
    """A resume refused by :func:`check_resume`: the checkpoints are of a build with other settings."""


MANIFEST = "build.json"
"""the settings of the build whose steps a checkpoint folder holds"""


def build_settings(system: System, config: BuildConfig) -> dict:
    """The settings that make a table, by their flag names (``horizon``, ``num_actions``, ...): JSON types."""
    random = config.points is PointMode.RANDOM
    return json.loads(json.dumps({
        "system": system.name, **system.params(), "horizon": config.horizon, "points": config.points.value,
        "points_per_cell": config.points_per_cell if random else None, "seed": config.seed if random else None,
        "ties": config.ties.value, **_map_settings(config)}))


def _map_settings(config: BuildConfig) -> dict:
    """The map's part of the build settings: nothing for a blind build, else its sha256, frame and radius."""
    m = config.local_map
    if m is None:
        return {}
    return {"map_sha256": m.sha256(), "map_origin": list(m.origin), "map_resolution": m.resolution,
            "map_shape": list(m.shape), "map_radius": float(config.radius), "map_rule": SAFE_RULE}


_BUILD_FLAGS = {"system": "--system", "horizon": "--horizon", "points": "--points", "points_per_cell": "--points-per-cell",
                "seed": "--seed", "ties": "--ties", "map_radius": "--radius"}
"""the flags of ``python -m precompute.build`` that set a build setting; the other settings are the map's or the
system's parameters"""


def _setting_name(key: str) -> str:
    """How a user sets the build setting ``key``: its flag, ``--param KEY`` for a system parameter (the per-system
    flags such as ``--num-actions`` are gone), or the map's own (its file decides)."""
    if key in _BUILD_FLAGS:
        return _BUILD_FLAGS[key]
    if key.startswith("map_"):
        return f"the map's {key[4:]} (--map)"
    return f"--param {key}"


def check_resume(checkpoint_dir: str | Path, system: System, config: BuildConfig) -> None:
    """ResumeError naming every setting (old and new value) that differs from the build whose steps
    ``checkpoint_dir`` holds; a no-op for a folder without settings (none yet, or from an older version)."""
    ckpt, settings = Path(checkpoint_dir), build_settings(system, config)
    try:
        saved = json.loads(read_capped_text(ckpt / MANIFEST, MAX_SMALL_JSON_BYTES, "a build manifest"))
    except (OSError, ValueError):
        return  # no manifest (an old folder) or a damaged one: the per-step fingerprints still guard the table
    if not isinstance(saved, dict):
        return
    changed = [k for k in sorted(set(saved) | set(settings)) if saved.get(k) != settings.get(k)]
    if changed:
        detail = "; ".join(f"{_setting_name(k)} was {saved.get(k)!r}, now {settings.get(k)!r}" for k in changed)
        raise ResumeError(f"--resume: the checkpoints in {ckpt} are of a build with other settings ({detail}); "
                          "resume with the old values, or rerun without --resume to start over")


def _solve_step(system: System, cells: np.ndarray, config: BuildConfig, t: int, stats: BuildStats,
                safe: SafeCells | None = None, keep: Callable | None = None) -> StepResult:
    A = system.action_set().shape[0]
    t0 = time.perf_counter()
    gen = step_generator(config.points, config.seed, t)  # per-step stream: resumable
    try:
        lvl: LevelStep = next_level(system, cells, config.points, config.points_per_cell, gen, config.ties,
                                    keep=keep)
    except EmptyLevelError:
        raise MapError(f"the map leaves no free cell at level {t + 1}: every cell reachable in {t + 1} step(s) lies "
                       f"within --radius {safe.radius:g} m of an obstacle (the start is boxed in)") from None
    t1 = time.perf_counter()
    n, m = len(cells), len(lvl.next_cells)
    arc_src, arc_dst, arc_index = unique_arcs(lvl.src, lvl.dst, m)
    flow = solve_maxflow(n, m, arc_src, arc_dst)
    t2 = time.perf_counter()
    probs, zero = action_probs_from_flow(n, A, lvl.src, lvl.act, arc_index, lvl.frac, flow)
    if safe is not None and zero.any():  # a cell without flow: uniform over its actions that stay free
        free = np.zeros((n, A), dtype=bool)
        free[lvl.src, lvl.act] = True
        some = zero & free.any(axis=1)
        probs[some] = free[some] / free[some].sum(axis=1, keepdims=True)
    t3 = time.perf_counter()
    stats.seconds["levels"] += lvl.seconds[0]
    stats.seconds["arcs"] += (t1 - t0) - lvl.seconds[0]
    stats.seconds["maxflow"] += t2 - t1
    stats.seconds["probabilities"] += t3 - t2
    return StepResult(lvl.next_cells, probs, lvl.src, lvl.act, lvl.dst, lvl.frac, flow.arc_src, flow.arc_dst,
                      flow.arc_flow, flow.value, int(zero.sum()), lvl.kept_fraction)


def build_table(
    system: System,
    config: BuildConfig = BuildConfig(),
    checkpoint_dir: str | Path | None = None,
    resume: bool = False,
    progress: Callable[[int, StepResult], None] | None = None,
    method: str = "maxflow",
) -> tuple[Table, BuildStats]:
    """Build the C-Uniform table of ``system`` from ``config.start`` (default: the zero state) for
    ``config.horizon`` steps.

    ``progress(t, step)`` is called after each step t -> t+1. With ``checkpoint_dir`` every step is saved there,
    with the build's settings (:func:`build_settings`); ``resume=True`` reuses the saved steps of a build with
    the same settings (others are recomputed; :func:`check_resume` first refuses them instead).
    """
    stats = BuildStats()
    fingerprint = _fingerprint(system, config)
    ckpt = Path(checkpoint_dir) if checkpoint_dir is not None else None
    if ckpt is not None:
        write_json(ckpt / MANIFEST, build_settings(system, config))
    grid = Grid.of(system)
    x0 = start_state(system, config.start)  # [1, d]
    safe = None if config.local_map is None else SafeCells(system, config.local_map, config.radius)
    viable = None
    if safe is not None:
        safe.check_start(grid.cells(x0), x0)
        viable = viable_levels(system, grid.cells(x0).numpy(), config.horizon, safe, config.points,
                               config.points_per_cell, config.seed, config.ties)  # no dead ends (viability.py)
    level_cells = [grid.cells(x0).numpy()]  # L_0: the start cell
    steps: list[StepResult] = []
    for t in range(config.horizon):
        path = ckpt / f"step_{t:04d}.npz" if ckpt is not None else None
        step = StepResult.load(path, fingerprint) if (resume and path is not None and path.exists()) else None
        if step is not None and len(step.probs) == len(level_cells[-1]):
            stats.resumed_steps += 1
        else:
            keep = None if viable is None else viable_keep(safe, viable[t + 1])
            step = _solve_step(system, level_cells[-1], config, t, stats, safe, keep)
            if path is not None:
                step.save(path, fingerprint)
        steps.append(step)
        level_cells.append(step.next_cells)
        stats.kept_fraction.append(step.kept_fraction)
        stats.zero_outflow.append(step.zero_outflow)
        if progress is not None:
            progress(t, step)

    t0 = time.perf_counter()
    table = _assemble(system, config, level_cells, steps, method, safe)
    stats.seconds["probabilities"] += time.perf_counter() - t0
    return table, stats


def _assemble(system: System, config: BuildConfig, level_cells: list[np.ndarray], steps: list[StepResult], method: str,
              safe: SafeCells | None = None) -> Table:
    A = system.action_set().shape[0]
    sizes = np.array([len(c) for c in level_cells], dtype=np.int64)
    offsets = np.concatenate(([0], np.cumsum(sizes))).astype(np.int64)
    probs = [s.probs for s in steps] + [np.full((sizes[-1], A), 1.0 / A)]  # last level: uniform
    cell_probs = [np.ones(1)]
    for t, s in enumerate(steps):
        nxt = propagate_cell_probs(cell_probs[-1], s.probs, s.src, s.act, s.dst, s.frac, int(sizes[t + 1]))
        if safe is not None:  # the mass of the actions into obstacles is gone: the distribution given no collision
            if not nxt.sum() > 0:
                raise MapError(f"every trajectory of the table collides before level {t + 1}")
            nxt = nxt / nxt.sum()
        cell_probs.append(nxt)

    arc_counts = np.array([len(s.arc_src) for s in steps], dtype=np.int64)
    trans_counts = np.array([len(s.src) for s in steps], dtype=np.int64)
    arcs = np.concatenate([np.stack((s.arc_src + offsets[t], s.arc_dst + offsets[t + 1]), 1) for t, s in enumerate(steps)])
    transitions = np.concatenate(
        [np.stack((s.src + offsets[t], s.act, s.dst + offsets[t + 1]), 1) for t, s in enumerate(steps)]
    )
    build_info = {
        "points": config.points.value,
        "ties": config.ties.value,
        "points_per_cell": config.points_per_cell if config.points is PointMode.RANDOM else None,
        "seed": config.seed if config.points is PointMode.RANDOM else None,
        "lattice_scale": "delta/2.01",
        "origin": "start cell of the zero state" if config.start is None else f"start cell of {list(config.start)}",
        "zero_outflow_cells": [s.zero_outflow for s in steps],
        "versions": {"python": platform.python_version(), "numpy": np.__version__, "scipy": scipy.__version__,
                     "torch": torch.__version__.split("+")[0]},
    }
    if safe is not None:  # blind tables keep their bytes
        build_info["map_rule"] = SAFE_RULE
    return Table(
        **system_fields(system, config.horizon),
        level_offsets=offsets,
        cells=np.concatenate(level_cells).astype(np.int64),
        action_probs=np.concatenate(probs).astype(np.float32),
        cell_probs=np.concatenate(cell_probs),
        flow_value=np.array([s.flow_value for s in steps], dtype=np.int64),
        flow_target=(sizes[:-1] * sizes[1:]).astype(np.int64),
        method=method,
        build_info=json.dumps(build_info, sort_keys=True),
        start=start_array(config.start),
        arc_offsets=np.concatenate(([0], np.cumsum(arc_counts))).astype(np.int64),
        arcs=arcs.astype(np.int64),
        arc_flow=np.concatenate([s.arc_flow for s in steps]).astype(np.int64),
        transition_offsets=np.concatenate(([0], np.cumsum(trans_counts))).astype(np.int64),
        transitions=transitions.astype(np.int64),
        transition_frac=np.concatenate([s.frac for s in steps]).astype(np.float64),
        **({} if safe is None else safe.table_keys()),
    )
