"""C-Uniform for a new system, chosen for the user: the action set, the cell sizes and the start grid from the
system's dynamics, its action bounds and a region of starts; then the table set, built or reused.

Shapes: P probe starts, M action sequences per probe start, T horizon, d state dimensions, q action dimensions,
A actions, k start dimensions, S members of the set.

What the user gives: a system (a dataclass of the :class:`~cuniform_torch.systems.System` protocol with a
``cell_size`` field, and a ``num_actions`` field when the chooser may pick the action count), its periodic
dimensions (``periodic``, declared by the system), the horizon and a box of starts (:func:`parse_region`:
``"0=-3.14159:3.14159 1=-8:8"``). What :func:`choose` does, and says in :attr:`Choice.reasons`:

1. **Actions.** ``actions_per_dim`` values evenly over the bounds (5 for one action dimension, 3 per dimension
   for more): odd, so the middle action is in the set, and both bounds, so the extreme manoeuvres are; the build
   cost grows linearly with A. Set only through a ``num_actions`` field of a one-dimensional action; otherwise the
   system's own action set is kept (and the report says so).
2. **Spread.** From P probe starts (the region's centre and seeded uniform draws), M action sequences (every
   constant action, then uniform random ones) are rolled out for T steps; a dimension's *spread* is the widest
   range, over the probes and steps, of the states' deviation from the middle action's trajectory (angles
   wrapped, at most a turn). Its *one-step resolution* is the spread after one step over (actions per dimension -
   1): at that cell neighbouring actions land in neighbouring cells.
3. **Cells.** Cell sizes proportional to the spread (every dimension gets the same number of cells across its
   reachable range), scaled by the smallest common factor whose level sets (the builder's own: cells reached from
   the centres of the previous level under every action, counted exactly from every probe start) total at most
   ``cell_budget`` cells in the largest table, and never finer than the one-step resolution (finer cells add no
   distinction any action makes). Angles are rounded to ``2 pi / K``. The max-flow build's cost grows with cells x
   actions, so the cell budget is its time and memory budget.
4. **Start grid.** A table depends on its start through the start's cell only, so members are at least a cell
   apart. The *shift* of start dimension j is how far (in cells, the worst state dimension, the 90th percentile
   over the probes' sequences) the trajectories move when the start moves by one unit of j, measured by moving
   every probe start by one cell of j. Spacing sigma_j is chosen so that a start half a spacing from its member
   sees level sets at most ``shift_cells`` cells away (shared equally by the start dimensions: there the table's
   nearest-cell fallback still answers); when that needs more than ``member_budget`` members, the allowed shift
   grows until the set fits, and the report says how many cells a start between members is off (the table set
   then misses there; the start-conditioned MLP of :mod:`training.auto` interpolates between members).

:func:`build_auto_set` builds the chosen set into ``<out>/<name>-h<T>-<digest>/`` (the digest of the choices: a
rerun reuses it), in parallel with ``workers``. The command ``python -m training.auto`` runs both and distils.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import re
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from cuniform_torch.common.checks import check_positive_int
from cuniform_torch.grid.cells import CellKeys, Grid
from cuniform_torch.policies.start_mlp import start_dims_of
from cuniform_torch.systems import _REGISTRY, System, check_system, register_system, system_to_json
from precompute.flow.builder import BuildConfig
from precompute.one_table import TableJob, build_table_file
from precompute.table_set import MAX_SET_MEMBERS, ensure_table_set

__all__ = ["AutoConfig", "Region", "Choice", "parse_region", "choose", "build_auto_set", "format_choice",
           "level_sizes"]

_ITEM = re.compile(r"^(\d+)=([^:]+):([^:]+)$")
_TWO_PI = 2.0 * math.pi


@dataclass(frozen=True)
class AutoConfig:
    """The chooser's budgets and sampling (every field is a flag of ``python -m training.auto``)."""

    horizon: int = 15
    """steps T of every table"""
    cell_budget: int = 3000
    """the most cells (all levels) of one table, at the largest probe start: the max-flow build's time and memory
    grow with cells x actions (a 3000-cell pendulum table builds in about 0.3 s)"""
    member_budget: int = 64
    """the most tables in the set"""
    shift_cells: float = 1.0
    """the level-set shift (cells) allowed between a start and its nearest member before the member budget binds"""
    actions_per_dim: int | None = None
    """actions per action dimension (None: 5 for one dimension, 3 per dimension for more)"""
    probes: int = 16
    """probe starts of the spread and shift measurements (the region's centre, then seeded draws)"""
    sequences: int = 256
    """random action sequences per probe start (on top of one per constant action)"""
    seed: int = 0
    """seed of the probe starts and sequences"""

    def __post_init__(self) -> None:
        for name in ("horizon", "cell_budget", "member_budget", "probes", "sequences"):
            check_positive_int(name, getattr(self, name), integral=False)
        if self.actions_per_dim is not None and (not isinstance(self.actions_per_dim, int) or self.actions_per_dim < 1):
            raise ValueError(f"actions_per_dim must be a positive integer or None, got {self.actions_per_dim!r}")
        if not (math.isfinite(self.shift_cells) and self.shift_cells > 0):
            raise ValueError(f"shift_cells must be a positive number of cells, got {self.shift_cells!r}")
        if self.member_budget > MAX_SET_MEMBERS:
            raise ValueError(f"member_budget must be at most {MAX_SET_MEMBERS}, got {self.member_budget}")


