"""The coverage method: C-Uniform-style tables that make *real* rollouts cover the reachable cells.

Shapes: M_t merged reachable states at level t, n_t reachable cells of level t, A actions, d state dims, T horizon.

The paper's flow network treats each cell as one point with deterministic arcs, while a controller executes
real actions from real states: one action from one cell lands in several next cells, and states leave the
level sets. This method works on the states that real rollouts can reach:

1. **Enumerate** (:mod:`precompute.coverage.reachable`) the states reachable from the origin level by level
   under every action, merging states that fall in the same sub-cell bin (``merge_resolution`` bins per cell
   and dimension; each bin keeps its first state as the representative, so the approximation error is below
   1/merge_resolution of a cell per step).
   The level set L_t is the set of cells of these states: exactly the cells real rollouts reach.
   A level that would hold more than ``state_budget`` merged states is merged more coarsely (the resolution
   is cut by a quarter, from that level on, until it fits): the cost of every later stage is linear in the
   merged states, whose number grows geometrically with the horizon at a fixed resolution (``state_budget=0``:
   never coarsen).
2. **Propagate** the state distribution exactly: a state in cell c takes action u with probability
   ``softmax(theta[t, c])[u]`` and moves deterministically to its successor state.
3. **Maximize** the expected number of distinct cells that N samples cover at every level,
   ``sum_t sum_c 1 - (1 - P_t(c))^N`` (``target_samples`` = N), over the logits theta by gradient ascent (Adam;
   the gradient by the adjoint of the propagation, :mod:`precompute.coverage.adjoint`). Perfect uniformity over
   L_t is the optimum when N is large; a finite N trades uniformity for reaching more cells. The ascent stops
   early once the objective gained less than ``tol`` (relative) over the last ``CONVERGENCE_WINDOW`` steps
   (``tol=0``: always ``steps`` iterations).

The table has the same format as the max-flow tables (``method`` = "coverage"): its level sets are the reachable
cells, ``cell_probs`` the exact propagated cell masses, ``transitions`` the mass-weighted fraction of each
(cell, action)'s states landing in each next cell (so ``cell_probs`` is again their exact propagation), and
``flow_value`` is 0 (there is no flow network; the report shows "-").
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import cast

import numpy as np
import torch

from cuniform_torch.common.checks import check_positive_int
from cuniform_torch.systems import System
from cuniform_torch.tables.file import Table, system_fields
from precompute.coverage.adjoint import StatePropagator
from precompute.coverage.reachable import ReachableLevels, enumerate_reachable
from precompute.levels.safe_map import LocalMap, SafeCells, map_table_keys
from precompute.levels.start import check_start, start_array

CONVERGENCE_WINDOW = 10
"""steps over which the early stop (``CoverageConfig.tol``) measures the objective's relative gain"""

__all__ = ["CoverageConfig", "ReachableLevels", "enumerate_reachable", "coverage_objective", "optimize_coverage",
           "build_coverage_table"]


@dataclass(frozen=True)
class CoverageConfig:
    """Settings of the coverage method."""

    horizon: int = 10
    target_samples: int = 2000
    """N in the objective: the number of rollouts whose expected coverage is maximized"""
    merge_resolution: int = 32
    """sub-cell bins per cell and dimension used to merge reachable states"""
    steps: int = 300
    """gradient-ascent iterations"""
    lr: float = 0.2
    """Adam learning rate on the logits"""
    entropy_weight: float = 10.0
    """adds ``entropy_weight * sum_t H(P_t) / log n_t`` (normalized entropy of each level's cell distribution): a
    tie-breaker towards uniformity on levels that N samples already cover completely"""
    max_states: int = 20_000_000
    """refuse to enumerate a level with more merged states than this (lower merge_resolution instead)"""
    state_budget: int = 2_000_000
    """merged states per level: a level with more is merged with a quarter less resolution (repeatedly, and so
    are the later levels) until it fits; 0 keeps merge_resolution on every level (the unapproximated enumeration)"""
    start: tuple[float, ...] | None = None
    """the state the table is built from (default: the zero state); an SE(2)-invariant system's pose must be 0"""
    tol: float = 0.0
    """stop the ascent when the objective gained less than this fraction over the last 10 steps; 0 (default) runs
    all steps. 1e-3 halves the default preset's build (89 of 300 steps) for 0.6% less coverage at N = 1000"""
    float32: bool = True
    """run the gradient ascent in float32 (about 2x faster); the final propagation is float64"""
    local_map: LocalMap | None = None
    """a local map in the start frame (:mod:`precompute.levels.safe_map`): states whose cell lies within ``radius`` of
    its obstacles are dropped (their successor is -1: the mass of that action is lost), None: blind"""
    radius: float = 0.0
    """the robot's radius (m) the map's obstacles are inflated by"""

    def __post_init__(self) -> None:
        for name in ("horizon", "target_samples", "merge_resolution", "steps", "max_states"):
            check_positive_int(name, getattr(self, name), integral=False)
        if not (self.lr > 0 and math.isfinite(self.lr)):
            raise ValueError(f"lr must be positive, got {self.lr!r}")
        if isinstance(self.state_budget, bool) or not isinstance(self.state_budget, int) or self.state_budget < 0:
            raise ValueError(f"state_budget must be a non-negative integer (0: no budget), got {self.state_budget!r}")
        if not (self.tol >= 0 and math.isfinite(self.tol)):
            raise ValueError(f"tol must be non-negative (0: no early stop), got {self.tol!r}")
        object.__setattr__(self, "start", check_start(self.start))


