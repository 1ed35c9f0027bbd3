"""A start-conditioned distilled policy pi(u | x, t, x0): one MLP for the starts of a table set.

Shapes: N states, d state dimensions, k start dimensions, S starts of the set, F0 state features, Fs start
features, H hidden units, A actions.

A table set (``python -m precompute.build --starts SPEC``) holds one table per start; ``python -m
training.distill --tables DIR`` distils all of them into one :class:`StartMLPPolicy`, whose inputs are the
state features of :class:`~cuniform_torch.policies.mlp.MLPPolicy` (in the start's frame on an SE(2)-invariant system,
as the runtime rolls out) followed by the start's features over its *start dimensions*
(:func:`start_dims_of`: the dimensions after (x, y, theta) of an SE(2)-invariant system, which the frame change
does not move, else every dimension), scaled like the state's: ``x0_i / feature_scale_i``, or ``cos`` and
``sin`` of an angle.

A rollout picks the start through :meth:`StartMLPPolicy.for_start` (what
:meth:`~cuniform_torch.sampling.rollout.RolloutPlan.run` calls, as for a
:class:`~cuniform_torch.policies.table_set.TableSetPolicy`), so :func:`~cuniform_torch.sampling.rollout.rollout`,
:class:`~cuniform_torch.CUniformMPPI` and :class:`~cuniform_torch.CUMPPI` use it unchanged. The start's part
of the first layer is folded into that layer's bias once per start, so a query costs what an
:class:`~cuniform_torch.policies.mlp.MLPPolicy`'s does.

The *start region* (:class:`StartRegion`, stored in the checkpoint) is the set's starts over the start
dimensions. A start is *inside* it when every start dimension lies in the starts' bounding box grown by half a
spacing (the range over the distinct values less one, i.e. a grid's step; at least one cell, the tolerance of
a single table's start). A rollout from a start outside it warns once per policy (``StartMismatchWarning``)
and is counted (:attr:`StartMLPPolicy.outside_starts`; the check reads the start on the host, one small copy per
rollout, a sync on a GPU). The support (honest-support counters, fallback) is the
pooled cells of the set's tables per level, as for an MLP of several tables.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from cuniform_torch.grid.cells import Grid
from cuniform_torch.policies.mlp import MLPConfig, MLPPolicy, MLPSupport
from cuniform_torch.policies.mlp_ops import check_query, inverse_cdf_draw, inverse_cdf_pick
from cuniform_torch.policies.table import Fallback
from cuniform_torch.sampling.rollout import OWN_ROBOT, StartMismatchWarning, check_states
from cuniform_torch.systems import System
from cuniform_torch.tables.lookup import MISS

__all__ = ["StartRegion", "StartMLPPolicy", "start_dims_of", "MAX_ABS_START"]

MAX_ABS_START = 1e6
"""the largest magnitude of a start value (state units: m, rad, m/s, ...): far beyond any robot's state, so a
larger one is a damaged or forged region (as :data:`~cuniform_torch.policies.checkpoint.MAX_ABS_WEIGHT` for
weights)"""


def start_dims_of(system: System) -> list[int]:
    """The dimensions a start-conditioned policy reads from the start: after (x, y, theta) on an
    SE(2)-invariant system, else all."""
    d = len(system.periodic)
    return list(range(3, d)) if getattr(system, "se2_invariant", False) else list(range(d))


@dataclass(frozen=True)
class StartRegion:
    """The starts a policy was trained on: ``starts [S, k]`` float64 over the state dimensions ``dims [k]``."""

    starts: Tensor
    dims: list[int]

    def check(self, system: System) -> None:
        """ValueError naming what is wrong: the dims must be :func:`start_dims_of` ``system``, the starts a
        finite float64 ``[S, k]`` tensor with S >= 1 and values within :data:`MAX_ABS_START`."""
        expect = start_dims_of(system)
        if list(self.dims) != expect:
            raise ValueError(f"start_region dims must be {expect} for {system.name} (the dimensions the frame change "
                             f"does not move), got {self.dims!r}")
        s = self.starts
        if not isinstance(s, Tensor) or s.dtype != torch.float64 or s.ndim != 2 or s.shape[1] != len(expect) \
                or s.shape[0] < 1:
            raise ValueError(f"start_region starts must be a float64 [S, {len(expect)}] tensor with S >= 1, got "
                             f"{getattr(s, 'dtype', type(s).__name__)} {list(getattr(s, 'shape', []))}")
        if not bool(torch.isfinite(s).all()):
            raise ValueError("start_region starts hold NaN or infinite values")
        if float(s.abs().max()) > MAX_ABS_START:
            raise ValueError(f"start_region starts hold a value of magnitude {float(s.abs().max()):.3g}, beyond the "
                             f"bound {MAX_ABS_START:g} of a robot's state")

    def bounds(self, grid: Grid) -> tuple[Tensor, Tensor]:
        """``(lo, hi)`` ``[k]`` float64: the starts' bounding box grown by half a spacing (module docstring)."""
        cell = torch.tensor(grid.cell_size, dtype=torch.float64)[self.dims]  # [k]
        lo, hi = self.starts.amin(dim=0), self.starts.amax(dim=0)
        distinct = torch.tensor([len(torch.unique(c)) for c in self.starts.T], dtype=torch.float64)  # [k]
        spacing = torch.where(distinct > 1, (hi - lo) / (distinct - 1).clamp_min(1), cell)
        margin = torch.maximum(spacing, cell) / 2
        return lo - margin, hi + margin

    def to_dict(self) -> dict[str, Any]:
        return {"starts": self.starts.detach().cpu(), "dims": list(self.dims)}


