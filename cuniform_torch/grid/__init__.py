"""Grids of a state space: integer cells, packed int64 keys, sorted-key and hashed lookups."""

from cuniform_torch.grid.cells import CellKeys, CellSet, Grid
from cuniform_torch.grid.key_hash import KeyHash

__all__ = ["Grid", "CellKeys", "CellSet", "KeyHash"]