def _propagate(levels: ReachableLevels, logits: list[torch.Tensor]) -> list[torch.Tensor]:
    """Cell masses ``[n_t]`` of every level for per-level logits ``[n_t, A]`` (differentiable, logits' dtype): the
    autograd reference the compiled passes of :class:`~precompute.coverage.adjoint.StatePropagator` are tested
    against (the build uses those)."""
    dtype = logits[0].dtype if logits else torch.float64
    mass = torch.ones(1, dtype=dtype)
    out = []
    for t in range(len(levels.cells)):
        n = len(levels.cells[t])
        out.append(torch.zeros(n, dtype=dtype).index_add(0, levels.state_cell[t], mass))
        if t < len(levels.successor):
            probs = torch.softmax(logits[t], dim=1)[levels.state_cell[t]]  # [M_t, A]
            succ = levels.successor[t].reshape(-1)
            moved = (mass.unsqueeze(1) * probs).reshape(-1)
            ok = succ >= 0  # a pruned successor's mass is lost
            mass = torch.zeros(levels.num_states[t + 1], dtype=dtype).index_add(0, succ[ok], moved[ok])
    return out


def expected_coverage(cell_mass: torch.Tensor, num_samples: int) -> torch.Tensor:
    """``sum_c 1 - (1 - P(c))^N``: expected distinct cells hit by N independent draws."""
    top = 1.0 - 1e-12 if cell_mass.dtype == torch.float64 else 1.0 - 1e-6
    return (1.0 - torch.exp(num_samples * torch.log1p(-cell_mass.clamp(max=top)))).sum()


def normalized_entropy(cell_mass: torch.Tensor) -> torch.Tensor:
    """``H(P) / log n`` in [0, 1] (1 = uniform over the n cells)."""
    p = cell_mass.clamp(min=1e-300)
    return -(cell_mass * torch.log(p)).sum() / math.log(len(cell_mass))


def _converged(history: list[float], tol: float) -> bool:
    """Whether the objective gained less than ``tol`` (relative) over the last CONVERGENCE_WINDOW steps."""
    if tol <= 0 or len(history) <= CONVERGENCE_WINDOW:
        return False
    gain = history[-1] - history[-1 - CONVERGENCE_WINDOW]
    return gain < tol * abs(history[-1])


def coverage_objective(cell_masses: list[torch.Tensor], config: CoverageConfig) -> torch.Tensor:
    """The ascent's objective from the cell masses ``[n_t]`` of levels 1..T: summed expected coverage of
    ``target_samples`` draws plus the entropy tie-breaker."""
    # the sums start at the int 0 (as sum() does), typed as the tensors they become
    objective = cast(torch.Tensor, sum(expected_coverage(m, config.target_samples) for m in cell_masses))
    if config.entropy_weight:
        objective = objective + config.entropy_weight * sum(normalized_entropy(m) for m in cell_masses if len(m) > 1)
    return objective


def _ascent_step(propagator: StatePropagator, logits: list[torch.Tensor], config: CoverageConfig) -> float:
    """Set ``logits[t].grad`` to minus the objective's gradient (the adjoint over the states, autograd over the
    small per-cell parts); returns the objective."""
    probs = [torch.softmax(l, dim=1) for l in logits]  # [n_t, A], differentiable in the logits
    with torch.no_grad():
        cells = propagator.forward([p.detach() for p in probs])
    leaves = [c.requires_grad_() for c in cells[1:]]
    objective = coverage_objective(leaves, config)
    cell_grads = [torch.zeros_like(cells[0])] + list(torch.autograd.grad(objective, leaves))
    with torch.no_grad():
        prob_grads = propagator.backward([p.detach() for p in probs], cell_grads)
    torch.autograd.backward(probs, [-g for g in prob_grads])
    return float(objective.detach())


