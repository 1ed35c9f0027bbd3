"""Policies pi(u | x, t): the table policy, table sets, the distilled MLP, the start-conditioned MLP and their checkpoint file."""

from cuniform_torch.policies.checkpoint import POLICY_FORMAT, PolicyCheckpointError, load_policy, save_policy
from cuniform_torch.policies.mlp import MLPConfig, MLPPolicy, MLPSupport
from cuniform_torch.policies.start_mlp import StartMLPPolicy, StartRegion
from cuniform_torch.policies.table import Fallback, TablePolicy, UniformPolicy
from cuniform_torch.policies.table_set import TableSetPolicy, load_table, load_table_set

__all__ = [
    "TablePolicy", "UniformPolicy", "Fallback", "TableSetPolicy", "load_table", "load_table_set",
    "MLPConfig", "MLPPolicy", "MLPSupport", "StartMLPPolicy", "StartRegion",
    "load_policy", "save_policy", "PolicyCheckpointError", "POLICY_FORMAT",
]