@dataclass(frozen=True)
class Region:
    """A box of starts: ``lo [k]`` and ``hi [k]`` over the state dimensions ``dims [k]`` (the others are 0)."""

    dims: tuple[int, ...]
    lo: tuple[float, ...]
    hi: tuple[float, ...]

    def width(self, j: int) -> float:
        return self.hi[j] - self.lo[j]


def parse_region(spec: str | dict[int, tuple[float, float]], system: System) -> Region:
    """``"DIM=LO:HI ..."`` (or ``{dim: (lo, hi)}``) -> a :class:`Region` over ``system``'s start dimensions; a
    clear ValueError naming the bad item. An angle's range may span the whole turn (``0=-3.14159:3.14159``)."""
    if isinstance(spec, str):
        items: dict[int, tuple[float, float]] = {}
        for word in spec.split():
            m = _ITEM.match(word)
            if m is None:
                raise ValueError(f"--starts: {word!r} is not DIM=LO:HI (e.g. --starts '0=-3.14159:3.14159 1=-8:8')")
            try:
                lo, hi = float(m[2]), float(m[3])
            except ValueError:
                raise ValueError(f"--starts: {word!r}: LO and HI must be numbers") from None
            if int(m[1]) in items:
                raise ValueError(f"--starts: dimension {m[1]} is given twice")
            items[int(m[1])] = (lo, hi)
    else:
        items = {int(k): (float(v[0]), float(v[1])) for k, v in dict(spec).items()}
    if not items:
        raise ValueError("--starts names no dimension; e.g. --starts '0=-3.14159:3.14159 1=-8:8'")
    allowed = start_dims_of(system)
    for dim, (lo, hi) in items.items():
        if dim not in allowed:
            raise ValueError(f"--starts: dimension {dim} is not a start dimension of {system.name} (those are "
                             f"{allowed}; an SE(2)-invariant system's x, y, theta need no starts)")
        if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
            raise ValueError(f"--starts: dimension {dim} needs finite LO <= HI, got {lo}:{hi}")
        if system.periodic[dim] and (lo < -math.pi - 1e-6 or hi > math.pi + 1e-6):
            raise ValueError(f"--starts: dimension {dim} is an angle: give a range within [-pi, pi], got {lo}:{hi}")
    dims = tuple(sorted(items))
    return Region(dims, tuple(items[k][0] for k in dims), tuple(items[k][1] for k in dims))


