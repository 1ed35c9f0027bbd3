"""cuniform_torch: the runtime library of C-Uniform trajectory sampling.

Systems, grid, table files, the table policy, batched rollouts, noise samplers, proposals, the MPPI family
(one core, :class:`MPPICore`, that takes a :class:`Proposal`) and navigation environments. See the README for a tour.
"""

from cuniform_torch.common.frames import se2_to_local, se2_to_world
from cuniform_torch.grid.cells import CellKeys, CellSet, Grid
from cuniform_torch.policies.checkpoint import POLICY_FORMAT, PolicyCheckpointError, load_policy, save_policy
from cuniform_torch.policies.mlp import MLPConfig, MLPPolicy, MLPSupport
from cuniform_torch.policies.start_mlp import StartMLPPolicy, StartRegion
from cuniform_torch.controllers.mppi import COST_CAP, CUMPPI, MPPI, CostFn, CUniformMPPI, LogMPPI, MPPICore, MPPIResult, mppi_weights
from cuniform_torch.maps.checkpoint import MAP_POLICY_FORMAT, MapCheckpointError, load_map_policy, map_policy_checkpoint, save_map_policy
from cuniform_torch.maps.encoder import MapEncoder, PatchSpec
from cuniform_torch.maps.policy import MapPolicy, MapPolicyConfig
from cuniform_torch.controllers.cfu import CFUMPPI, SensedMapPolicy
from cuniform_torch.maps.sensing import local_map, sense_patch
from cuniform_torch.policies.table import Fallback, TablePolicy, UniformPolicy
from cuniform_torch.policies.table_set import TableSetPolicy, load_table, load_table_set
from cuniform_torch.controllers.proposals import (BankProposal, BankRefreshWarning, CompositeProposal, GaussianProposal, NormalLogNormalProposal,
                        PolicyProposal, Proposal)
from cuniform_torch.sampling.rollout import ActionSampler, Policy, PolicyTraits, StartMismatchWarning, rollout, rollout_actions
from cuniform_torch.sampling.noise import GaussianSampler, NormalLogNormalSampler, lognormal_params
from cuniform_torch.systems import (
    KinematicSingleTrack,
    KinematicSingleTrackSpeed,
    check_system,
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
from cuniform_torch.tables.file import TABLE_FORMAT, Table, TableError, read_table, write_table

__all__ = [
    "se2_to_local", "se2_to_world", "POLICY_FORMAT", "MLPConfig", "MLPPolicy", "MLPSupport", "PolicyCheckpointError",
    "load_policy", "save_policy", "CellKeys", "CellSet", "Grid",
    "COST_CAP", "CUMPPI", "MPPI", "CostFn", "CUniformMPPI", "LogMPPI", "MPPICore", "MPPIResult", "mppi_weights",
    "BankProposal", "BankRefreshWarning", "CompositeProposal", "GaussianProposal", "NormalLogNormalProposal",
    "PolicyProposal", "Proposal",
    "Fallback", "TablePolicy", "UniformPolicy", "load_table", "ActionSampler", "Policy", "PolicyTraits",
    "StartMismatchWarning", "rollout",
    "rollout_actions",
    "GaussianSampler", "NormalLogNormalSampler", "lognormal_params",
    "Dubins", "KinematicSingleTrack", "KinematicSingleTrackSpeed", "check_system", "RandomWalk1D", "System", "UnknownSystemError", "known_systems", "make_system", "register_system",
    "system_from_json", "system_to_json", "TABLE_FORMAT", "Table", "TableError", "read_table", "write_table", "TableSetPolicy", "load_table_set",
    "MAP_POLICY_FORMAT", "MapCheckpointError", "load_map_policy", "map_policy_checkpoint", "save_map_policy",
    "MapEncoder", "PatchSpec", "MapPolicy", "MapPolicyConfig", "CFUMPPI", "SensedMapPolicy", "local_map", "sense_patch",
    "StartMLPPolicy", "StartRegion",
]
__version__ = "0.1.0"
