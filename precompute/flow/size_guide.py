"""Build-size guidance of a max-flow build: projected level sizes and peak memory, and a warning that names
the flags that make the build smaller (used by :mod:`precompute.build`; importable from :mod:`precompute.flow.builder`)."""

from __future__ import annotations

import math
from collections.abc import Sized
from dataclasses import dataclass, field
from typing import Protocol


class StepSizes(Protocol):
    """What the guide reads of one build step (:class:`precompute.flow.builder.StepResult` is one): the lengths
    of its transitions, arcs and next level's cells. A protocol, so the guide does not import the builder."""

    src: Sized
    arc_src: Sized
    next_cells: Sized

__all__ = ["SizeGuide", "project_level_sizes", "estimate_build_bytes", "available_memory_bytes"]


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

    def update(self, step: StepSizes) -> list[str]:
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
                         f"--horizon ({shorter}) or a coarser grid (--param cell_size=[...]){extra}")
        self.exceeds = over
        return lines
