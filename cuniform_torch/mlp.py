"""The distilled policy: a small MLP pi(u | x, t) with the Policy interface, and its checkpoint file.

Shapes: N states, d state dimensions, F input features, A actions, q action dimensions, T horizon.

Input features of a state ``x`` at step ``t`` (documented scales, settled from the table at distillation):

* every non-periodic dimension i: ``x_i / scale_i`` (``scale_i`` = the largest |cell centre| of the table in
  that dimension, so features lie in about [-1, 1]);
* every angle dimension: ``cos x_i`` and ``sin x_i``;
* the time ``t / T``.

For Dubins that is ``(x / sx, y / sy, cos theta, sin theta, t / T)``. The network is ``layers`` hidden layers of
``hidden`` units with SiLU activations, then a linear layer to A logits; ``action_probs`` is their softmax.

Checkpoint (``.pt``, format ``cuniform-policy/1``): a dict of plain types and tensors that
``torch.load(path, weights_only=True)`` reads: ``format``, ``state_dict``, ``config`` (this module's
:class:`MLPConfig` as a dict), ``system`` (the table's system JSON), ``actions`` ``[A, q]``, ``source`` (the
table's path and sha256) and ``metrics`` (free-form numbers from the distillation).
"""

from __future__ import annotations

import dataclasses
import hashlib
import io
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import torch
from torch import Tensor, nn

from .fileio import write_bytes
from .grid import Grid
from .rollout import check_states
from .systems import System, system_from_json

__all__ = ["POLICY_FORMAT", "MLPConfig", "MLPPolicy", "PolicyCheckpointError", "policy_checkpoint", "save_policy",
           "load_policy", "file_sha256", "default_feature_scale"]

POLICY_FORMAT = "cuniform-policy/1"

MAX_HIDDEN = 1 << 16
MAX_LAYERS = 64


class PolicyCheckpointError(ValueError):
    """A policy checkpoint that is missing, corrupt, of an unknown format, or does not match its network."""


@dataclass
class MLPConfig:
    """Sizes and input features of an :class:`MLPPolicy` (stored in the checkpoint as a plain dict)."""

    state_dim: int
    num_actions: int
    horizon: int
    periodic: list[bool]
    feature_scale: list[float]
    """divisor of each non-periodic dimension (ignored on angle dimensions)"""
    hidden: int = 256
    layers: int = 3

    def __post_init__(self) -> None:
        for name in ("state_dim", "num_actions", "horizon", "hidden", "layers"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"MLPConfig.{name} must be a positive integer, got {value!r}")
        if self.hidden > MAX_HIDDEN or self.layers > MAX_LAYERS:
            raise ValueError(f"MLPConfig: at most {MAX_LAYERS} layers of {MAX_HIDDEN} units, got {self.layers} x {self.hidden}")
        if not isinstance(self.periodic, (list, tuple)) or not all(isinstance(p, bool) for p in self.periodic):
            raise ValueError(f"MLPConfig: periodic must be a list of bools, got {self.periodic!r}")
        if not isinstance(self.feature_scale, (list, tuple)) or len(self.periodic) != self.state_dim \
                or len(self.feature_scale) != self.state_dim:
            raise ValueError(f"MLPConfig: periodic and feature_scale need {self.state_dim} entries each")
        if any(isinstance(s, bool) or not isinstance(s, (int, float)) or not (0 < s < math.inf)
               for s in self.feature_scale):
            raise ValueError(f"MLPConfig: feature_scale must be positive finite numbers, got {self.feature_scale}")

    @property
    def num_features(self) -> int:
        return sum(2 if p else 1 for p in self.periodic) + 1

    @property
    def num_weights(self) -> int:
        """Weights and biases of the network this config describes."""
        width, total = self.num_features, 0
        for _ in range(self.layers):
            total += (width + 1) * self.hidden
            width = self.hidden
        return total + (width + 1) * self.num_actions

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