class StartMLPPolicy(MLPPolicy):
    """pi(u | x, t, x0) (module docstring): an :class:`MLPPolicy` that also reads the start, which each rollout
    sets through :meth:`for_start` (the region's first start until then)."""

    reads_start = True

    _start: Tensor  # a buffer, declared so that nn.Module's __getattr__ (Tensor | Module) does not hide its type

    def __init__(self, config: MLPConfig, system: System, actions: Tensor, region: StartRegion,
                 support: MLPSupport | None = None, fallback: str | Fallback = Fallback.NEAREST):
        if config.frequencies:
            raise ValueError("a start-conditioned policy reads the plain features: config.frequencies must be 0, "
                             f"got {config.frequencies}")
        if list(config.start_dims) != list(region.dims):
            raise ValueError(f"config.start_dims {config.start_dims} differ from the start region's dims {region.dims}")
        region.check(system)
        super().__init__(config, system, actions, support=support, fallback=fallback)
        self.region = region
        dims = list(region.dims)
        self._start_linear = [i for i in dims if not config.periodic[i]]
        self._start_angle = [i for i in dims if config.periodic[i]]
        self._rest = tuple(self.net)[1:]  # a tuple, not a Module: no second copy in the state_dict
        a = self._angle  # angle dimensions one after another are read as a slice (a view, not a gather)
        self._angle_slice = slice(a[0], a[-1] + 1) if a and a == list(range(a[0], a[-1] + 1)) else None
        lo, hi = region.bounds(self._grid)
        self._lo, self._hi = lo, hi  # [k] float64, on the host
        self._periodic = torch.tensor([config.periodic[i] for i in dims])  # [k]
        first = torch.zeros(len(system.periodic), dtype=torch.float64)
        first[dims] = region.starts[0]
        self.register_buffer("_start", first.float(), persistent=False)  # [d] the current start
        self._warned = False
        self._outside_starts = 0
        self._fold_key: tuple | None = None
        self._folded_layer: tuple | None = None

    @property
    def build_start(self) -> Tensor:
        """The current start over the start dimensions (0 elsewhere), ``[d]`` float64: what a table built for it
        would record."""
        start = torch.zeros_like(self._start, dtype=torch.float64, device="cpu")
        start[self.region.dims] = self._start.detach().double().cpu()[self.region.dims]
        return start

    def start_features(self, start: Tensor) -> Tensor:
        """``start [N, d]`` (full states; only the start dimensions are read) -> ``[N, Fs]``."""
        start = start.to(self.dtype)
        parts = [start[:, self._start_linear] * self.inv_scale[self._start_linear]]
        if self._start_angle:
            ang = start[:, self._start_angle]
            parts += [torch.cos(ang), torch.sin(ang)]
        return torch.cat(parts, dim=1)

    def forward(self, x: Tensor, t: int | Tensor, start: Tensor | None = None) -> Tensor:
        """Logits ``[N, A]`` of ``x [N, d]`` at ``t`` (int or ``[N]``) from ``start [N, d]`` (training), or from
        the current start (``None``; without gradients, through the folded layers of :meth:`_folded`)."""
        if start is None and torch.is_grad_enabled():  # the folded layer is detached: gradients need the plain one
            start = self._start.expand(x.shape[0], -1)
        if start is None:
            check_states(x, self.config.state_dim, self.device)
            return self._logits(x.to(self.dtype), t)
        h = self.net[0](torch.cat((self.features(x, t), self.start_features(start)), dim=1))
        for layer in self._rest:
            h = layer(h)
        return h

    def _logits(self, x: Tensor, t: int | Tensor) -> Tensor:
        """:meth:`forward` from the current start through the folded layers, for checked states of the policy's
        dtype (no gradient)."""
        wx, offset, wcs, bias, rows, rest = self._folded()
        bias_t = rows[t] if isinstance(t, int) else bias.index_select(0, t.long())  # [H] or [N, H]
        h = torch.addmm(bias_t, x, wx)
        if offset is not None:  # [cos, sin] of the angles as one sin: sin(a + pi/2) = cos(a)
            ang = x[:, self._angle_slice] if self._angle_slice is not None else x[:, self._angle]
            ang = ang.repeat(1, 2) if ang.shape[1] > 1 else ang  # [N, 2a], or [N, 1] broadcast against [2]
            h.addmm_(torch.sin(ang + offset), wcs)
        for w_t, b in rest:  # SiLU in place, then the next linear layer (no module calls: a query is short)
            h = torch.addmm(b, torch.nn.functional.silu(h, inplace=True), w_t)
        return h

    def _folded(self) -> tuple:
        """The first layer for the current start with the feature scales, the time and the start folded in:
        ``wx [d, H]`` (scaled rows for the non-periodic dimensions, zero rows for the angles), ``offset [2a]``
        (pi/2 then 0: ``sin(angles + offset)`` is ``[cos, sin]``; None without angles), ``wcs [2a, H]``,
        ``bias [T+1, H]`` and its rows, so that ``x @ wx + sin(angles + offset) @ wcs + bias[t]`` is the first
        layer's output; and the later linear layers as ``(weight.T, bias)``. Rebuilt when the weights or the
        start change (their version counters)."""
        first = self.net[0]
        assert isinstance(first, torch.nn.Linear)  # the network starts with a linear layer (MLPPolicy builds it)
        key = (tuple((p._version, p.data_ptr()) for p in self.net.parameters()), self._start._version,
               self._start.data_ptr())
        if self._fold_key != key:
            with torch.no_grad():
                w = first.weight.detach()  # [H, F]
                nl, na, f0 = len(self._linear), len(self._angle), self.config.num_state_features
                wx = w.new_zeros((self.config.state_dim, w.shape[0]))
                wx[self._linear] = (w[:, :nl] * self.inv_scale[self._linear]).T
                wcs = w[:, nl:nl + 2 * na].T.contiguous()  # [2a, H]
                s = self.start_features(self._start.unsqueeze(0)).squeeze(0)  # [Fs]
                base = first.bias.detach() + w[:, f0:] @ s  # [H]
                steps = torch.arange(self.horizon + 1, dtype=w.dtype, device=w.device) / self.horizon
                bias = base + steps.unsqueeze(1) * w[:, f0 - 1]  # [T+1, H]: the time feature t / T
                rest = [(m.weight.detach().T.contiguous(), m.bias.detach()) for m in self._rest
                        if isinstance(m, torch.nn.Linear)]  # [in, out], [out] of the layers after the first
                offset = torch.tensor([math.pi / 2] * na + [0.0] * na, dtype=w.dtype, device=w.device) if na else None
            self._folded_layer, self._fold_key = (wx, offset, wcs, bias, bias.unbind(0), rest), key
        assert self._folded_layer is not None  # built with its key above
        return self._folded_layer

    def _weights(self, x: Tensor, t: int) -> Tensor:
        """Unnormalised probabilities ``[N, A]`` of checked states (ones on the rows the fallback answers
        uniformly), the lookups counted as :meth:`MLPPolicy.action_probs` counts them."""
        check_query(x, t, self.horizon, self.config.state_dim, self.dtype, self.device)
        with torch.no_grad():
            logits = self._logits(x, t)  # [N, A]
            e = logits.sub_(logits.amax(dim=1, keepdim=True)).exp_()  # torch.softmax is slow on few actions
            code = self.support_codes(x, t)  # [N]
            self.counts.add(x.shape[0], code.sum())
            return e.masked_fill_((code >= MISS).unsqueeze(1), 1.0)

    def action_probs(self, x: Tensor, t: int) -> Tensor:
        """``x [N, d]`` at level ``t`` from the current start -> ``[N, A]``, checked and counted, with the
        fallback, as :meth:`MLPPolicy.action_probs`."""
        e = self._weights(x, t)
        return e / e.sum(dim=1, keepdim=True)

    def sample(self, x: Tensor, t: int, generator: torch.Generator | None = None) -> Tensor:
        """Actions ``[N, q]`` drawn from :meth:`action_probs` (inverse CDF, one uniform per state: cheaper than
        ``torch.multinomial``); what a rollout draws through."""
        return inverse_cdf_draw(self._weights(x, t).cumsum_(dim=1), self.actions, generator)

    def draw(self, x: Tensor, t: int, r: Tensor) -> Tensor:
        """:meth:`sample` with the uniforms ``r [N]`` in ``[0, 1)`` given."""
        return inverse_cdf_pick(self._weights(x, t).cumsum_(dim=1), self.actions, r)

    def for_start(self, x0: Tensor) -> StartMLPPolicy:
        """Serve rollouts from ``x0 [d]`` (or the first row of ``[N, d]``) from now on; returns ``self``."""
        row = x0 if x0.ndim == 1 else x0[0]
        self._start.copy_(row.detach())
        return self

    def outside(self, x0: Tensor) -> bool:
        """Whether the start ``x0 [d]`` (or the first row of ``[N, d]``) lies outside the start region."""
        row = (x0 if x0.ndim == 1 else x0[0]).detach().double().cpu()[self.region.dims]  # [k]
        if not bool(torch.isfinite(row).all()):
            return True
        below, above = self._lo - row, row - self._hi  # [k] > 0 beyond a side
        gap = torch.maximum(below, above).clamp_min(0)
        wrapped = torch.stack([torch.maximum(self._lo - (row + k), (row + k) - self._hi).clamp_min(0)
                               for k in (-2 * math.pi, 2 * math.pi)]).amin(dim=0)
        gap = torch.where(self._periodic, torch.minimum(gap, wrapped), gap)  # an angle may lie a turn away
        return bool((gap > 0).any())

    def watch_start(self, x0: Tensor, relative: bool) -> Callable[[], None] | None:
        """Before a rollout from ``x0``: count it when it starts outside the region, and warn (once per policy,
        after the rollout, with its miss rate)."""
        if not self.outside(x0):
            return None
        self._outside_starts += 1
        if self._warned:
            return None
        queries, misses = self.queries, self.misses.clone()
        return lambda: self._warn(x0, queries, misses)

    def _warn(self, x0: Tensor, queries: int, misses: Tensor) -> None:
        self._warned = True
        asked, missed = self.queries - queries, int(self.misses) - int(misses)
        rate = f"{missed / asked:.3f} ({missed} of {asked} lookups)" if asked else "not counted"
        start = [round(v, 4) for v in (x0 if x0.ndim == 1 else x0[0]).tolist()]
        box = ", ".join(f"dim {i}: [{lo:.4g}, {hi:.4g}]" for i, lo, hi in
                        zip(self.region.dims, self._lo.tolist(), self._hi.tolist()))
        warnings.warn(
            f"start-conditioned MLP policy ({self.system.name}) was trained on {self.region.starts.shape[0]} starts "
            f"({box}, half a spacing included) and is rolled out from {start}, outside them: its answers there are "
            f"extrapolation. Miss rate on this rollout: {rate}. Add starts to the table set and distil again (see "
            f"{OWN_ROBOT}). Warned once per policy; outside_starts counts every such rollout.",
            StartMismatchWarning, stacklevel=5)

    def reset_counters(self) -> None:
        """Zero the lookup counters of :class:`MLPPolicy` and :attr:`outside_starts`."""
        super().reset_counters()
        self._outside_starts = 0

    @property
    def outside_starts(self) -> int:
        """Rollouts since the last :meth:`reset_counters` whose start lay outside the start region."""
        return self._outside_starts
