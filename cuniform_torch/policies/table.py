"""Table policy: p(u | cell, t) looked up from a C-Uniform table by packed keys, on any device.

Shapes: N states, d state dimensions, A actions, q action dimensions, C table cells, H halo cells.

:class:`TablePolicy` is a thin class over two parts, each in its own module:

* the **index** (:mod:`~cuniform_torch.tables.lookup`): a frozen :class:`~cuniform_torch.tables.lookup.TableIndex` built once
  from the table: key constants per dimension, the (level, cell) entries with their halo
  (:mod:`~cuniform_torch.tables.halo`), a dense or hash index of their keys (``lookup=``, :class:`Lookup`), per-entry
  probability rows, fallback codes and alias tables (:mod:`~cuniform_torch.tables.alias`);
* a **kernel** that reads it (``kernel=``, :class:`Kernel`): :mod:`~cuniform_torch.tables.torch_kernel` (pure tensor ops,
  any device), :mod:`~cuniform_torch.tables.cpu_kernels` (the same arithmetic as one compiled CPU loop) or, on a
  CUDA device, :mod:`~cuniform_torch.tables.gpu_kernels` (a Dubins table's whole rollout as one Triton kernel).

The policy checks its input, draws the uniforms, runs the kernel and keeps the counters.

Fallback for a state whose cell is not in L_t (``fallback=``):

* ``"nearest"`` (default): the action row of the nearest cell of L_t when the state's cell is within one cell
  of L_t (counted in ``nearest_hits``), else uniform over the actions (counted in ``misses``);
* ``"uniform"``: uniform over the actions (counted in ``misses``).

Tables are built from the origin (:attr:`TablePolicy.build_start`, the zero state). For an SE(2)-invariant
system (``system.se2_invariant``), states given to ``action_probs`` are in the frame of the start pose;
:func:`~cuniform_torch.sampling.rollout.rollout` does that change of frame, so one table serves every start pose
(``start_relative`` is True). For any other system a table is valid from its build start only: a rollout from
another start (or, SE(2)-relative, with other speeds or steering angles than the build start's) warns once per
policy (:class:`~cuniform_torch.sampling.rollout.StartMismatchWarning`), with that rollout's miss rate.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor

from cuniform_torch.common.options import Option, option_label
from cuniform_torch.grid.cells import Grid
from cuniform_torch.sampling.fallback_counts import CountsFallbacks, FallbackCounts
from cuniform_torch.sampling.rollout import StartWatch, check_generator, check_states
from cuniform_torch.sampling.start_watch import WatchesStart
from cuniform_torch.systems import System
from cuniform_torch.systems.models import Dubins
from cuniform_torch.tables import cpu_kernels, gpu_kernels
from cuniform_torch.tables.file import Table, read_table
from cuniform_torch.tables.lookup import Lookup, TableIndex, build_index
from cuniform_torch.tables.torch_kernel import lookup_and_draw, lookup_entries

__all__ = ["Fallback", "Kernel", "Lookup", "TablePolicy", "UniformPolicy", "load_table"]



@option_label('fallback')
class Fallback(Option):
    """What a :class:`TablePolicy` does for a state outside the level set."""

    NEAREST = "nearest"
    UNIFORM = "uniform"


@option_label('kernel')
class Kernel(Option):
    """What runs :meth:`TablePolicy.sample`'s per-step lookup and draw."""

    AUTO = "auto"
    """numba where it applies (see :data:`NUMBA`); on a CUDA device, Triton's fused rollout where it applies (see
    :data:`TRITON`); else torch"""
    TORCH = "torch"
    """about 24 small tensor ops per step, on any device (``compile=True`` wraps them in ``torch.compile``)"""
    NUMBA = "numba"
    """one compiled CPU loop (:mod:`~cuniform_torch.tables.cpu_kernels`): float32 on a CPU, dense or int32-hash lookup"""
    TRITON = "triton"
    """a Dubins table's whole rollout as one GPU kernel (:mod:`~cuniform_torch.tables.gpu_kernels`): float32 on a
    CUDA device, dense lookup; single lookups (``sample``, ``action_probs``) run the torch ops"""