class MLPPolicy(nn.Module):
    """pi(u | x, t): ``action_probs(x [N, d], t) -> [N, A]``; works in ``rollout`` and every controller."""

    start_relative = True
    """like a table, it is trained on states relative to the start pose (SE(2)-invariant systems)"""

    def __init__(self, config: MLPConfig, system: System, actions: Tensor):
        super().__init__()
        if actions.ndim != 2 or actions.shape[0] != config.num_actions:
            raise ValueError(f"actions must be [{config.num_actions}, q], got {list(actions.shape)}")
        if len(system.periodic) != config.state_dim:
            raise ValueError(f"system {system.name} has {len(system.periodic)} state dims, config says {config.state_dim}")
        self.config = config
        self.system = system
        self.horizon = config.horizon
        self.register_buffer("actions", actions.detach().clone().float())  # [A, q]
        scale = torch.tensor(config.feature_scale, dtype=torch.float32)
        self.register_buffer("inv_scale", 1.0 / scale)  # [d]
        self._angle = [i for i, p in enumerate(config.periodic) if p]
        self._linear = [i for i, p in enumerate(config.periodic) if not p]
        layers: list[nn.Module] = []
        width = config.num_features
        for _ in range(config.layers):
            layers += [nn.Linear(width, config.hidden), nn.SiLU()]
            width = config.hidden
        layers.append(nn.Linear(width, config.num_actions))
        self.net = nn.Sequential(*layers)

    @property
    def device(self) -> torch.device:
        return self.actions.device

    @property
    def dtype(self) -> torch.dtype:
        return self.actions.dtype

    def features(self, x: Tensor, t: int | Tensor) -> Tensor:
        """``x [N, d]``, ``t`` (int or ``[N]``) -> ``[N, F]`` network inputs (see the module docstring)."""
        check_states(x, self.config.state_dim, self.device)
        x = x.to(self.dtype)
        parts = [x[:, self._linear] * self.inv_scale[self._linear]]
        if self._angle:
            ang = x[:, self._angle]
            parts += [torch.cos(ang), torch.sin(ang)]
        tt = torch.as_tensor(t, dtype=x.dtype, device=x.device)
        parts.append((tt / self.config.horizon).expand(x.shape[0]).unsqueeze(1) if tt.ndim == 0 else (tt / self.config.horizon).unsqueeze(1))
        return torch.cat(parts, dim=1)

    def forward(self, x: Tensor, t: int | Tensor) -> Tensor:
        """Logits ``[N, A]``."""
        return self.net(self.features(x, t))

    def action_probs(self, x: Tensor, t: int) -> Tensor:
        """Softmax of the logits: ``x [N, d]`` at level ``t`` -> ``[N, A]``, checked as a TablePolicy checks.

        ``t`` must be an int in ``0..horizon`` and ``x`` of the policy's dtype and device (ValueError otherwise;
        no silent conversion). A state with a NaN or infinite coordinate gets the uniform row, as a table's
        "not found" state does, and is counted in :attr:`misses`; ``queries`` counts every state looked up.
        """
        if isinstance(t, bool) or not isinstance(t, int) or not 0 <= t <= self.horizon:
            raise ValueError(f"level t={t!r} is outside the policy's levels 0..{self.horizon} (an integer)")
        check_states(x, self.config.state_dim, self.device)
        if x.dtype != self.dtype:
            raise ValueError(f"states are {x.dtype} but the policy is {self.dtype}")
        with torch.no_grad():
            probs = torch.softmax(self(x, t), dim=1)  # [N, A]
            bad = ~torch.isfinite(x).all(dim=1, keepdim=True)  # [N, 1]: cos(inf) and NaN give NaN logits
            self._count_misses(x.shape[0], bad)
            return torch.where(bad, torch.full_like(probs[:1], 1.0 / probs.shape[1]), probs)

    def _count_misses(self, n: int, bad: Tensor) -> None:
        """Add ``n`` queries and the ``bad [N, 1]`` rows to the counters (a device tensor: counting never syncs)."""
        misses = getattr(self, "_misses", None)
        if misses is None or misses.device != bad.device:  # not a buffer: counters stay out of the checkpoint
            self._misses, self._queries = torch.zeros((), dtype=torch.int64, device=bad.device), 0
        self._queries += n
        self._misses += bad.sum()

    @property
    def queries(self) -> int:
        """States looked up by :meth:`action_probs` so far (a host int)."""
        return getattr(self, "_queries", 0)

    @property
    def misses(self) -> Tensor:
        """States given the uniform row by :meth:`action_probs` (NaN or infinite ones; a 0-d device tensor)."""
        misses = getattr(self, "_misses", None)
        return misses.clone() if misses is not None else torch.zeros((), dtype=torch.int64, device=self.device)


def file_sha256(path: str | os.PathLike) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def policy_checkpoint(policy: MLPPolicy, system_json: str, source: dict[str, str] | None = None,
                      metrics: dict[str, Any] | None = None) -> dict[str, Any]:
    """The checkpoint dict of DESIGN.md (plain types and CPU tensors; ``weights_only`` loadable)."""
    return {
        "format": POLICY_FORMAT,
        "state_dict": {k: v.detach().cpu() for k, v in policy.state_dict().items()},
        "config": policy.config.to_dict(),
        "system": system_json,
        "actions": policy.actions.detach().cpu(),
        "source": dict(source or {}),
        "metrics": dict(metrics or {}),
    }


