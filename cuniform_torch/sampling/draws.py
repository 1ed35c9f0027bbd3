"""Drawing a discrete action from given uniforms (what a batched rollout does with the uniforms it drew up front).

Shapes: N states, A actions, q action dimensions.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["inverse_cdf_pick"]


def inverse_cdf_pick(cdf: Tensor, actions: Tensor, r: Tensor) -> Tensor:
    """One action ``[N, q]`` per row of ``cdf [N, A]`` (cumulative, unnormalised weights) for the uniforms
    ``r [N]`` in ``[0, 1)``: ``r`` scaled to the row's total, then the first action whose cdf exceeds it."""
    u = r.to(cdf.dtype).unsqueeze(1) * cdf[:, -1:]  # [N, 1]
    pick = torch.searchsorted(cdf, u, right=True).squeeze(1).clamp_max_(cdf.shape[1] - 1)
    actions = actions if actions.dtype == cdf.dtype else actions.to(cdf.dtype)
    return actions.index_select(0, pick)
