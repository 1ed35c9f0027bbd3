"""Map-conditioned policies (C-Free-Uniform): the local map, its encoder and local features, sensing, the policy and its checkpoint."""

from cuniform_torch.maps.checkpoint import (
    MAP_POLICY_FORMAT,
    MapCheckpointError,
    load_map_policy,
    map_policy_checkpoint,
    save_map_policy,
)
from cuniform_torch.maps.encoder import MapEncoder, PatchSpec
from cuniform_torch.maps.policy import MapPolicy, MapPolicyConfig
from cuniform_torch.maps.sensing import local_map, sense_patch

__all__ = [
    "MapPolicy", "MapPolicyConfig", "MapEncoder", "PatchSpec", "local_map", "sense_patch",
    "load_map_policy", "save_map_policy", "map_policy_checkpoint", "MapCheckpointError", "MAP_POLICY_FORMAT",
]
