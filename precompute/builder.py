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
import math
import platform
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import scipy
import torch

from cuniform_torch.fileio import write_json, write_npz
from cuniform_torch.grid import Grid
from cuniform_torch.systems import System, system_to_json
from cuniform_torch.table import Table, system_fields

from .levels import LevelStep, PointMode, TieRule, next_level
from .maxflow import action_probs_from_flow, solve_maxflow, unique_arcs
from .start import check_start, start_array, start_state

__all__ = ["BuildConfig", "BuildStats", "ResumeError", "build_settings", "check_resume", "build_table", "propagate_cell_probs", "SizeGuide", "project_level_sizes",
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
    def load(cls, path: Path, fingerprint: str) -> "StepResult | None":
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
            "seed": config.seed if config.points is PointMode.RANDOM else None, "ties": config.ties.value}
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
        "ties": config.ties.value}))


def check_resume(checkpoint_dir: str | Path, system: System, config: BuildConfig) -> None:
    """ResumeError naming every setting (old and new value) that differs from the build whose steps
    ``checkpoint_dir`` holds; a no-op for a folder without settings (none yet, or from an older version)."""
    ckpt, settings = Path(checkpoint_dir), build_settings(system, config)
    try:
        saved = json.loads((ckpt / MANIFEST).read_text())
    except (OSError, ValueError):
        return  # no manifest (an old folder) or a damaged one: the per-step fingerprints still guard the table
    if not isinstance(saved, dict):
        return
    changed = [k for k in sorted(set(saved) | set(settings)) if saved.get(k) != settings.get(k)]
    if changed:
        flag = lambda k: "--" + k.replace("_", "-")  # noqa: E731
        detail = "; ".join(f"{flag(k)} was {saved.get(k)!r}, now {settings.get(k)!r}" for k in changed)
        raise ResumeError(f"--resume: the checkpoints in {ckpt} are of a build with other settings ({detail}); "
                          "resume with the old values, or rerun without --resume to start over")


def _solve_step(system: System, cells: np.ndarray, config: BuildConfig, t: int, stats: BuildStats) -> StepResult:
    A = system.action_set().shape[0]
    t0 = time.perf_counter()
    gen = None
    if config.points is PointMode.RANDOM:
        gen = torch.Generator().manual_seed(config.seed * 1_000_003 + t)  # per-step stream: resumable
    lvl: LevelStep = next_level(system, cells, config.points, config.points_per_cell, gen, config.ties)
    t1 = time.perf_counter()
    n, m = len(cells), len(lvl.next_cells)
    arc_src, arc_dst, arc_index = unique_arcs(lvl.src, lvl.dst, m)
    flow = solve_maxflow(n, m, arc_src, arc_dst)
    t2 = time.perf_counter()
    probs, zero = action_probs_from_flow(n, A, lvl.src, lvl.act, arc_index, lvl.frac, flow)
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
    level_cells = [grid.cells(x0).numpy()]  # L_0: the start cell
    steps: list[StepResult] = []
    for t in range(config.horizon):
        path = ckpt / f"step_{t:04d}.npz" if ckpt is not None else None
        step = StepResult.load(path, fingerprint) if (resume and path is not None and path.exists()) else None
        if step is not None and len(step.probs) == len(level_cells[-1]):
            stats.resumed_steps += 1
        else:
            step = _solve_step(system, level_cells[-1], config, t, stats)
            if path is not None:
                step.save(path, fingerprint)
        steps.append(step)
        level_cells.append(step.next_cells)
        stats.kept_fraction.append(step.kept_fraction)
        stats.zero_outflow.append(step.zero_outflow)
        if progress is not None:
            progress(t, step)

    t0 = time.perf_counter()
    table = _assemble(system, config, level_cells, steps, method)
    stats.seconds["probabilities"] += time.perf_counter() - t0
    return table, stats


def _assemble(system: System, config: BuildConfig, level_cells: list[np.ndarray], steps: list[StepResult], method: str) -> Table:
    A = system.action_set().shape[0]
    sizes = np.array([len(c) for c in level_cells], dtype=np.int64)
    offsets = np.concatenate(([0], np.cumsum(sizes))).astype(np.int64)
    probs = [s.probs for s in steps] + [np.full((sizes[-1], A), 1.0 / A)]  # last level: uniform
    cell_probs = [np.ones(1)]
    for t, s in enumerate(steps):
        cell_probs.append(propagate_cell_probs(cell_probs[-1], s.probs, s.src, s.act, s.dst, s.frac, int(sizes[t + 1])))

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
    )


# ------------------------------------------------------------------------------------------ size guidance

# Peak memory model of a maxflow build plus its report, calibrated on the ks preset at horizons 10 and 15
# (peak RSS 1.27 GB and 11.0 GB; the model says 1.33 GB and 11.3 GB): every recorded transition and flow arc is
# held per step, then concatenated into the table, and the report's TablePolicy indexes every cell with its
# 3^d - 1 neighbours (the nearest-cell halo). Transitions and arcs per cell are those of the latest step,
# applied to every level, which leans high.
_BASE_BYTES = 400e6  # python, torch, scipy
_BYTES_PER_TRANSITION = 84  # src, act, dst, frac per step; the table's transitions [K, 3] and frac; copies
_BYTES_PER_ARC = 56  # arc_src, arc_dst, arc_flow per step; arcs [E, 2], arc_flow; the flow network
_HALO_BYTES = 17  # per halo entry and key component: int64 keys, sort orders and the sorted copy


