"""cuniform_torch: the runtime library of C-Uniform trajectory sampling.

Load a table (or a distilled policy), roll it out, or control with one of the MPPI family, whose one core
(:class:`MPPICore`) takes any :class:`Proposal`. The names a user needs are here:

* systems: :class:`System` (the protocol), :class:`Dubins`, :class:`RandomWalk1D`, :class:`KinematicSingleTrack`,
  :func:`make_system`, :func:`register_system`, :func:`check_system`;
* tables: :class:`Table`, :func:`read_table`, :func:`write_table` (the file), :func:`load_table` (a table or a
  table-set folder as a policy);
* policies: :class:`TablePolicy`, :func:`load_policy` (a distilled MLP), :func:`load_map_policy` (a map policy);
* sampling: :func:`rollout` (a policy's rollouts), :func:`rollout_actions` (the states of given actions: what
  your own proposal returns);
* controllers: :class:`MPPI`, :class:`LogMPPI`, :class:`CUniformMPPI`, :class:`CUMPPI`, :class:`CFUMPPI`,
  :class:`MPPICore`, :class:`Proposal`;
* environments: :class:`Environment`, :class:`Circle`, :class:`Rect`, :class:`Polygon`, :class:`NavigationCost`,
  :func:`simulate`.

Everything else stays importable from its sub-package, each with a short ``__all__``: ``cuniform_torch.systems``,
``.grid``, ``.tables``, ``.policies``, ``.sampling``, ``.controllers``, ``.maps``, ``.envs`` and the module
``.metrics`` (coverage, uniformity). Coming from pytorch_mppi:
``MPPI`` takes a dynamics function with pytorch_mppi's keywords, and ``cuniform_torch.pytorch_mppi`` is a drop-in
(its ``MPPI`` and ``MPPI_Batched``, pytorch_mppi's signatures).
"""

from cuniform_torch.controllers.cfu import CFUMPPI
from cuniform_torch.controllers.core import MPPICore
from cuniform_torch.controllers.mppi import CUMPPI, MPPI, CUniformMPPI, LogMPPI
from cuniform_torch.controllers.proposals import Proposal
from cuniform_torch.envs.costs import NavigationCost
from cuniform_torch.envs.environment import Environment
from cuniform_torch.envs.shapes import Circle, Polygon, Rect
from cuniform_torch.envs.sim import simulate
from cuniform_torch.maps.checkpoint import load_map_policy
from cuniform_torch.policies.checkpoint import load_policy
from cuniform_torch.policies.table import TablePolicy
from cuniform_torch.policies.table_set import load_table
from cuniform_torch.sampling.rollout import rollout, rollout_actions
from cuniform_torch.systems import (
    Dubins,
    KinematicSingleTrack,
    RandomWalk1D,
    System,
    check_system,
    make_system,
    register_system,
)
from cuniform_torch.tables.file import Table, read_table, write_table

__all__ = [
    # systems
    "System", "Dubins", "RandomWalk1D", "KinematicSingleTrack", "make_system", "register_system", "check_system",
    # tables
    "Table", "read_table", "write_table", "load_table",
    # policies
    "TablePolicy", "load_policy", "load_map_policy",
    # sampling
    "rollout", "rollout_actions",
    # controllers
    "MPPI", "LogMPPI", "CUniformMPPI", "CUMPPI", "CFUMPPI", "MPPICore", "Proposal",
    # environments
    "Environment", "Circle", "Rect", "Polygon", "NavigationCost", "simulate",
]
__version__ = "0.1.0"
