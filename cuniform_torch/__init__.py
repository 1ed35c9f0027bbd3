"""cuniform_torch: the runtime library of C-Uniform trajectory sampling (systems, grid, tables, policies, rollouts)."""

from .grid import CellKeys, CellSet, Grid
from .policy import TablePolicy, load_table
from .rollout import Policy, rollout
from .systems import (
    Dubins,
    RandomWalk1D,
    System,
    UnknownSystemError,
    known_systems,
    make_system,
    register_system,
    system_from_json,
    system_to_json,
)
from .table import TABLE_FORMAT, Table, TableError, read_table, write_table

__all__ = [
    "CellKeys", "CellSet", "Grid", "TablePolicy", "load_table", "Policy", "rollout", "Dubins", "RandomWalk1D",
    "System", "UnknownSystemError", "known_systems", "make_system", "register_system", "system_from_json",
    "system_to_json", "TABLE_FORMAT", "Table", "TableError", "read_table", "write_table",
]
__version__ = "0.1.0"
