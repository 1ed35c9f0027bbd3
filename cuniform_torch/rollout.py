"""Batched rollouts of a policy through a system: one batched step per time step, no loop over samples.

Shapes: N samples, T horizon, d state dimensions, q action dimensions, A actions.
"""

from __future__ import annotations

from typing import Protocol

import torch
from torch import Tensor

from .systems import System

__all__ = ["Policy", "rollout"]


class Policy(Protocol):
    """Anything with a discrete action set and per-state action probabilities."""

    actions: Tensor
    """``[A, q]``"""

    def action_probs(self, x: Tensor, t: int) -> Tensor:
        """``x [N, d]`` at step ``t`` -> ``[N, A]`` probabilities (rows sum to 1)."""
        ...


def rollout(
    system: System,
    policy: Policy,
    x0: Tensor,
    num_samples: int,
    horizon: int,
    generator: torch.Generator | None = None,
) -> tuple[Tensor, Tensor]:
    """Sample ``num_samples`` trajectories of ``horizon`` steps from ``x0 [d]`` (or ``[N, d]``).

    Returns ``states [N, T+1, d]`` (start included) and ``actions [N, T, q]``. The dtype and device are those of
    ``x0``; pass a seeded ``generator`` on that device for reproducible samples.
    """
    d = len(system.periodic)
    for name, value, least in (("num_samples", num_samples, 1), ("horizon", horizon, 0)):
        if isinstance(value, bool) or not isinstance(value, int) or value < least:
            raise ValueError(f"{name} must be an integer >= {least}, got {value!r}")
    if not isinstance(x0, torch.Tensor) or not x0.is_floating_point():
        raise ValueError(f"x0 must be a floating-point tensor, got {getattr(x0, 'dtype', type(x0).__name__)}")
    if x0.shape != (d,) and x0.shape != (num_samples, d):
        raise ValueError(f"x0 must have shape [{d}] or [{num_samples}, {d}], got {list(x0.shape)}")
    if x0.ndim == 1:
        x0 = x0.unsqueeze(0).expand(num_samples, d)
    if not bool(torch.isfinite(x0).all()):
        raise ValueError("x0 contains NaN or infinite values")
    table_horizon = getattr(policy, "horizon", None)
    if table_horizon is not None and horizon > table_horizon:
        raise ValueError(f"horizon {horizon} is longer than the policy's table ({table_horizon} steps)")
    actions = policy.actions.to(dtype=x0.dtype)  # [A, q]
    states = [x0]
    taken = []
    x = x0
    for t in range(horizon):
        probs = policy.action_probs(x, t)  # [N, A]
        idx = torch.multinomial(probs, 1, generator=generator).squeeze(1)  # [N]
        u = actions[idx]  # [N, q]
        x = system.step(x, u)
        states.append(x)
        taken.append(u)
    states_t = torch.stack(states, dim=1)  # [N, T+1, d]
    actions_t = torch.stack(taken, dim=1) if taken else x0.new_zeros((num_samples, 0, actions.shape[1]))
    return states_t, actions_t