def save_policy(path: str | os.PathLike, checkpoint: dict[str, Any]) -> None:
    """Write a checkpoint dict atomically."""
    buf = io.BytesIO()
    torch.save(checkpoint, buf)
    write_bytes(path, buf.getvalue())


def load_policy(source: str | os.PathLike | dict, device: torch.device | str = "cpu", *,
                trust_factory: str | Callable[..., Any] | None = None) -> MLPPolicy:
    """A ready :class:`MLPPolicy` from a checkpoint path or an already loaded dict; errors are clear.

    The file is read with ``torch.load(weights_only=True)`` and its system is rebuilt from the registry or from
    ``trust_factory`` (see :func:`~cuniform_torch.systems.system_from_json`): nothing it names is imported. Every
    field has one source of truth, checked against the others: the actions (system, top level, state_dict),
    the feature scales (config, state_dict), the horizon and angle dimensions (config, system); weights must
    be finite, and the network may not be larger than the weights the file holds.
    """
    where = str(source) if not isinstance(source, dict) else "checkpoint dict"
    if isinstance(source, dict):
        ckpt = source
    else:
        path = Path(source)
        if not path.is_file():
            raise PolicyCheckpointError(f"{path}: no checkpoint file there")
        try:
            ckpt = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as exc:  # corrupt, truncated, or holding objects that need arbitrary unpickling
            raise PolicyCheckpointError(f"{path}: not a readable policy checkpoint ({type(exc).__name__}: {exc})") from None

    def fail(msg: str) -> None:
        raise PolicyCheckpointError(f"{where}: {msg}")

    if not isinstance(ckpt, dict):
        fail(f"a checkpoint must be a dict, got {type(ckpt).__name__}")
    fmt = ckpt.get("format")
    if fmt != POLICY_FORMAT:
        fail(f"unknown policy format {fmt!r}; this reader knows {POLICY_FORMAT!r}")
    missing = [k for k in ("state_dict", "config", "system", "actions") if k not in ckpt]
    if missing:
        fail(f"missing key(s) {', '.join(missing)}")
    state = ckpt["state_dict"]
    if not isinstance(state, dict) or not all(isinstance(k, str) and isinstance(v, Tensor) for k, v in state.items()):
        fail("state_dict must map names to tensors")
    for key, value in state.items():
        if not value.is_floating_point() or not bool(torch.isfinite(value).all()):
            fail(f"state_dict[{key!r}] holds non-finite or non-float values")
    if not isinstance(ckpt["config"], dict):
        fail(f"config must be a dict, got {type(ckpt['config']).__name__}")
    try:
        config = MLPConfig(**ckpt["config"])
    except (TypeError, ValueError) as exc:
        fail(f"config does not describe a policy ({exc})")
    try:
        system, horizon = system_from_json(ckpt["system"], trust_factory=trust_factory)
    except ValueError as exc:  # includes UnknownSystemError
        fail(f"the system cannot be rebuilt: {exc}")
    if config.horizon != horizon:
        fail(f"config.horizon is {config.horizon} but the system JSON says {horizon}")
    if list(config.periodic) != list(system.periodic):
        fail(f"config.periodic {list(config.periodic)} does not match the system's {list(system.periodic)}")
    held = sum(v.numel() for k, v in state.items() if k.startswith("net."))
    if config.num_weights != held:
        fail(f"state_dict does not match the network of its config ({config.num_weights} weights described, "
             f"{held} held)")
    actions = ckpt["actions"]
    expect = system.action_set(dtype=torch.float32)
    for field_name, value in (("actions", actions), ("state_dict['actions']", state.get("actions"))):
        if not isinstance(value, Tensor) or value.shape != expect.shape or not torch.allclose(expect, value.float(), atol=1e-6):
            fail(f"{field_name} does not match the actions of the system {system.name!r}")
    inv_scale = state.get("inv_scale")
    expect_inv = 1.0 / torch.tensor(config.feature_scale, dtype=torch.float32)
    if not isinstance(inv_scale, Tensor) or inv_scale.shape != expect_inv.shape or not torch.equal(inv_scale.float(), expect_inv):
        fail("state_dict['inv_scale'] does not match config.feature_scale")
    try:
        policy = MLPPolicy(config, system, actions)
        policy.load_state_dict(state, strict=True)
    except (RuntimeError, TypeError, ValueError, AttributeError) as exc:
        fail(f"state_dict does not match the network of its config ({str(exc)[:300]})")
    return policy.to(device).eval()


def default_feature_scale(cells_centres: Tensor, grid: Grid) -> list[float]:
    """``max |centre|`` per non-periodic dimension (1.0 where that is 0, and on angle dimensions)."""
    scale = cells_centres.abs().amax(dim=0).tolist()
    return [1.0 if (p or s == 0) else float(s) for s, p in zip(scale, grid.periodic)]
