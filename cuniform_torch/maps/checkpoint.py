"""The map-conditioned policy's checkpoint file (format ``cuniform-map-policy/1``): written atomically, read with
``torch.load(weights_only=True)``, every key checked.

Keys (nothing else is accepted): ``format``; ``state_dict`` (name -> finite float tensor, exactly the network's);
``config`` (:class:`~cuniform_torch.maps.policy.MapPolicyConfig` as a dict, patch spec included; ``local_features``
only when > 0, so files written before it read as 0); ``system`` (the data set's system JSON); ``actions``
``[A, q]`` (the system's); ``source`` (str -> str: the data sets and their digests); ``metrics`` (str -> number
or string: the training's); and ``content_sha256`` (the file's content digest, written by
:func:`save_map_policy`; absent from files written before digests, which load after a one-line note).

Integrity and limits as for the MLP policy's checkpoint (:mod:`cuniform_torch.policies.checkpoint`): a load from a
path checks the digest before using any value; ``state_dict`` values must be finite and within
:data:`~cuniform_torch.policies.checkpoint.MAX_ABS_WEIGHT`; the config must be within the limits of
:mod:`cuniform_torch.maps.policy` (parameters, feature maps), checked before the network is built.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from cuniform_torch.common.digest import DIGEST_KEY
from cuniform_torch.maps.policy import MapPolicy, MapPolicyConfig
from cuniform_torch.maps.pretrained import pretrained_names, pretrained_path
from cuniform_torch.policies.checkpoint import (
    check_checkpoint_digest,
    read_checkpoint_file,
    read_network_keys,
    save_policy,
)

__all__ = ["MAP_POLICY_FORMAT", "MapCheckpointError", "map_policy_checkpoint", "save_map_policy", "load_map_policy"]

MAP_POLICY_FORMAT = "cuniform-map-policy/1"
_KEYS = {"format", "state_dict", "config", "system", "actions", "source", "metrics"}


class MapCheckpointError(ValueError):
    """A map-policy checkpoint that is missing, corrupt, of an unknown format, or does not match its network."""


def map_policy_checkpoint(policy: MapPolicy, system_json: str, source: dict[str, str] | None = None,
                          metrics: dict[str, Any] | None = None) -> dict[str, Any]:
    """The checkpoint dict (plain types and CPU tensors; ``weights_only`` loadable)."""
    return {
        "format": MAP_POLICY_FORMAT,
        "state_dict": {k: v.detach().cpu() for k, v in policy.state_dict().items()},
        "config": policy.config.to_dict(),
        "system": system_json,
        "actions": policy.actions.detach().cpu(),
        "source": dict(source or {}),
        "metrics": dict(metrics or {}),
    }


def save_map_policy(path: str | os.PathLike, checkpoint: dict[str, Any]) -> None:
    """Write a checkpoint dict atomically, with its ``content_sha256`` (as
    :func:`~cuniform_torch.policies.checkpoint.save_policy` does)."""
    save_policy(path, checkpoint)


def load_map_policy(source: str | os.PathLike | dict, device: torch.device | str = "cpu", *,
                    trust_factory: str | Callable[..., Any] | None = None) -> MapPolicy:
    """A ready :class:`MapPolicy` (eval mode, on ``device``, no map set) from a path, a loaded dict, or the name
    of a shipped policy (:mod:`cuniform_torch.maps.pretrained`, e.g. ``"unicycle-0.5"``);
    :class:`MapCheckpointError` naming the first key that is wrong. A file's ``content_sha256`` is checked first
    (a dict is checked for its structure only)."""
    if isinstance(source, str) and not Path(source).exists() and source in pretrained_names():
        source = pretrained_path(source)  # a shipped policy by name, checked against its model card
    where = "checkpoint dict" if isinstance(source, dict) else str(source)
    if isinstance(source, dict):
        ckpt = source
    else:
        path = Path(source)
        if not path.is_file():
            raise MapCheckpointError(f"{path}: no checkpoint file there")
        ckpt = read_checkpoint_file(path, MapCheckpointError, "map-policy checkpoint")

    def fail(msg: str) -> None:
        raise MapCheckpointError(f"{where}: {msg}")

    if not isinstance(ckpt, dict):
        fail(f"a checkpoint must be a dict, got {type(ckpt).__name__}")
    if ckpt.get("format") != MAP_POLICY_FORMAT:
        fail(f"unknown format {ckpt.get('format')!r}; this reader knows {MAP_POLICY_FORMAT!r}")
    if not isinstance(source, dict):  # a file's integrity; a dict in memory is the caller's
        check_checkpoint_digest(ckpt, where, MapCheckpointError)
    if set(ckpt) - {DIGEST_KEY} != _KEYS:
        missing, extra = sorted(_KEYS - set(ckpt)), sorted(set(ckpt) - _KEYS - {DIGEST_KEY})
        fail("; ".join(([f"missing key(s) {', '.join(missing)}"] if missing else [])
                       + ([f"unknown key(s) {', '.join(map(str, extra))}"] if extra else [])))
    state, config, system = read_network_keys(ckpt, MapPolicyConfig, "a map policy", trust_factory, fail)
    expect = system.action_set(dtype=torch.float32)
    for name, value in (("actions", ckpt["actions"]), ("state_dict['actions']", state.get("actions"))):
        if not isinstance(value, Tensor) or value.shape != expect.shape or not torch.allclose(expect, value.float(),
                                                                                              atol=1e-6):
            fail(f"{name} does not match the actions of the system {system.name!r}")
    inv_scale = state.get("inv_scale")
    expect_inv = 1.0 / torch.tensor(config.feature_scale, dtype=torch.float32)
    if not isinstance(inv_scale, Tensor) or inv_scale.shape != expect_inv.shape \
            or not torch.equal(inv_scale.float(), expect_inv):
        fail("state_dict['inv_scale'] does not match config.feature_scale")
    for name in ("source", "metrics"):
        value = ckpt[name]
        if not isinstance(value, dict) or not all(isinstance(k, str) for k in value):
            fail(f"{name} must be a dict with string keys")
    if not all(isinstance(v, str) for v in ckpt["source"].values()):
        fail("source values must be strings")
    if not all(isinstance(v, str) or (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v))
               for v in ckpt["metrics"].values()):
        fail("metrics values must be finite numbers or strings")
    try:
        policy = MapPolicy(config, system, ckpt["actions"])
        policy.load_state_dict(state, strict=True)
    except (RuntimeError, TypeError, ValueError) as exc:
        fail(f"state_dict does not match the network of its config ({str(exc)[:300]})")
    return policy.to(device).eval()
