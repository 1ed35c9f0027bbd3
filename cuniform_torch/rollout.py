"""Batched rollouts of a policy or a noise sampler through a system: one batched step per time step.

Shapes: N samples, T horizon, d state dimensions, q action dimensions, A actions.

Two kinds of proposal sources drive the same :func:`rollout`:

* a discrete :class:`Policy` (``actions [A, q]`` and ``action_probs(x, t) -> [N, A]``): a table or an MLP;
  actions are drawn by categorical sampling;
* a continuous :class:`ActionSampler` (``sample(x, t, generator) -> [N, q]``): Gaussian (MPPI) or
  normal x log-normal (log-MPPI) noise around a nominal sequence, see :mod:`cuniform_torch.samplers`.

A policy with ``start_relative = True`` (tables and MLPs, built at the origin) on an SE(2)-invariant system is
rolled out from the origin and its states are moved to the start pose by a rigid transform.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import torch
from torch import Tensor

from .frames import se2_to_world
from .systems import System

__all__ = ["Policy", "ActionSampler", "rollout", "check_states", "check_generator", "same_device"]


@runtime_checkable
class Policy(Protocol):
    """Anything with a discrete action set and per-state action probabilities."""

    actions: Tensor
    """``[A, q]``"""

    def action_probs(self, x: Tensor, t: int) -> Tensor:
        """``x [N, d]`` at step ``t`` -> ``[N, A]`` probabilities (rows sum to 1)."""
        ...


@runtime_checkable
class ActionSampler(Protocol):
    """Anything that draws continuous actions for a batch of states."""

    def sample(self, x: Tensor, t: int, generator: torch.Generator | None) -> Tensor:
        """``x [N, d]`` at step ``t`` -> actions ``[N, q]``."""
        ...


def _device_index(device: torch.device) -> int:
    if device.index is not None:
        return device.index
    return torch.cuda.current_device() if device.type == "cuda" else 0


def same_device(a: torch.device | str, b: torch.device | str) -> bool:
    """Whether two devices are one: ``"cuda"`` (no index: the current device) is ``cuda:0`` when that is current,
    which ``torch.device`` equality says it is not (a tensor's device always has its index)."""
    a, b = torch.device(a), torch.device(b)
    return a.type == b.type and (a.index == b.index or _device_index(a) == _device_index(b))


def check_states(x: Tensor, dim: int, device: torch.device, who: str = "the policy") -> None:
    """Raise ValueError unless ``x`` is a floating-point ``[N, dim]`` tensor on ``device``."""
    if not isinstance(x, Tensor) or x.ndim != 2 or x.shape[1] != dim:
        raise ValueError(f"states must have shape [N, {dim}], got {list(getattr(x, 'shape', []))}")
    if not same_device(x.device, device):
        raise ValueError(f"states are on {x.device} but {who} is on {device}")
    if not x.is_floating_point():
        raise ValueError(f"states must be a floating-point tensor, got {x.dtype}")


def check_generator(generator: object, device: torch.device, name: str = "generator") -> None:
    """Raise TypeError unless ``generator`` is None or a ``torch.Generator``, ValueError if it is not on ``device``."""
    if generator is None:
        return
    if not isinstance(generator, torch.Generator):
        raise TypeError(f"{name} must be a torch.Generator or None, got {type(generator).__name__} ({generator!r:.40}); "
                        f"make one with torch.Generator(device).manual_seed(seed)")
    if not same_device(generator.device, device):
        raise ValueError(f"{name} is on {generator.device} but the samples are drawn on {device}")


def _check_args(system: System, x0: Tensor, num_samples: int, horizon: int) -> int:
    d = len(system.periodic)
    for name, value, least in (("num_samples", num_samples, 1), ("horizon", horizon, 0)):
        if isinstance(value, bool) or not isinstance(value, int) or value < least:
            raise ValueError(f"{name} must be an integer >= {least}, got {value!r}")
    if not isinstance(x0, torch.Tensor) or not x0.is_floating_point():
        raise ValueError(f"x0 must be a floating-point tensor, got {getattr(x0, 'dtype', type(x0).__name__)}")
    if x0.shape != (d,) and x0.shape != (num_samples, d):
        raise ValueError(f"x0 must have shape [{d}] or [{num_samples}, {d}], got {list(x0.shape)}")
    return d


def rollout(
    system: System,
    policy: Policy | ActionSampler,
    x0: Tensor,
    num_samples: int,
    horizon: int,
    generator: torch.Generator | None = None,
) -> tuple[Tensor, Tensor]:
    """Sample ``num_samples`` trajectories of ``horizon`` steps from ``x0 [d]`` (or ``[N, d]``).

    Returns ``states [N, T+1, d]`` (start included) and ``actions [N, T, q]``, in the dtype and on the device
    of ``x0``; pass a seeded ``generator`` on that device for reproducible samples. No gradient flows through a
    rollout: an ``x0`` that requires grad is detached. A policy's ``action_probs`` must return ``[N, A]``.
    """
    d = _check_args(system, x0, num_samples, horizon)
    check_generator(generator, x0.device)
    x0 = x0.detach()
    table_horizon = getattr(policy, "horizon", None)
    if table_horizon is not None and horizon > table_horizon:
        raise ValueError(f"horizon {horizon} is longer than the policy's table ({table_horizon} steps)")
    policy_device = getattr(policy, "device", None)
    if policy_device is not None and not same_device(policy_device, x0.device):
        raise ValueError(f"x0 is on {x0.device} but the policy is on {policy_device}")
    if not bool(torch.isfinite(x0).all()):
        raise ValueError("x0 contains NaN or infinite values")
    nominal = getattr(policy, "nominal", None)  # noise samplers: an action sequence [T', q]
    if nominal is not None:
        if nominal.shape[0] < horizon:
            raise ValueError(f"the sampler's nominal sequence has {nominal.shape[0]} steps, fewer than horizon {horizon}")
        if nominal.dtype != x0.dtype or nominal.device != x0.device:
            raise ValueError(f"the sampler is {nominal.dtype} on {nominal.device} but x0 is {x0.dtype} on {x0.device}")
    discrete = not isinstance(policy, ActionSampler)
    if discrete and not isinstance(policy, Policy):
        raise ValueError(f"{type(policy).__name__} is neither a Policy (actions, action_probs) nor an ActionSampler (sample)")
    start = x0.unsqueeze(0).expand(num_samples, d) if x0.ndim == 1 else x0  # [N, d]
    relative = bool(getattr(policy, "start_relative", False)) and system.se2_invariant
    # in the start pose's frame the start is (0, 0, 0, *rest): the frame change leaves speeds etc. unchanged
    x = torch.cat((torch.zeros_like(start[:, :3]), start[:, 3:]), dim=1) if relative else start
    x = x.T.contiguous().T  # column-major [N, d]: every column a policy or a step reads is contiguous (faster)
    actions = policy.actions.to(dtype=x0.dtype) if discrete else None  # [A, q]
    planned = None
    if not discrete and hasattr(policy, "sample_sequences"):  # open-loop noise: draw it all at once
        planned = policy.sample_sequences(num_samples, horizon, generator)  # [N, T, q]
    states, taken = [x], []
    for t in range(horizon):
        if planned is not None:
            u = planned[:, t]
        elif discrete:
            probs = policy.action_probs(x, t)  # [N, A]
            if not isinstance(probs, Tensor) or probs.shape != (num_samples, actions.shape[0]):
                raise ValueError(f"{type(policy).__name__}.action_probs returned "
                                 f"{list(probs.shape) if isinstance(probs, Tensor) else type(probs).__name__} at step "
                                 f"{t}; expected [{num_samples}, {actions.shape[0]}] probabilities (states x actions)")
            u = actions[torch.multinomial(probs, 1, generator=generator).squeeze(1)]  # [N, q]
        else:
            u = policy.sample(x, t, generator)  # [N, q]
        x = system.step(x, u)
        if x.shape != (num_samples, d):
            raise ValueError(f"{getattr(system, 'name', type(system).__name__)}.step returned shape {list(x.shape)} "
                             f"for {num_samples} states of dimension {d}; expected [{num_samples}, {d}]")
        states.append(x)
        taken.append(u)
    if relative and (x0.ndim == 2 or bool(x0[:3].any())):  # the origin pose needs no change of frame
        # the column-major states stacked time-major ([T+1, d, N], one copy) and viewed as [N, T+1, d]: the frame
        # change reads contiguous runs and writes the [N, T+1, d] result once
        local = torch.stack([s.T for s in states]).permute(2, 0, 1)
        states_t = se2_to_world(local, x0 if x0.ndim == 1 else start.unsqueeze(1))
    else:
        states_t = torch.stack(states, dim=1)  # [N, T+1, d]
    q = policy.actions.shape[1] if hasattr(policy, "actions") else (nominal.shape[1] if nominal is not None else 0)
    if planned is not None:
        actions_t = planned  # [N, T, q]
    else:
        # stacked time-major, then one transposing copy: cheaper on a CPU than stacking [N, q] along dim 1
        actions_t = torch.stack(taken).transpose(0, 1).contiguous() if taken else x0.new_zeros((num_samples, 0, q))
    return states_t, actions_t
