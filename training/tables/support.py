"""The support a distilled policy records: the cells per level of the tables it was trained on.

:class:`cuniform_torch.policies.mlp.MLPSupport` holds them in the checkpoint (key ``support``), so that the loaded
:class:`~cuniform_torch.policies.mlp.MLPPolicy` counts and falls back on states outside them, as a table does.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from cuniform_torch.policies.mlp import MLPSupport
from cuniform_torch.tables.file import Table

__all__ = ["pooled_support"]


def pooled_support(tables: Sequence[Table], horizon: int) -> MLPSupport:
    """The union of the tables' cells per level ``0..horizon``, each level's cells distinct and in ascending
    (row-major) order as in a table: ``cells [C, d]``, ``level_offsets [horizon + 2]``."""
    levels = []
    for t in range(horizon + 1):
        rows = [tb.cells[tb.level_offsets[t]:tb.level_offsets[t + 1]] for tb in tables]
        levels.append(np.unique(np.concatenate(rows), axis=0))
    offsets = np.concatenate([[0], np.cumsum([len(c) for c in levels])]).astype(np.int64)
    return MLPSupport(torch.from_numpy(np.concatenate(levels).astype(np.int64)), torch.from_numpy(offsets))
