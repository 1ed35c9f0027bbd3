"""The halo of a table: the cells next to each level set, each answered by its nearest cell of that level.

Shapes: C table cells, H halo cells, d state dimensions, O = 3^d - 1 neighbour offsets.

A state just outside L_t (one cell away, angles wrapped) takes the action row of the nearest cell of L_t
(``fallback="nearest"``, see :class:`~cuniform_torch.policies.table.TablePolicy`). "Nearest" is the smallest squared grid
distance between cell indices; ties go to the lower table row. :func:`halo` lists those cells once, when the
index is built (:func:`~cuniform_torch.tables.lookup.build_index`), so a lookup never searches for a neighbour.
"""

from __future__ import annotations

import itertools

import torch
from torch import Tensor

from cuniform_torch.grid.cells import CellKeys, CellSet, Grid

__all__ = ["halo"]


def halo(keyed: Tensor, grid: Grid) -> tuple[Tensor, Tensor]:
    """Neighbour cells of each level not in it, with the row of their nearest cell: ``([H, 1+d], [H])``.

    ``keyed [C, 1+d]`` holds (level, cell) per table row. The halo cells come out in packed-key order, each with
    the table row of least grid distance, ties to the lower row. One neighbour offset at a time, so memory stays
    in proportion to the table and the halo rather than to the 3^d - 1 neighbours of every cell.
    """
    d = grid.dim
    offsets = torch.tensor([o for o in itertools.product((-1, 0, 1), repeat=d) if any(o)], dtype=torch.int64)  # [O, d]
    dist2 = (offsets**2).sum(dim=1).tolist()  # [O] squared grid distance
    C = keyed.shape[0]
    k = grid.num_angle_cells
    box = CellKeys.covering(keyed)  # widened by the one-cell step on every non-angle dimension; angles: [0, K)
    lo, span = box.lo.clone(), box.span.clone()
    for dim in range(d):
        lo[1 + dim], span[1 + dim] = (0, k[dim]) if k[dim] else (lo[1 + dim] - 1, span[1 + dim] + 2)
    keys = CellKeys(lo, span)
    own = CellSet.build(keyed, keys)
    packed_parts, rank_parts = [], []
    rows = torch.arange(C)
    for offset, d2 in zip(offsets, dist2):
        nb = keyed.clone()  # [C, 1+d]
        nb[:, 1:] += offset
        for dim, kk in enumerate(k):
            if kk:
                nb[:, 1 + dim] = torch.remainder(nb[:, 1 + dim], kk)
        outside = own.lookup(nb) < 0  # [C]
        packed_parts.append(keys.pack(nb[outside]))
        rank_parts.append(d2 * C + rows[outside])  # ordered by (distance, source row)
    packed, rank = torch.cat(packed_parts), torch.cat(rank_parts)
    cells, inverse = torch.unique(packed, return_inverse=True)  # [H] ascending
    best = torch.full_like(cells, torch.iinfo(torch.int64).max).scatter_reduce_(0, inverse, rank, reduce="amin")
    return keys.unpack(cells), best % C