@dataclass
class Choice:
    """What :func:`choose` chose (module docstring) and why."""

    system: System
    """the user's system with the chosen ``cell_size`` (and ``num_actions``)"""
    horizon: int
    starts: np.ndarray
    """``[S, d]`` float64 members' starts"""
    region: Region
    spread: list[float]
    """``[d]`` widest deviation range over the probes and steps"""
    resolution: list[float]
    """``[d]`` one-step resolution (0: the action does not reach the dimension in one step)"""
    shift: list[float]
    """``[k]`` cells the trajectories move per unit of each start dimension"""
    counts: list[int]
    """``[k]`` members per start dimension"""
    predicted_shift: float
    """cells between the level sets of a start half a spacing from its member and the member's"""
    level_sizes: list[int]
    """the largest probe table's level sizes under the chosen grid"""
    reasons: list[str] = field(default_factory=list)
    seconds: float = 0.0

    @property
    def digest(self) -> str:
        """12 hex digits of the choices (system JSON with the chosen parameters, horizon, starts): the cache key."""
        spec = {"system": system_to_json(self.system, self.horizon), "starts": np.round(self.starts, 12).tolist()}
        return hashlib.sha256(json.dumps(spec, sort_keys=True).encode()).hexdigest()[:12]

    def to_dict(self) -> dict[str, Any]:
        return {"system": self.system.name, "params": json.loads(json.dumps(self.system.params(), default=list)),
                "horizon": self.horizon, "cell_size": list(self.system.cell_size),
                "actions": self.system.action_set(dtype=torch.float64).tolist(), "members": len(self.starts),
                "counts": self.counts, "spread": self.spread, "resolution": self.resolution, "shift": self.shift,
                "predicted_shift_cells": self.predicted_shift, "level_sizes": self.level_sizes,
                "reasons": self.reasons, "digest": self.digest, "seconds": self.seconds}


def _check_choosable(system: System) -> None:
    """ValueError naming what keeps the chooser from setting the grid of ``system``."""
    check_system(system)
    if not dataclasses.is_dataclass(system) or isinstance(system, type):
        raise ValueError(f"system {system.name!r}: the chooser sets its cell sizes, so it must be a dataclass "
                         f"instance with a cell_size field (got {type(system).__name__})")
    names = {f.name for f in dataclasses.fields(system) if f.init}
    if "cell_size" not in names:
        raise ValueError(f"system {system.name!r}: the chooser sets its cell sizes: give its dataclass a cell_size "
                         f"field (its fields: {', '.join(sorted(names))})")


def _with(system: System, **changes: Any) -> System:
    """``system`` with ``changes``, checked to survive its ``params()`` (tables rebuild a system from them)."""
    new = dataclasses.replace(system, **changes)  # type: ignore[type-var]
    check_system(new)
    params = new.params()
    for key, value in changes.items():
        stored = params.get(key)
        same = (list(np.atleast_1d(stored)) == list(np.atleast_1d(value))) if stored is not None else False
        if not same:
            raise ValueError(f"system {system.name!r}: params() must return its {key} ({value!r}) so that a table "
                             f"rebuilds the chosen system; it returned {stored!r} (return dataclasses.asdict(self))")
    return new


def _probe_starts(region: Region, d: int, count: int, gen: torch.Generator) -> Tensor:
    """``[P, d]`` float64: the region's centre, then seeded uniform draws in it (other dimensions 0)."""
    lo = torch.tensor(region.lo, dtype=torch.float64)
    hi = torch.tensor(region.hi, dtype=torch.float64)
    draws = lo + (hi - lo) * torch.rand((count, len(region.dims)), dtype=torch.float64, generator=gen)
    draws[0] = (lo + hi) / 2
    out = torch.zeros((count, d), dtype=torch.float64)
    out[:, list(region.dims)] = draws
    return out


def _sequences(A: int, T: int, M: int, gen: torch.Generator) -> Tensor:
    """``[A + M, T]`` action indices: each constant action, then M uniform random sequences."""
    const = torch.arange(A).unsqueeze(1).expand(A, T)
    return torch.cat((const, torch.randint(0, A, (M, T), generator=gen)))