def project_level_sizes(sizes: list[int], horizon: int, num_actions: int) -> list[int]:
    """Extrapolate measured level sizes ``n_0..n_t`` (t >= 3) to ``n_0..n_horizon``: an upper-leaning estimate.

    Level sets of vehicles grow like a power of t whose local exponent ``p_t = log(n_t / n_{t-1}) / log(t / (t-1))``
    still rises over the first levels; the projection continues the last exponent and its last rise
    (``n_s = n_{s-1} (s / (s-1))^p``, ``p`` += the last rise, never falling), and caps every level at A times
    the one before. Projected from level 6 on, the final level of the ks, ks_speed and Dubins presets comes out
    at 0.8-3x its true size; earlier projections can be far off, so :class:`SizeGuide` re-makes it every level.
    """
    t = len(sizes) - 1
    if t < 3 or any(n < 1 for n in sizes):
        raise ValueError(f"a projection needs levels 0..3 or more with cells, got {sizes}")
    out = [int(n) for n in sizes]
    p1 = math.log(sizes[t] / sizes[t - 1]) / math.log(t / (t - 1))
    p0 = math.log(sizes[t - 1] / sizes[t - 2]) / math.log((t - 1) / (t - 2))
    rise, p, n = max(0.0, p1 - p0), p1, float(sizes[t])
    for s in range(t + 1, horizon + 1):
        p += rise
        n = min(n * (s / (s - 1)) ** max(p, 0.0), n * num_actions)
        out.append(int(math.ceil(n)))
    return out


def estimate_build_bytes(sizes: list[int], transitions_per_cell: float, arcs_per_cell: float, state_dim: int,
                         num_actions: int, report: bool = True) -> float:
    """Estimated peak memory (bytes) of building (and, with ``report``, reporting on) a table with these level
    sizes, when each cell of a level has ``transitions_per_cell`` recorded transitions and ``arcs_per_cell``
    flow arcs into the next level."""
    total = float(sum(sizes))
    sources = float(sum(sizes[:-1]))
    bytes_ = _BASE_BYTES + sources * (transitions_per_cell * _BYTES_PER_TRANSITION + arcs_per_cell * _BYTES_PER_ARC)
    bytes_ += total * (state_dim * 8 + num_actions * 12)  # cells, probabilities
    if report:
        bytes_ += total * (3 ** state_dim - 1) * (1 + state_dim) * _HALO_BYTES
    return bytes_


def available_memory_bytes() -> int | None:
    """``MemAvailable`` of /proc/meminfo (Linux), else physical memory from sysconf, else None."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        import os

        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return None


@dataclass
class SizeGuide:
    """Build-size guidance: fed every finished step, it projects the level sizes and the build's peak memory
    from level ``first_level`` on and says when the projection exceeds ``budget_bytes``.

    :meth:`update` returns the lines to print: the projection (when first made, and again when the projected
    total changes by more than 2x); a warning, which names the flags that make the build smaller, when the
    projection first exceeds the budget; and a note when a later (better) projection fits again. Level 5 is the
    first projection because earlier ones are far off (on ks at level 4: 6.6 million cells against 1.1 million).
    """

    horizon: int
    num_actions: int
    state_dim: int
    budget_bytes: float | None
    report: bool = True
    first_level: int = 5
    sizes: list[int] = field(default_factory=lambda: [1])
    transitions: list[int] = field(default_factory=list)
    arcs: list[int] = field(default_factory=list)
    projection: list[int] | None = None
    """the latest projected level sizes"""
    estimate_bytes: float | None = None
    """the latest projected peak memory"""
    warned: bool = False
    """whether a warning was given"""
    exceeds: bool = False
    """whether the latest projection exceeds the budget"""
    _printed_total: int | None = None

    def update(self, step: "StepResult") -> list[str]:
        self.transitions.append(len(step.src))
        self.arcs.append(len(step.arc_src))
        self.sizes.append(len(step.next_cells))
        t = len(self.sizes) - 1
        if t < self.first_level or t >= self.horizon:
            return []
        proj = project_level_sizes(self.sizes, self.horizon, self.num_actions)
        per_trans = self.transitions[-1] / self.sizes[-2]  # of the latest step, per source cell (still rising)
        per_arc = self.arcs[-1] / self.sizes[-2]
        estimate = estimate_build_bytes(proj, per_trans, per_arc, self.state_dim, self.num_actions, self.report)
        self.projection, self.estimate_bytes = proj, estimate
        lines = []
        total = sum(proj)
        if self._printed_total is None or not 0.5 <= total / self._printed_total <= 2.0:
            self._printed_total = total
            lines.append(f"projected level sizes after {t} levels (an upper-leaning estimate): {proj[t + 1:]} for "
                         f"levels {t + 1}..{self.horizon}; about {total:,} cells, {estimate / 1e9:.1f} GB peak memory")
        over = self.budget_bytes is not None and estimate > self.budget_bytes
        if self.exceeds and not over:
            lines.append(f"the projection now fits in the {self.budget_bytes / 1e9:.1f} GB available "
                         f"(about {estimate / 1e9:.1f} GB); the warning above no longer applies")
        if over and not self.exceeds:
            self.warned = True
            fits = [h for h in range(1, self.horizon + 1) if estimate_build_bytes(
                proj[:h + 1], per_trans, per_arc, self.state_dim, self.num_actions, self.report) <= self.budget_bytes]
            shorter = f"--horizon {max(fits)} fits" if fits else "even --horizon 1 may not fit"
            extra = "; --no-report saves the report's lookup index" if self.report else ""
            lines.append(f"warning: this build is projected to need about {estimate / 1e9:.1f} GB, more than the "
                         f"{self.budget_bytes / 1e9:.1f} GB available (--max-memory); make it smaller with a shorter "
                         f"--horizon ({shorter}) or a coarser --cell-size{extra}")
        self.exceeds = over
        return lines
