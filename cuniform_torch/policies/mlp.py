"""The distilled policy: a small MLP pi(u | x, t) with the Policy interface, and the support it knows.

Shapes: N states, d state dimensions, F input features, A actions, q action dimensions, T horizon.

Input features of a state ``x`` at step ``t`` (documented scales, settled from the table at distillation):

* every non-periodic dimension i: ``x_i / scale_i`` (``scale_i`` = the largest |cell centre| of the table in
  that dimension, so features lie in about [-1, 1]);
* every angle dimension: ``cos x_i`` and ``sin x_i``;
* the time ``t / T``;
* with ``frequencies`` K > 0 (the config's), each of those features f also as ``sin(2^k pi f)``, ``cos(2^k pi f)``
  for k = 0..K-1 (all the sines, then all the cosines, feature-major): detail as fine as a cell is then a few
  hundred optimiser steps away rather than thousands.

For Dubins that is ``(x / sx, y / sy, cos theta, sin theta, t / T)`` (and with K = 6 their 60 sines and
cosines). The network is ``layers`` hidden layers of ``hidden`` units with SiLU activations, then a linear layer
to A logits; ``action_probs`` is their softmax.

Its checkpoint file (format ``cuniform-policy/1``) is :mod:`cuniform_torch.policies.checkpoint`'s.

Support and fallback (as :class:`~cuniform_torch.policies.table.TablePolicy`'s, ``fallback=``): a state at level ``t``
is *in the support* when its cell is one of level ``t``'s support cells; with ``"nearest"`` (default) a state
whose cell is within one cell of them still gets the network's answer (counted in ``nearest_hits``), and any
other state gets uniform probabilities (counted in ``misses``); with ``"uniform"`` every state outside the
support gets them. A checkpoint without ``support`` (older ones) gives the box of the table's cells instead:
each non-periodic dimension within ``feature_scale_i + cell_size_i / 2`` of 0 (``feature_scale`` is the
largest |cell centre|, over all levels), angles anywhere; "within one cell" is that box grown by one cell.
NaN or infinite states are always misses. Levels beyond the horizon are a ValueError, as for a table.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from cuniform_torch.grid.cells import Grid
from cuniform_torch.policies.mlp_ops import check_query, encode_features, state_features
from cuniform_torch.policies.table import Fallback
from cuniform_torch.sampling.fallback_counts import CountsFallbacks, FallbackCounts
from cuniform_torch.sampling.rollout import StartWatch, check_states
from cuniform_torch.sampling.start_watch import WatchesStart
from cuniform_torch.systems import MAX_ACTIONS, MAX_HORIZON, System
from cuniform_torch.tables.file import Table
from cuniform_torch.tables.lookup import MISS, NEAREST, Lookup, TableIndex, build_index
from cuniform_torch.tables.torch_kernel import lookup_entries

__all__ = ["MLPConfig", "MLPPolicy", "MLPSupport", "default_feature_scale", "MAX_HIDDEN", "MAX_LAYERS",
           "MAX_WEIGHTS", "MAX_STATE_DIM", "MAX_FREQUENCIES"]

# Limits of a config, checked when it is made (MLPConfig.__post_init__): before any network is built, so a
# checkpoint's config cannot make the reader allocate more than these describe (see docs/formats.md).
MAX_HIDDEN = 8192
"""the most hidden units per layer"""
MAX_LAYERS = 32
"""the most hidden layers"""
MAX_WEIGHTS = 1 << 26
"""the most weights and biases in all (``num_weights``; 67M, 256 MiB of float32)"""
MAX_STATE_DIM = 64
"""the most state dimensions (as a table file's)"""
MAX_FREQUENCIES = 12
"""the most octaves of the sin / cos feature encoding (``2^11 pi`` is still resolved by float32 on features
of about [-1, 1])"""


@dataclass
class MLPConfig:
    """Sizes and input features of an :class:`MLPPolicy` (stored in the checkpoint as a plain dict)."""

    state_dim: int
    num_actions: int
    horizon: int
    periodic: list[bool]
    feature_scale: list[float]
    """divisor of each non-periodic dimension (ignored on angle dimensions)"""
    hidden: int = 256
    layers: int = 3
    start_dims: list[int] = field(default_factory=list)
    """state dimensions of the start x0 the network also reads (:mod:`cuniform_torch.policies.start_mlp`); empty: pi(u | x, t)"""
    frequencies: int = 0
    """octaves K of the sin / cos encoding of the state and time features (module docstring); 0: the plain
    features (every checkpoint written before the encoding)"""

    def __post_init__(self) -> None:
        for name in ("state_dim", "num_actions", "horizon", "hidden", "layers"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"MLPConfig.{name} must be a positive integer, got {value!r}")
        if isinstance(self.frequencies, bool) or not isinstance(self.frequencies, int) \
                or not 0 <= self.frequencies <= MAX_FREQUENCIES:
            raise ValueError(f"MLPConfig.frequencies must be an integer in 0..{MAX_FREQUENCIES}, "
                             f"got {self.frequencies!r}")
        if self.hidden > MAX_HIDDEN or self.layers > MAX_LAYERS:
            raise ValueError(f"MLPConfig: at most {MAX_LAYERS} layers of {MAX_HIDDEN} units, got {self.layers} x {self.hidden}")
        for name, limit in (("state_dim", MAX_STATE_DIM), ("num_actions", MAX_ACTIONS), ("horizon", MAX_HORIZON)):
            if getattr(self, name) > limit:
                raise ValueError(f"MLPConfig.{name} is {getattr(self, name)}; at most {limit} is supported")
        if not isinstance(self.periodic, (list, tuple)) or not all(isinstance(p, bool) for p in self.periodic):
            raise ValueError(f"MLPConfig: periodic must be a list of bools, got {self.periodic!r}")
        if not isinstance(self.feature_scale, (list, tuple)) or len(self.periodic) != self.state_dim \
                or len(self.feature_scale) != self.state_dim:
            raise ValueError(f"MLPConfig: periodic and feature_scale need {self.state_dim} entries each")
        if any(isinstance(s, bool) or not isinstance(s, (int, float)) or not (0 < s < math.inf)
               for s in self.feature_scale):
            raise ValueError(f"MLPConfig: feature_scale must be positive finite numbers, got {self.feature_scale}")
        dims = self.start_dims
        if not isinstance(dims, (list, tuple)) or not all(type(i) is int and 0 <= i < self.state_dim for i in dims) \
                or list(dims) != sorted(set(dims)):
            raise ValueError(f"MLPConfig: start_dims must be distinct ascending dimensions in 0..{self.state_dim - 1}, "
                             f"got {dims!r}")
        if self.num_weights > MAX_WEIGHTS:  # the one check of the network's size, before anything is allocated
            raise ValueError(f"MLPConfig: {self.layers} layers of {self.hidden} units make {self.num_weights} weights; "
                             f"at most {MAX_WEIGHTS} are supported")

    @property
    def num_state_features(self) -> int:
        """Features of the state and the time (the start's come after them), before the encoding."""
        return sum(2 if p else 1 for p in self.periodic) + 1

    @property
    def num_features(self) -> int:
        """Inputs of the network: the state and time features with their encoding, then the start's."""
        return self.num_state_features * (1 + 2 * self.frequencies) + sum(
            2 if self.periodic[i] else 1 for i in self.start_dims)

    @property
    def num_weights(self) -> int:
        """Weights and biases of the network this config describes."""
        width, total = self.num_features, 0
        for _ in range(self.layers):
            total += (width + 1) * self.hidden
            width = self.hidden
        return total + (width + 1) * self.num_actions

    def to_dict(self) -> dict[str, Any]:
        """A plain dict; ``start_dims`` only when there are some (a pi(u | x, t) checkpoint keeps its old keys), and
        ``frequencies`` only when it is not 0 (so a network without the encoding writes the keys it always did)."""
        out = dataclasses.asdict(self)
        if not out["start_dims"]:
            del out["start_dims"]
        if not out["frequencies"]:
            del out["frequencies"]
        return out


@dataclass(frozen=True)
class MLPSupport:
    """The cells per level a policy was trained on: ``cells [C, d]`` int64 grid cells (angles in ``0..K-1``),
    level ``t`` being rows ``level_offsets[t]:level_offsets[t+1]`` of ``level_offsets [T+2]`` int64."""

    cells: Tensor
    level_offsets: Tensor

    def check(self, grid: Grid, horizon: int) -> None:
        """ValueError naming what does not describe cells per level of ``grid`` for levels ``0..horizon``."""
        cells, offsets = self.cells, self.level_offsets
        if not isinstance(cells, Tensor) or cells.dtype != torch.int64 or cells.ndim != 2 or cells.shape[1] != grid.dim:
            raise ValueError(f"support cells must be an int64 [C, {grid.dim}] tensor, got "
                             f"{getattr(cells, 'dtype', type(cells).__name__)} {list(getattr(cells, 'shape', []))}")
        if not isinstance(offsets, Tensor) or offsets.dtype != torch.int64 or offsets.shape != (horizon + 2,):
            raise ValueError(f"support level_offsets must be an int64 [{horizon + 2}] tensor (horizon {horizon}), got "
                             f"{getattr(offsets, 'dtype', type(offsets).__name__)} {list(getattr(offsets, 'shape', []))}")
        if int(offsets[0]) != 0 or int(offsets[-1]) != cells.shape[0] or bool((offsets.diff() < 0).any()):
            raise ValueError(f"support level_offsets must rise from 0 to the {cells.shape[0]} cells, got "
                             f"{offsets.tolist()[:8]}...")
        for dim, k in enumerate(grid.num_angle_cells):
            if k and cells.shape[0] and not (0 <= int(cells[:, dim].min()) and int(cells[:, dim].max()) < k):
                raise ValueError(f"support cells of angle dimension {dim} must lie in 0..{k - 1}")

    def index(self, grid: Grid, nearest: bool, dtype: torch.dtype, device: torch.device) -> TableIndex:
        """A lookup index of these cells (one dummy action): entries below C are support cells, then the halo."""
        C, d = self.cells.shape
        zeros = np.zeros(len(self.level_offsets) - 2, dtype=np.int64)
        table = Table(system="", actions=np.zeros((1, 1), np.float32), cell_size=np.array(grid.cell_size),
                      periodic=np.array(grid.periodic), cell_offset=np.array(grid.offset),
                      level_offsets=self.level_offsets.numpy(), cells=self.cells.numpy(),
                      action_probs=np.ones((C, 1), np.float32), cell_probs=np.zeros(C), flow_value=zeros,
                      flow_target=zeros)
        return build_index(table, grid, nearest=nearest, lookup=Lookup.AUTO, dtype=dtype, device=device)

    def to_dict(self) -> dict[str, Tensor]:
        return {"cells": self.cells.cpu(), "level_offsets": self.level_offsets.cpu()}


class MLPPolicy(WatchesStart, CountsFallbacks, nn.Module):
    """pi(u | x, t): ``action_probs(x [N, d], t) -> [N, A]``; works in ``rollout`` and every controller.

    It knows its support (``support``, else the box of the table's cells; see the module docstring), counts the
    states outside it (``queries``, ``nearest_hits``, ``misses``, ``miss_rate``) and answers them by
    ``fallback`` as a table does.
    """

    # declared so that nn.Module's __getattr__ (Tensor | Module) does not hide their types
    config: MLPConfig
    actions: Tensor
    inv_scale: Tensor
    _box_half: Tensor
    _box_cell: Tensor

    reads_start = False
    """whether the network reads start features after the state's (:class:`~cuniform_torch.policies.start_mlp.StartMLPPolicy`)"""

    def __init__(self, config: MLPConfig, system: System, actions: Tensor, support: MLPSupport | None = None,
                 fallback: str | Fallback = Fallback.NEAREST):
        super().__init__()
        if actions.ndim != 2 or actions.shape[0] != config.num_actions:
            raise ValueError(f"actions must be [{config.num_actions}, q], got {list(actions.shape)}")
        if len(system.periodic) != config.state_dim:
            raise ValueError(f"system {system.name} has {len(system.periodic)} state dims, config says {config.state_dim}")
        if config.start_dims and not self.reads_start:
            raise ValueError("a config with start_dims describes a start-conditioned policy: "
                             "cuniform_torch.policies.start_mlp.StartMLPPolicy")
        self.config = config
        self.system = system
        self.horizon = config.horizon
        self.register_buffer("actions", actions.detach().clone().float())  # [A, q]
        scale = torch.tensor(config.feature_scale, dtype=torch.float32)
        self.register_buffer("inv_scale", 1.0 / scale)  # [d]
        self._angle = [i for i, p in enumerate(config.periodic) if p]
        self._linear = [i for i, p in enumerate(config.periodic) if not p]
        layers: list[nn.Module] = []
        width = config.num_features
        for _ in range(config.layers):
            layers += [nn.Linear(width, config.hidden), nn.SiLU()]
            width = config.hidden
        layers.append(nn.Linear(width, config.num_actions))
        self.net = nn.Sequential(*layers)
        self.fallback = Fallback.parse(fallback)
        self._grid = Grid.of(system)
        if support is not None:
            support.check(self._grid, config.horizon)
        self.support = support
        self._support_index: TableIndex | None = None  # built on first use, on the device of the states
        # the box of the table's cells (non-periodic dimensions), for a checkpoint without support
        half = torch.tensor([s + c / 2 for s, c in zip(config.feature_scale, self._grid.cell_size)])
        # not persistent: they follow .to() but stay out of the state_dict (the config holds them)
        self.register_buffer("_box_half", half[self._linear], persistent=False)  # [d_lin]
        self.register_buffer("_box_cell", torch.tensor(self._grid.cell_size)[self._linear], persistent=False)
        # the build start: the centre of the support's level-0 cell (a table built at a start other than the zero
        # state), else the zero state
        start = None if support is None else self._grid.centers(support.cells[:1])[0]
        self.counts = FallbackCounts(self.device)
        """the lookups' fallback counts (:class:`~cuniform_torch.sampling.fallback_counts.FallbackCounts`)"""
        self._start_watch = StartWatch(f"MLP policy ({system.name})", system, start, self.counts)

    @property
    def start_relative(self) -> bool:
        """True only for an SE(2)-invariant system (states relative to the start pose, as for its table)."""
        return bool(self.system.se2_invariant)

    @property
    def device(self) -> torch.device:
        return self.actions.device

    @property
    def dtype(self) -> torch.dtype:
        return self.actions.dtype

    def features(self, x: Tensor, t: int | Tensor) -> Tensor:
        """``x [N, d]``, ``t`` (int or ``[N]``) -> ``[N, F]`` network inputs (see the module docstring)."""
        check_states(x, self.config.state_dim, self.device)
        f = state_features(x.to(self.dtype), t, self._linear, self._angle, self.inv_scale, self.config.horizon)
        return encode_features(f, self.config.frequencies)

    def forward(self, x: Tensor, t: int | Tensor) -> Tensor:
        """Logits ``[N, A]``."""
        return self.net(self.features(x, t))

    def action_probs(self, x: Tensor, t: int) -> Tensor:
        """Softmax of the logits: ``x [N, d]`` at level ``t`` -> ``[N, A]``, checked as a TablePolicy checks.

        ``t`` must be an int in ``0..horizon`` and ``x`` of the policy's dtype and device (ValueError otherwise;
        no silent conversion). A state outside the support gets the fallback (module docstring): the uniform row
        (counted in :attr:`misses`, as are NaN or infinite states) or, within one cell of it with
        ``fallback="nearest"``, the network's answer (counted in :attr:`nearest_hits`); ``queries`` counts every
        state looked up.
        """
        check_query(x, t, self.horizon, self.config.state_dim, self.dtype, self.device)
        with torch.no_grad():
            probs = torch.softmax(self(x, t), dim=1)  # [N, A]
            code = self.support_codes(x, t)  # [N]
            self.counts.add(x.shape[0], code.sum())
            miss = (code >= MISS).unsqueeze(1)  # [N, 1]
            return torch.where(miss, torch.full_like(probs[:1], 1.0 / probs.shape[1]), probs)

    def support_codes(self, x: Tensor, t: int) -> Tensor:
        """Fallback code of each state ``x [N, d]`` at level ``t``: ``[N]`` int64, 0 in the support,
        :data:`~cuniform_torch.tables.lookup.NEAREST` within one cell of it (``fallback="nearest"`` only),
        :data:`~cuniform_torch.tables.lookup.MISS` outside (and for NaN or infinite states)."""
        if self.support is not None:
            code = self._support_codes_exact(x, t)
        else:
            code = self._support_codes_box(x)
        finite = torch.isfinite(x).all(dim=1)  # [N]: cos(inf) and NaN give NaN logits
        return torch.where(finite, code, MISS)

    def _support_codes_exact(self, x: Tensor, t: int) -> Tensor:
        index = self._support_index
        if index is None or index.entry_code.device != x.device:
            assert self.support is not None  # support_codes reads the exact support only when there is one
            index = self._support_index = self.support.index(self._grid, self.fallback is Fallback.NEAREST,
                                                             self.dtype, x.device)
        entry = lookup_entries(index, x, t)  # [N] int32
        return index.entry_code.index_select(0, entry)

    def _support_codes_box(self, x: Tensor) -> Tensor:
        half, size = self._box_half.to(x.dtype), self._box_cell.to(x.dtype)  # [d_lin] each
        if self._linear:  # cells beyond the box, in the worst dimension
            excess = ((x[:, self._linear].abs() - half) / size).amax(dim=1)  # [N]
        else:
            excess = x.new_full((x.shape[0],), -1.0)
        near = self.fallback is Fallback.NEAREST
        code = torch.where(excess <= 0, 0, torch.where((excess <= 1) & near, NEAREST, MISS))
        return torch.where(torch.isnan(excess), MISS, code)


def default_feature_scale(cells_centres: Tensor, grid: Grid) -> list[float]:
    """``max |centre|`` per non-periodic dimension (1.0 where that is 0, and on angle dimensions)."""
    scale = cells_centres.abs().amax(dim=0).tolist()
    return [1.0 if (p or s == 0) else float(s) for s, p in zip(scale, grid.periodic)]