class TablePolicy(WatchesStart, CountsFallbacks):
    """The Policy interface over a table: ``actions [A, q]`` and ``action_probs(x [N, d], t) -> [N, A]``.

    Also an :class:`~cuniform_torch.sampling.rollout.ActionSampler`: ``sample(x, t, generator)`` draws the actions with
    Walker's alias method, one uniform per state (what :func:`~cuniform_torch.sampling.rollout.rollout` uses).
    ``lookup`` picks how cells are found (:class:`Lookup`): a dense index over the table's key box where that is
    small (the Dubins tables: 5 MB at horizon 10, 17 MB at 15), else a static hash; both answer exactly the same.
    ``compile=True`` wraps the per-step lookup-and-sample kernel (about 17 small tensor ops) in
    ``torch.compile``: a few seconds of compilation, meant for GPUs, where it saves the launches of those small
    kernels (not measured here: no GPU). On a CPU the compiled kernel is a scalar loop (its gathers keep inductor
    from vectorizing it) and runs slower than eager: 8.1 against 6.4 ms for a table rollout at N = 10000,
    T = 15 on our 2-core machine.
    """

    def __init__(
        self,
        table: Table,
        device: torch.device | str = "cpu",
        dtype: torch.dtype = torch.float32,
        fallback: str | Fallback = Fallback.NEAREST,
        compile: bool = False,
        lookup: str | Lookup = Lookup.AUTO,
        kernel: str | Kernel = Kernel.AUTO,
    ):
        self.table = table
        self.system: System = table.make_system()
        self.grid = Grid.of(self.system)
        self._dim = self.grid.dim
        self.horizon = table.horizon
        self.fallback = Fallback.parse(fallback)
        self.device = torch.device(device)
        self.dtype = dtype
        self.index: TableIndex = build_index(table, self.grid, nearest=self.fallback is Fallback.NEAREST,
                                             lookup=Lookup.parse(lookup), dtype=dtype, device=self.device)
        self.lookup = self.index.lookup
        self.actions = self.index.actions  # [A, q]
        self.probs = torch.from_numpy(table.action_probs).to(device=self.device, dtype=dtype)  # [C, A]
        self.entry_row = self.index.entry_row  # [C + H] table row of each entry
        self.num_cells = self.index.num_cells
        self.num_halo = self.index.num_entries - self.num_cells
        build_start = None if getattr(table, "start", None) is None else torch.from_numpy(table.start)
        self.counts = FallbackCounts(self.device)
        """the lookups' fallback counts (:class:`~cuniform_torch.sampling.fallback_counts.FallbackCounts`)"""
        self._start_watch = StartWatch(f"table policy ({self.system.name})", self.system, build_start, self.counts)
        asked = Kernel.parse(kernel)
        self.kernel = self._choose_kernel(asked, compile)
        # the numba kernel compiles (or loads from numba's disk cache) now, not in the first control cycle
        self._numba = cpu_kernels.NumbaKernel(self.index) if self.kernel is Kernel.NUMBA else None
        self._triton = self._make_triton(asked) if self.kernel is Kernel.TRITON else None
        self._torch_step = torch.compile(lookup_and_draw, dynamic=False) if compile else lookup_and_draw
        self.compiled = True
        """roll out a Dubins system in one compiled call (:meth:`fused_rollout`) when the numba kernel runs"""
        # compiled, the level goes in as a 0-d tensor: one graph serves every level
        self._levels = [torch.tensor(t, device=self.device) if compile else t for t in range(self.horizon + 1)]

    def _choose_kernel(self, kernel: Kernel, compile: bool) -> Kernel:
        """The kernel :meth:`sample` runs: numba when asked for (an error naming what rules it out) or, for
        ``auto``, when every condition holds; else torch."""
        if kernel is Kernel.TORCH:
            return kernel
        asked_torch = ["compile=True asks for the torch kernel"] if compile else []
        unmet = cpu_kernels.unmet(self.index) + asked_torch
        unmet_gpu = gpu_kernels.unmet(self.index) + asked_torch
        if kernel is Kernel.NUMBA and unmet:
            raise ValueError(f"kernel='numba' cannot be used: {'; '.join(unmet)}")
        if kernel is Kernel.TRITON and unmet_gpu:
            raise ValueError(f"kernel='triton' cannot be used: {'; '.join(unmet_gpu)}")
        if kernel is not Kernel.AUTO:
            return kernel
        if not unmet:
            return Kernel.NUMBA
        return Kernel.TRITON if self.device.type == "cuda" and not unmet_gpu else Kernel.TORCH

    def _make_triton(self, asked: Kernel) -> gpu_kernels.TritonRollout | None:
        """The fused GPU rollout (compiled now). Where Triton fails to compile it (a toolchain that does not match
        the driver, say), ``kernel='triton'`` is a RuntimeError and ``auto`` warns once and runs the torch ops."""
        try:
            return gpu_kernels.TritonRollout(self.index)
        except Exception as exc:  # noqa: BLE001 - any compiler failure: the torch ops compute the same
            if asked is Kernel.TRITON:
                raise RuntimeError(f"kernel='triton': the Triton rollout did not compile ({type(exc).__name__}: "
                                   f"{exc}); use kernel='torch'") from exc
            warnings.warn(f"the Triton table rollout did not compile ({type(exc).__name__}: {exc}); the table "
                          f"policy runs the torch ops instead (kernel='torch' says so without trying)",
                          RuntimeWarning, stacklevel=3)
            self.kernel = Kernel.TORCH
            return None

    @property
    def start_relative(self) -> bool:
        """True only for an SE(2)-invariant system: then states are relative to the start pose (the table is
        built at the origin); else they are used as they are, and the table holds from :attr:`build_start`."""
        return bool(self.system.se2_invariant)

    @property
    def num_actions(self) -> int:
        return int(self.actions.shape[0])

    def level_size(self, t: int) -> int:
        return int(self.table.level_offsets[t + 1] - self.table.level_offsets[t])

    def _check(self, x: Tensor, t: int) -> None:
        if isinstance(t, bool) or not isinstance(t, int) or not 0 <= t <= self.horizon:
            raise ValueError(f"level t={t!r} is outside the table's levels 0..{self.horizon} (an integer)")
        if (type(x) is Tensor and x.dtype == self.dtype and x.ndim == 2 and x.shape[1] == self._dim
                and x.device == self.device):
            return  # the common case, checked in well under a microsecond; else the checks that say what is wrong
        check_states(x, self.grid.dim, self.device)
        if x.dtype != self.dtype:
            raise ValueError(f"states are {x.dtype} but the policy is {self.dtype}")

    def rows(self, x: Tensor, t: int) -> Tensor:
        """Table row of each state's cell in level ``t``: ``x [N, d]`` -> ``[N]`` int64 (-1: not in L_t)."""
        self._check(x, t)
        entry = lookup_entries(self.index, x, t).long()  # [N]
        return torch.where(entry < self.num_cells, entry, -1)  # entries below C are table rows

    def action_probs(self, x: Tensor, t: int) -> Tensor:
        """p(u | cell of x, t): ``x [N, d]`` -> ``[N, A]``, with the fallback for states outside L_t."""
        self._check(x, t)
        entry = lookup_entries(self.index, x, t)  # [N]
        self.counts.add(x.shape[0], self.index.entry_code.index_select(0, entry).sum())
        return self.index.entry_probs.index_select(0, entry)  # [N, A]; entry E: the uniform row

    def sample(self, x: Tensor, t: int, generator: torch.Generator | None = None) -> Tensor:
        """Draw one action per state from its row (alias method, one uniform each): ``x [N, d]`` -> ``[N, q]``."""
        self._check(x, t)
        if generator is not None and not isinstance(generator, torch.Generator):
            check_generator(generator, self.device)  # the clear TypeError
        r = torch.empty(x.shape[0], device=self.device, dtype=self.dtype).uniform_(0, self.num_actions,
                                                                                    generator=generator)  # [N]
        return self._draw_scaled(x, t, r)

    def draw(self, x: Tensor, t: int, r: Tensor) -> Tensor:
        """:meth:`sample` with the uniforms given: ``x [N, d]``, ``r [N]`` in ``[0, 1)`` (the policy's dtype and
        device) -> ``[N, q]``. ``sample`` draws ``r`` from its generator and does this, so the two agree."""
        self._check(x, t)
        return self._draw_scaled(x, t, r * self.num_actions)

    def fused_rollout(self, system: System, x0: Tensor, num_samples: int, horizon: int,
                      generator: torch.Generator | None,
                      uniforms: Tensor | None = None) -> tuple[Tensor, Tensor] | None:
        """The rollout's own loop, when it has one (:func:`~cuniform_torch.sampling.rollout.rollout` asks): with the
        numba kernel (a CPU, float32) or the Triton kernel (a CUDA device, float32) on a
        :class:`~cuniform_torch.systems.models.Dubins` system (its own speed and time step; states
        ``(x, y, heading)`` only, so every start's rollouts in its own frame start at the origin), the start-frame
        states ``[T+1, 3, N]`` (time-major) and actions ``[N, T, q]`` of one compiled call: the step-by-step
        path's lookups and draws, to float rounding of the step. ``uniforms [T, N]`` in ``[0, 1)`` are the draws
        (else ``torch.rand((T, N))`` from ``generator``: the step-by-step path's stream). Else None.
        ``compiled = False`` turns it off."""
        fused = self._numba or self._triton
        if not (self.compiled and fused is not None and type(system) is Dubins and self._dim == 3
                and (generator is None or generator.device.type == self.device.type)):
            return None
        if uniforms is None:
            uniforms = torch.rand((horizon, num_samples), generator=generator, dtype=torch.float32,
                                  device=self.device)
        if self._numba is not None:
            states, actions, total = self._numba.dubins_rollout(uniforms, system.dt, system.speed)
            self.counts.add(num_samples * horizon, total)
        else:
            assert self._triton is not None
            states, actions, code = self._triton(uniforms, system.dt, system.speed)
            self.counts.add(num_samples * horizon, code)
        return states, actions

    def _draw_scaled(self, x: Tensor, t: int, r: Tensor) -> Tensor:
        """The alias draw of ``x [N, d]`` with ``r [N]`` in ``[0, A)``."""
        n = x.shape[0]
        if self._numba is not None:
            u, total = self._numba.draw(x, t, r)  # [N, q], a host int
            self.counts.add(n, total)
            return u
        u, code = self._torch_step(self.index, x, self._levels[t], r)
        self.counts.add(n, code.sum())
        return u  # [N, q]