def optimize_coverage(levels: ReachableLevels, num_actions: int, config: CoverageConfig,
                      progress: Callable[[int, float], None] | None = None) -> tuple[list[torch.Tensor], list[float]]:
    """Logits ``[n_t, A]`` per level t < T maximizing the summed expected coverage; and the history of the objective."""
    dtype = torch.float32 if config.float32 else torch.float64
    logits = [torch.zeros((len(c), num_actions), dtype=dtype, requires_grad=True) for c in levels.cells[:-1]]
    opt = torch.optim.Adam(logits, lr=config.lr)
    propagator = StatePropagator(levels, num_actions, dtype)
    history: list[float] = []
    for step in range(config.steps):
        opt.zero_grad()
        history.append(_ascent_step(propagator, logits, config))
        opt.step()
        if progress is not None:
            progress(step, history[-1])
        if _converged(history, config.tol):
            break
    return [l.detach().double() for l in logits], history


def build_coverage_table(system: System, config: CoverageConfig = CoverageConfig(),
                         progress: Callable[[str, int, float], None] | None = None) -> tuple[Table, dict]:
    """Enumerate, optimize and assemble the table; returns it with build facts (timings, predicted coverage)."""
    t0 = time.perf_counter()
    levels = enumerate_reachable(system, config.horizon, config.merge_resolution, config.max_states,
                                 None if progress is None else (lambda t, m, n: progress("enumerate", t, m)),
                                 state_budget=config.state_budget, start=config.start,
                                 safe=None if config.local_map is None else
                                 SafeCells(system, config.local_map, config.radius))
    t1 = time.perf_counter()
    A = system.action_set().shape[0]
    logits, history = optimize_coverage(levels, A, config,
                                        None if progress is None else (lambda s, v: progress("optimize", s, v)))
    t2 = time.perf_counter()
    probs = [torch.softmax(l, dim=1) for l in logits] + [torch.full((len(levels.cells[-1]), A), 1.0 / A, dtype=torch.float64)]
    # the exact propagation in float64 (the compiled passes; _propagate's arithmetic in the same order): the cell
    # masses, and the state masses the transitions are weighted by
    final = StatePropagator(levels, A, torch.float64)
    masses = final.forward(probs[:-1])
    sizes = np.array([len(c) for c in levels.cells], dtype=np.int64)
    offsets = np.concatenate(([0], np.cumsum(sizes))).astype(np.int64)
    from precompute.coverage.loops import level_transitions  # numba: compiled (or loaded) on first use

    transitions, fracs, trans_counts = [], [], []
    for t in range(config.horizon):
        sc, succ = levels.state_cell[t], levels.successor[t]  # [M], [M, A]
        # each (cell, action, next cell) reached, ascending, with the fraction of the (cell, action)'s mass
        # landing there (states without mass count equally): one compiled pass over the cells' states
        src, act, dst, frac = level_transitions(sc.numpy(), succ.reshape(-1).numpy(),
                                                levels.state_cell[t + 1].numpy(), final.mass[t],
                                                len(levels.cells[t]), A)
        transitions.append(torch.from_numpy(np.stack((src + offsets[t], act, dst + offsets[t + 1]), 1)))
        fracs.append(torch.from_numpy(frac))
        trans_counts.append(len(src))
    predicted = {str(N): [float(expected_coverage(mm, N)) for mm in masses] for N in (250, 1000, 10000)}
    facts = {
        "seconds": {"enumerate": t1 - t0, "optimize": t2 - t1, "assemble": time.perf_counter() - t2},
        "merged_states": levels.num_states,
        "merge_resolutions": levels.resolution,
        "steps_run": len(history),
        "objective_first_last": [history[0], history[-1]] if history else [],
        "predicted_coverage_per_level": predicted,
    }
    build_info = {"method": "coverage", "target_samples": config.target_samples,
                  "merge_resolution": config.merge_resolution, "steps": config.steps, "lr": config.lr,
                  "merged_states": levels.num_states, "state_budget": config.state_budget,
                  "merge_resolutions": levels.resolution, "tol": config.tol, "steps_run": len(history)}
    cell_probs = torch.cat(masses).numpy()
    table = Table(
        **system_fields(system, config.horizon),
        level_offsets=offsets,
        cells=torch.cat(levels.cells).numpy().astype(np.int64),
        action_probs=torch.cat(probs).numpy().astype(np.float32),
        cell_probs=cell_probs / np.add.reduceat(cell_probs, offsets[:-1]).repeat(sizes),
        flow_value=np.zeros(config.horizon, dtype=np.int64),
        flow_target=(sizes[:-1] * sizes[1:]).astype(np.int64),
        method="coverage",
        build_info=json.dumps(build_info, sort_keys=True),
        start=start_array(config.start),
        transition_offsets=np.concatenate(([0], np.cumsum(trans_counts))).astype(np.int64),
        transitions=torch.cat(transitions).numpy().astype(np.int64),
        transition_frac=torch.cat(fracs).numpy(),
        **({} if config.local_map is None else map_table_keys(config.local_map, config.radius)),
    )
    return table, facts
