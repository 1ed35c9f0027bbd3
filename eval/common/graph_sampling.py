"""Graph sampling (the ``cu_graph`` baseline): cell sequences drawn on a table's flow graph, as the paper's
reference release samples them. An evaluation baseline, not part of the runtime: controllers cannot use it.

Shapes: N sampled sequences, T horizon, d state dimensions, E arcs.

From the start cell, each step follows one arc of the max-flow network leaving the current cell, with
probability proportional to the arc's flow (a cell whose arcs all carry zero flow picks one of them
uniformly). The result is a sequence of *cells*, not an executed trajectory: the arcs say that some point of
the cell reaches the next cell with some action, not that the sampled state does. The paper's coverage table
(Table I) counts these sequences; :func:`~cuniform_torch.sampling.rollout.rollout` of a
:class:`~cuniform_torch.policies.table.TablePolicy` executes real actions instead. Needs a table with ``arcs`` and
``arc_flow`` (the max-flow builder writes them).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from cuniform_torch.grid.cells import Grid
from cuniform_torch.tables.file import Table, TableError

__all__ = ["GraphSampler"]


class GraphSampler:
    """Samples cell sequences ``[N, T+1, d]`` on ``table``'s flow graph (see the module docstring)."""

    def __init__(self, table: Table, device: torch.device | str = "cpu"):
        if table.arcs is None or table.arc_flow is None or table.arc_offsets is None:
            raise TableError(f"graph sampling needs the flow graph (arcs, arc_flow); this {table.method or 'table'} "
                             f"table has none: build it with --method maxflow")
        self.table = table
        self.system = table.make_system()
        self.grid = Grid.of(self.system)
        self.horizon = table.horizon
        self.device = torch.device(device)
        order = np.lexsort((np.arange(len(table.arcs)), table.arcs[:, 0]))  # group arcs by source row, stable
        arcs = table.arcs[order]
        flow = table.arc_flow[order].astype(np.float64)
        C = len(table.cells)
        out_count = np.bincount(arcs[:, 0], minlength=C)
        out_flow = np.bincount(arcs[:, 0], weights=flow, minlength=C)
        weight = np.where(out_flow[arcs[:, 0]] > 0, flow, 1.0)  # zero-flow cells: uniform over their arcs
        self._first = torch.from_numpy(np.concatenate(([0], np.cumsum(out_count)[:-1]))).to(self.device)  # [C]
        self._count = torch.from_numpy(out_count).to(self.device)  # [C]
        cum = np.cumsum(weight)
        self._cum = torch.from_numpy(cum).to(self.device)  # [E] running weight
        self._before = torch.from_numpy(cum - weight).to(self.device)  # [E] running weight before each arc
        self._to = torch.from_numpy(arcs[:, 1]).to(self.device)  # [E]
        self._cells = torch.from_numpy(table.cells).to(self.device)  # [C, d]
        start = int(table.level_offsets[0])
        self._start_row = start
        last = int(table.level_offsets[-2])
        if bool((out_count[:last] == 0).any()):
            bad = int(np.flatnonzero(out_count[:last] == 0)[0])
            raise TableError(f"graph sampling: table row {bad} (not in the last level) has no outgoing arc")

    def sample_rows(self, num_samples: int, horizon: int | None = None,
                    generator: torch.Generator | None = None) -> Tensor:
        """``[N, T+1]`` global table rows of the sampled cell sequences."""
        T = self.horizon if horizon is None else horizon
        if T > self.horizon:
            raise ValueError(f"horizon {T} is longer than the table ({self.horizon} steps)")
        row = torch.full((num_samples,), self._start_row, dtype=torch.int64, device=self.device)
        rows = [row]
        for _ in range(T):
            first, count = self._first[row], self._count[row]
            lo = self._before[first]  # running weight before the cell's first arc
            hi = self._cum[first + count - 1]
            r = torch.rand(num_samples, generator=generator, dtype=torch.float64, device=self.device)
            target = lo + r * (hi - lo)
            arc = torch.searchsorted(self._cum, target, right=True)
            arc = torch.minimum(torch.maximum(arc, first), first + count - 1)  # float edge cases stay in the group
            row = self._to[arc]
            rows.append(row)
        return torch.stack(rows, dim=1)

    def sample(self, num_samples: int, horizon: int | None = None, generator: torch.Generator | None = None,
               dtype: torch.dtype = torch.float32) -> Tensor:
        """``[N, T+1, d]`` cell centres of the sampled sequences (usable wherever states are expected)."""
        rows = self.sample_rows(num_samples, horizon, generator)
        return self.grid.centers(self._cells[rows], dtype=dtype)