def load_table(
    path: str | os.PathLike,
    device: torch.device | str = "cpu",
    dtype: torch.dtype = torch.float32,
    fallback: str | Fallback = Fallback.NEAREST,
    compile: bool = False,
    lookup: str | Lookup = Lookup.AUTO,
    kernel: str | Kernel = Kernel.AUTO,
    trust_factory: str | Callable[..., Any] | None = None,
) -> TablePolicy:
    """Read and validate a table file (not its flow graph, which a policy does not use), and return its
    :class:`TablePolicy` on ``device``. The table's system comes from the registry or ``trust_factory``
    (see :func:`~cuniform_torch.systems.system_from_json`); nothing the file names is imported. (The package's
    ``cuniform_torch.load_table`` also reads a table-set folder: :func:`cuniform_torch.policies.table_set.load_table`.)"""
    table = read_table(path, graph=False, trust_factory=trust_factory)
    return TablePolicy(table, device=device, dtype=dtype, fallback=fallback,
                       compile=compile, lookup=lookup, kernel=kernel)


class UniformPolicy:
    """Uniform random discrete actions: ``action_probs`` is ``1/A`` everywhere (the paper's "uniform" baseline).

    Has the Policy interface, so it drives :func:`~cuniform_torch.sampling.rollout.rollout` and
    :class:`~cuniform_torch.controllers.mppi.CUniformMPPI` like a table does; ``horizon=None`` means any horizon. ``sample``
    draws as a table draws from its uniform row (one uniform ``r`` in ``[0, A)`` per state, action ``floor(r)``),
    so a rollout costs no more than a table's and consumes the generator alike.
    """

    start_relative = False

    def __init__(self, system: System, horizon: int | None = None, device: torch.device | str = "cpu",
                 dtype: torch.dtype = torch.float32):
        self.system = system
        self.horizon = horizon
        self.device = torch.device(device)
        self.dtype = dtype
        self.actions = system.action_set(dtype=dtype, device=self.device)  # [A, q]

    def action_probs(self, x: Tensor, t: int) -> Tensor:
        """``x [N, d]`` -> ``[N, A]`` all ``1/A``."""
        check_states(x, len(self.system.periodic), self.device)
        A = self.actions.shape[0]
        return torch.full((x.shape[0], A), 1.0 / A, dtype=self.dtype, device=self.device)

    def sample(self, x: Tensor, t: int, generator: torch.Generator | None = None) -> Tensor:
        """One uniformly drawn action per state: ``x [N, d]`` -> ``[N, q]`` in the dtype of ``x``."""
        check_states(x, len(self.system.periodic), self.device)
        if generator is not None and not isinstance(generator, torch.Generator):
            check_generator(generator, self.device)  # the clear TypeError
        A = self.actions.shape[0]
        r = torch.empty(x.shape[0], device=self.device, dtype=self.dtype).uniform_(0, A, generator=generator)  # [N]
        return self._pick(x, r)

    def draw(self, x: Tensor, t: int, r: Tensor) -> Tensor:
        """:meth:`sample` with the uniforms ``r [N]`` in ``[0, 1)`` given."""
        check_states(x, len(self.system.periodic), self.device)
        return self._pick(x, r * self.actions.shape[0])

    def _pick(self, x: Tensor, r: Tensor) -> Tensor:
        A = self.actions.shape[0]
        actions = self.actions if x.dtype == self.dtype else self.actions.to(x.dtype)  # [A, q]
        return actions.index_select(0, r.to(torch.int32).clamp_(max=A - 1))  # [N, q]