def _roll(system: System, starts: Tensor, actions: Tensor, seqs: Tensor) -> Tensor:
    """States ``[P, M, T+1, d]`` float64 of every sequence ``seqs [M, T]`` from every start ``[P, d]``."""
    P, d = starts.shape
    M, T = seqs.shape
    x = starts.unsqueeze(1).expand(P, M, d).reshape(-1, d)
    out = [x]
    for t in range(T):
        u = actions[seqs[:, t]].repeat(P, 1)  # [P*M, q]
        x = system.step(x, u)
        out.append(x)
    return torch.stack(out, dim=1).reshape(P, M, T + 1, d)


def _wrapped(delta: Tensor, periodic: Sequence[bool]) -> Tensor:
    per = torch.tensor(list(periodic), dtype=torch.bool)
    return torch.where(per, torch.remainder(delta + math.pi, _TWO_PI) - math.pi, delta)


def level_sizes(system: System, start: Tensor, horizon: int, limit: int | None = None) -> list[int]:
    """The builder's level sizes from ``start [d]`` (cells reached from the previous level's centres under every
    action, ties as the builder's symmetric rule); stops once their total passes ``limit`` (the last size then
    makes the total exceed it)."""
    grid = Grid.of(system)
    actions = system.action_set(dtype=torch.float64)  # [A, q]
    A = actions.shape[0]
    cells = grid.cells(start.view(1, -1))  # [1, d]
    sizes = [1]
    for _ in range(horizon):
        centres = grid.centers(cells)  # [n, d]
        n = centres.shape[0]
        x = centres.repeat_interleave(A, dim=0)
        reached = grid.cells_from(cells.repeat_interleave(A, dim=0), system.step(x, actions.repeat(n, 1)))
        keys = CellKeys.covering(reached)
        cells = keys.unpack(torch.unique(keys.pack(reached)))
        sizes.append(int(cells.shape[0]))
        if limit is not None and sum(sizes) > limit:
            break
    return sizes


def _snap(size: float, periodic: bool) -> float:
    """An angle cell as ``2 pi / K`` (K >= 1 an integer); other sizes as they are."""
    return _TWO_PI / max(1, round(_TWO_PI / size)) if periodic else size


