"""The device and tensor checks that rollouts, policies, samplers and controllers share: whether two devices are
one, states ``[N, d]`` on a device, a generator on a device. Each raises one ValueError (or TypeError) naming
the problem. This module imports no other module of the package.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["same_device", "check_states", "check_generator"]


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
