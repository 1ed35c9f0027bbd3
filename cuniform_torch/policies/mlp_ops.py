"""Pieces the MLP policies share (:mod:`cuniform_torch.policies.mlp`, :mod:`cuniform_torch.policies.start_mlp`,
:mod:`cuniform_torch.maps.policy`): the state / time features, the query check and the inverse-CDF draw.

Shapes: N states, d state dimensions, F features, A actions, q action dimensions.
"""

from __future__ import annotations

import torch
from torch import Tensor

from cuniform_torch.sampling.draws import inverse_cdf_pick
from cuniform_torch.sampling.rollout import check_states

__all__ = ["state_features", "encode_features", "check_query", "inverse_cdf_draw"]


def state_features(x: Tensor, t: int | Tensor, linear: list[int], angle: list[int], inv_scale: Tensor,
                   horizon: int) -> Tensor:
    """``x [N, d]``, ``t`` (int or ``[N]``) -> ``[N, F]``: ``x_i * inv_scale_i`` on ``linear`` dimensions,
    ``cos``, ``sin`` on ``angle`` ones, then ``t / horizon``."""
    parts = [x[:, linear] * inv_scale[linear]]
    if angle:
        ang = x[:, angle]
        parts += [torch.cos(ang), torch.sin(ang)]
    tt = torch.as_tensor(t, dtype=x.dtype, device=x.device) / horizon
    parts.append(tt.expand(x.shape[0]).unsqueeze(1) if tt.ndim == 0 else tt.unsqueeze(1))
    return torch.cat(parts, dim=1)


def encode_features(f: Tensor, frequencies: int) -> Tensor:
    """``f [N, F]`` -> ``[N, F (1 + 2K)]``: ``f``, then ``sin(2^k pi f)`` of every feature and k = 0..K-1
    (feature-major: feature 0's K octaves first), then the cosines likewise; ``f`` itself when K = 0."""
    if not frequencies:
        return f
    octaves = torch.pi * torch.pow(2.0, torch.arange(frequencies, dtype=f.dtype, device=f.device))  # [K]
    z = (f.unsqueeze(2) * octaves).flatten(1)  # [N, F K]
    return torch.cat((f, torch.sin(z), torch.cos(z)), dim=1)


def check_query(x: Tensor, t: int, horizon: int, state_dim: int, dtype: torch.dtype, device: torch.device) -> None:
    """ValueError unless ``t`` is an int in ``0..horizon`` and ``x [N, d]`` checked states of ``dtype``."""
    if isinstance(t, bool) or not isinstance(t, int) or not 0 <= t <= horizon:
        raise ValueError(f"level t={t!r} is outside the policy's levels 0..{horizon} (an integer)")
    check_states(x, state_dim, device)
    if x.dtype != dtype:
        raise ValueError(f"states are {x.dtype} but the policy is {dtype}")


def inverse_cdf_draw(cdf: Tensor, actions: Tensor, generator: torch.Generator | None) -> Tensor:
    """One action ``[N, q]`` per row of ``cdf [N, A]`` (cumulative, unnormalised weights; consumed in place):
    a uniform per row scaled to the row's total, then the first action whose cdf exceeds it."""
    r = torch.rand(cdf.shape[0], generator=generator, dtype=cdf.dtype, device=cdf.device)
    return inverse_cdf_pick(cdf, actions, r)