def choose(system: System, region: Region | str | dict, config: AutoConfig = AutoConfig()) -> Choice:
    """Choose the actions, cells and start grid of ``system`` over ``region`` (module docstring)."""
    t_start = time.perf_counter()
    _check_choosable(system)
    if not isinstance(region, Region):
        region = parse_region(region, system)
    gen = torch.Generator().manual_seed(config.seed)
    T, d, periodic = config.horizon, len(system.periodic), tuple(system.periodic)
    reasons: list[str] = []

    # 1. actions
    q = system.action_set(dtype=torch.float64).shape[1]
    per_dim = config.actions_per_dim or (5 if q == 1 else 3)
    fields = {f.name for f in dataclasses.fields(system) if f.init}  # type: ignore[arg-type]
    if "num_actions" in fields and q == 1:
        system = _with(system, num_actions=per_dim)
        acts = system.action_set(dtype=torch.float64)
        reasons.append(f"actions: {per_dim} values evenly in [{float(acts.min()):.4g}, {float(acts.max()):.4g}] "
                       "(odd: the middle action is in the set; both bounds: the extreme manoeuvres are; the build's "
                       "cost grows with the action count)")
    else:
        acts = system.action_set(dtype=torch.float64)
        per_dim = max(2, round(acts.shape[0] ** (1 / q))) if acts.shape[0] > 1 else 1
        reasons.append(f"actions: the system's own {acts.shape[0]} (no num_actions field of a one-dimensional "
                       "action to set)")
    A = acts.shape[0]

    # 2. spread
    probes = _probe_starts(region, d, config.probes, gen)  # [P, d]
    seqs = _sequences(A, T, config.sequences, gen)  # [A + M, T]
    states = _roll(system, probes, acts, seqs)  # [P, M, T+1, d]
    ref = states[:, A // 2 : A // 2 + 1]  # the middle constant action's trajectory [P, 1, T+1, d]
    dev = _wrapped(states - ref, periodic)
    width = (dev.amax(dim=1) - dev.amin(dim=1))  # [P, T+1, d]
    spread = width.amax(dim=(0, 1))  # [d]
    spread = torch.where(torch.tensor(periodic), spread.clamp(max=_TWO_PI), spread)
    resolution = width[:, 1].median(dim=0).values / max(per_dim - 1, 1)  # [d]
    own = torch.tensor(system.cell_size, dtype=torch.float64)
    flat = spread <= 1e-12 * (1 + spread.max())
    if bool(flat.any()):
        reasons.append(f"dimension(s) {flat.nonzero().flatten().tolist()}: no action moves them within the horizon; "
                       "their cells stay the system's own")

    # 3. cells: the smallest common factor s whose level sets fit the budget
    floor = torch.where(resolution > 0, resolution, torch.zeros_like(resolution))

    def cells_at(s: float) -> tuple[float, ...]:
        raw = torch.where(flat, own, torch.maximum(s * spread, floor))
        return tuple(_snap(float(c), p) for c, p in zip(raw, periodic))

    def total(s: float) -> tuple[int, list[int]]:
        trial = dataclasses.replace(system, cell_size=cells_at(s))  # type: ignore[type-var]
        worst: list[int] = []
        for p in probes:
            sizes = level_sizes(trial, p, T, limit=config.cell_budget)
            if sum(sizes) > sum(worst):
                worst = sizes
            if sum(worst) > config.cell_budget:
                break
        return sum(worst), worst

    finest = float((floor / spread.clamp_min(1e-300)).masked_fill(flat, 0).max())  # below it the floors bind
    lo, hi = max(finest, 1e-6), 1.0
    n_lo, sizes_lo = total(lo)
    if n_lo <= config.cell_budget:
        s, sizes = lo, sizes_lo
        reasons.append(f"cells: the one-step resolution (neighbouring actions land in neighbouring cells after one "
                       f"step; finer cells add no distinction); its largest probe table has {n_lo} cells, within "
                       f"the budget of {config.cell_budget}")
    else:
        n_hi, sizes = total(hi)
        while n_hi > config.cell_budget and hi < 1e6:  # a budget below even one cell per spread
            hi *= 2
            n_hi, sizes = total(hi)
        for _ in range(24):  # bisection on log s
            mid = math.sqrt(lo * hi)
            n_mid, sizes_mid = total(mid)
            if n_mid <= config.cell_budget:
                hi, sizes = mid, sizes_mid
            else:
                lo = mid
            if hi / lo < 1.02:
                break
        s = hi
        reasons.append(f"cells: {1 / s:.3g} cells across each dimension's spread, the finest whose largest probe "
                       f"table ({sum(sizes)} cells over {T + 1} levels) fits the budget of {config.cell_budget} cells")
    system = _with(system, cell_size=cells_at(s))
    cell = torch.tensor(system.cell_size, dtype=torch.float64)

    # 4. start grid
    k = len(region.dims)
    shift = []
    for dim in region.dims:
        h = float(cell[dim])
        moved = probes.clone()
        moved[:, dim] += h
        moved = Grid.of(system).wrap(moved)
        delta = _wrapped(_roll(system, moved, acts, seqs) - states, periodic).abs() / cell  # [P, M, T+1, d]
        per_seq = delta.amax(dim=(2, 3)).flatten()  # [P*M] worst step and dimension of each trajectory
        shift.append(float(torch.quantile(per_seq, 0.9)) / h)  # cells per unit of the start dimension

    def grid_for(allowed: float) -> tuple[list[int], list[np.ndarray]]:
        counts, axes = [], []
        for j, dim in enumerate(region.dims):
            w = region.width(j)
            full = periodic[dim] and w >= _TWO_PI - 1e-3
            sigma = 2 * allowed / (k * shift[j]) if shift[j] > 0 else math.inf
            sigma = max(sigma, float(cell[dim]))  # one start cell holds one table
            if full:
                n = max(1, math.ceil(_TWO_PI / sigma))
                axes.append(-math.pi + _TWO_PI * np.arange(n) / n)
            else:
                n = 1 if w == 0 else max(2, math.ceil(w / sigma) + 1) if sigma < w else 1
                axes.append(np.linspace(region.lo[j], region.hi[j], n) if n > 1
                            else np.array([(region.lo[j] + region.hi[j]) / 2]))
            counts.append(len(axes[-1]))
        return counts, axes

    allowed = config.shift_cells
    counts, axes = grid_for(allowed)
    while math.prod(counts) > config.member_budget:
        allowed *= 1.05
        counts, axes = grid_for(allowed)
    spacing = [(2 * math.pi / c if periodic[dim] and region.width(j) >= _TWO_PI - 1e-3 else
                (region.width(j) / (c - 1) if c > 1 else region.width(j)))  # one member: the box's edges
               for j, (dim, c) in enumerate(zip(region.dims, counts))]
    predicted = sum(sp / 2 * sh for sp, sh in zip(spacing, shift))
    mesh = np.stack([a.ravel() for a in np.meshgrid(*axes, indexing="ij")], axis=1)  # [S, k]
    starts = np.zeros((len(mesh), d))
    starts[:, list(region.dims)] = mesh
    starts = np.round(starts, 12)
    dims_txt = ", ".join(f"dim {dim}: {c} ({sp:.4g} apart, {sh:.3g} cells of shift per unit)"
                         for dim, c, sp, sh in zip(region.dims, counts, spacing, shift))
    if allowed > config.shift_cells * 1.0001:
        reasons.append(f"starts: {len(starts)} members ({dims_txt}); the member budget of {config.member_budget} "
                       f"binds: a start half a spacing from its member sees level sets about {predicted:.2g} cells "
                       f"off (more than the nearest-cell fallback's 1): the table set misses there, the "
                       f"start-conditioned MLP interpolates")
    else:
        reasons.append(f"starts: {len(starts)} members ({dims_txt}): a start half a spacing from its member sees "
                       f"level sets at most about {predicted:.2g} cells off, within the nearest-cell fallback")
    return Choice(system, T, starts, region, spread.tolist(), resolution.tolist(), shift, counts, predicted,
                  sizes, reasons, time.perf_counter() - t_start)


def format_choice(choice: Choice) -> str:
    """What was chosen and why, as text."""
    sys_ = choice.system
    acts = sys_.action_set(dtype=torch.float64)
    lines = [f"C-Uniform for {sys_.name}, horizon {choice.horizon} (chosen in {choice.seconds:.1f} s; digest "
             f"{choice.digest})",
             "  cell_size " + ", ".join(f"{c:.5g}" for c in sys_.cell_size) + "  (spread "
             + ", ".join(f"{s:.4g}" for s in choice.spread) + "; one-step resolution "
             + ", ".join(f"{r:.3g}" for r in choice.resolution) + ")",
             f"  actions [{acts.shape[0]}, {acts.shape[1]}]: "
             + ", ".join("(" + ", ".join(f"{v:.4g}" for v in row) + ")" for row in acts.tolist()),
             f"  largest table's level sizes {choice.level_sizes} ({sum(choice.level_sizes)} cells)",
             f"  starts: {len(choice.starts)} members, " + " x ".join(str(c) for c in choice.counts)
             + f" over dimensions {list(choice.region.dims)}"]
    lines += [f"  why {r}" for r in choice.reasons]
    return "\n".join(lines)


def register_chosen(system: System) -> None:
    """Make sure the chosen system's name rebuilds it (its tables are read back through the registry)."""
    if system.name not in _REGISTRY:
        register_system(system.name, type(system))


def build_auto_set(choice: Choice, out: Path, workers: int = 1, quiet: bool = False) -> Path:
    """Build (or reuse) the chosen set into ``out/<name>-h<T>-<digest>`` (a single table file ``.npz`` when the
    region is one start); returns its path."""
    register_chosen(choice.system)
    folder = Path(out) / f"{choice.system.name}-h{choice.horizon}-{choice.digest}"
    template = TableJob(system=choice.system, out=folder / "start_0000.npz", build=BuildConfig(horizon=choice.horizon),
                        report=False, quiet=quiet)
    if len(choice.starts) == 1:
        path = folder.with_suffix(".npz")
        if not path.exists():
            build_table_file(template.from_start(tuple(choice.starts[0]), path))
        return path
    return ensure_table_set(template, choice.starts, folder, workers=workers)
