"""The distilled policy's checkpoint file: writing it, and reading it back without running any code it names.

Checkpoint (``.pt``, format ``cuniform-policy/1``): a dict of plain types and tensors that
``torch.load(path, weights_only=True)`` reads: ``format``, ``state_dict``, ``config``
(:class:`~cuniform_torch.policies.mlp.MLPConfig` as a dict), ``system`` (the table's system JSON), ``actions`` ``[A, q]``,
``source`` (the table's path and sha256) and ``metrics`` (free-form numbers from the distillation); optionally
``support`` (:class:`~cuniform_torch.policies.mlp.MLPSupport` as a dict: ``cells`` int64 ``[C, d]`` and
``level_offsets`` int64 ``[T+2]``, the cells per level it was trained on, as in a table file); and, for a
start-conditioned policy (:mod:`cuniform_torch.policies.start_mlp`, whose config has ``start_dims``), ``start_region``
(:class:`~cuniform_torch.policies.start_mlp.StartRegion` as a dict: ``starts`` float64 ``[S, k]``, the set's starts over
``dims [k]``). A checkpoint without ``start_region`` loads as an :class:`~cuniform_torch.policies.mlp.MLPPolicy`.

Integrity: :func:`save_policy` stores ``content_sha256``, the :func:`checkpoint_digest` of everything else in the
file (every tensor by its key path, the other values as JSON); a load from a path checks it before using any
value (a mismatch names the file; a file written before digests loads after a one-line note). Every tensor of
``state_dict`` must be finite and within :data:`MAX_ABS_WEIGHT`, and the config's sizes within the limits of
:mod:`cuniform_torch.policies.mlp` (checked before any network is built).
"""

from __future__ import annotations

import hashlib
import io
import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from cuniform_torch.common.digest import DIGEST_KEY, DigestError, check_digest, content_digest
from cuniform_torch.common.fileio import open_regular, write_bytes
from cuniform_torch.grid.cells import Grid
from cuniform_torch.policies.mlp import MLPConfig, MLPPolicy, MLPSupport
from cuniform_torch.policies.start_mlp import StartMLPPolicy, StartRegion
from cuniform_torch.policies.table import Fallback
from cuniform_torch.systems import system_from_json

__all__ = ["POLICY_FORMAT", "PolicyCheckpointError", "policy_checkpoint", "save_policy", "load_policy", "file_sha256",
           "read_network_keys", "checkpoint_digest", "check_checkpoint_digest", "MAX_ABS_WEIGHT",
           "MAX_CHECKPOINT_BYTES", "read_checkpoint_file"]

POLICY_FORMAT = "cuniform-policy/1"

MAX_ABS_WEIGHT = 1e6
"""the largest magnitude a ``state_dict`` value may have: a trained network's weights are of order 1 (and its
buffers, the actions and ``1 / feature_scale``, of the system's scale), while weights of 1e38 overflow float32
activations into NaN probabilities; such a checkpoint is refused by name instead"""


MAX_CHECKPOINT_BYTES = 8 * (1 << 26) + (64 << 20)
"""the largest checkpoint file a loader reads (576 MiB): the networks' weight limits (2^26 values, of at most 8
bytes) and room for the rest; a larger file is refused from its size, before ``torch.load`` reads it"""


class PolicyCheckpointError(ValueError):
    """A policy checkpoint that is missing, corrupt, of an unknown format, or does not match its network."""


def read_checkpoint_file(path: Path, error: type[Exception], what: str,
                         max_bytes: int = MAX_CHECKPOINT_BYTES) -> Any:
    """``torch.load(weights_only=True)`` of the regular file ``path`` (never a FIFO or a device: an ``error``),
    refused from its size, before it is read, over ``max_bytes``; ``error`` when it does not load."""
    try:
        fh = open_regular(path, what)
    except (OSError, ValueError) as exc:
        raise error(f"{path}: not a readable {what} ({exc})") from None
    with fh:
        size = os.fstat(fh.fileno()).st_size
        if size > max_bytes:
            raise error(f"{path}: {size} bytes, over the {max_bytes} bytes any {what} this package writes can hold; "
                        "is it the right file?")
        try:
            return torch.load(fh, map_location="cpu", weights_only=True)
        except Exception as exc:  # corrupt, truncated, or holding objects that need arbitrary unpickling
            raise error(f"{path}: not a readable {what} ({type(exc).__name__}: {str(exc)[:200]})") from None


def file_sha256(path: str | os.PathLike) -> str:
    digest = hashlib.sha256()
    with open_regular(path) as fh:
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
        **({"support": policy.support.to_dict()} if policy.support is not None else {}),
        **({"start_region": policy.region.to_dict()} if isinstance(policy, StartMLPPolicy) else {}),
    }


def _checkpoint_arrays(checkpoint: dict[str, Any]) -> dict[str, Any]:
    """What a checkpoint's digest covers: every tensor, nested dicts included, by its key path
    (``"state_dict/net.0.weight"``), and every other value in one JSON text (sorted keys), all but the
    :data:`~cuniform_torch.common.digest.DIGEST_KEY` entry. ValueError for content that has no digest
    (a key that is not a string, values JSON cannot write)."""
    arrays: dict[str, Any] = {}
    plain: dict[str, Any] = {}

    def walk(prefix: str, value: dict) -> None:
        for key, item in value.items():
            if not isinstance(key, str):
                raise ValueError(f"key {key!r} of {prefix or 'the checkpoint'} is not a string")
            if not prefix and key == DIGEST_KEY:
                continue
            name = f"{prefix}/{key}" if prefix else key
            if isinstance(item, dict):
                walk(name, item)
            elif isinstance(item, Tensor) and item.layout != torch.strided:  # sparse: no bytes to digest
                raise ValueError(f"tensor {name!r} is {item.layout}, not a dense tensor")
            else:
                (arrays if isinstance(item, Tensor) else plain)[name] = item

    walk("", checkpoint)
    try:
        text = json.dumps(plain, sort_keys=True)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"a value JSON cannot write ({exc})") from None
    if "\0plain" in arrays:
        raise ValueError("a tensor's key path is '\\0plain', the name of the JSON part")
    return {**arrays, "\0plain": np.array(text)}


def checkpoint_digest(checkpoint: dict[str, Any]) -> str:
    """The content digest (:func:`~cuniform_torch.common.digest.content_digest`) of a checkpoint dict: its
    tensors by key path and its other values as JSON (see :func:`save_policy`)."""
    return content_digest(_checkpoint_arrays(checkpoint))


def check_checkpoint_digest(checkpoint: dict[str, Any], where: str, error: type[Exception]) -> None:
    """Check a checkpoint read from the file ``where`` against its stored ``content_sha256``, before any value is
    used: ``error`` (the family's exception) with the digest's message, naming the file, on a mismatch or on
    content that has no digest; a one-line note on stderr (once per file) when the file has none (written
    before digests were recorded)."""
    stored = checkpoint.get(DIGEST_KEY)
    try:
        check_digest({} if stored is None else _checkpoint_arrays(checkpoint), stored, where)
    except DigestError as exc:
        raise error(str(exc)) from None
    except ValueError as exc:
        raise error(f"{where}: its content has no digest: {exc}") from None


def save_policy(path: str | os.PathLike, checkpoint: dict[str, Any]) -> None:
    """Write a checkpoint dict atomically, with its ``content_sha256`` (:func:`checkpoint_digest`)."""
    buf = io.BytesIO()
    torch.save({**checkpoint, DIGEST_KEY: checkpoint_digest(checkpoint)}, buf)
    write_bytes(path, buf.getvalue())


def read_network_keys(ckpt: dict, config_class: type, what: str, trust_factory: Any,
                      fail: Callable[[str], None]) -> tuple[dict[str, Tensor], Any, Any]:
    """The checks every policy checkpoint shares: ``state_dict`` (names -> finite float tensors), ``config`` (a dict
    that builds ``config_class``, else "config does not describe {what}"), ``system`` (rebuilt from the registry or
    ``trust_factory``; its horizon and periodic dimensions agree with the config). Returns (state, config, system);
    each problem is one ``fail(message)``."""
    state = ckpt["state_dict"]
    if not isinstance(state, dict) or not all(isinstance(k, str) and isinstance(v, Tensor) for k, v in state.items()):
        fail("state_dict must map names to tensors")
    for key, value in state.items():
        if not value.is_floating_point() or not bool(torch.isfinite(value).all()):
            fail(f"state_dict[{key!r}] holds non-finite or non-float values")
        if value.numel() and float(value.abs().max()) > MAX_ABS_WEIGHT:
            fail(f"state_dict[{key!r}] holds a value of magnitude {float(value.abs().max()):.3g}, beyond the "
                 f"bound {MAX_ABS_WEIGHT:g} of a sane network (a damaged or diverged checkpoint)")
    if not isinstance(ckpt["config"], dict):
        fail(f"config must be a dict, got {type(ckpt['config']).__name__}")
    try:
        config = config_class(**ckpt["config"])
    except (TypeError, ValueError) as exc:
        fail(f"config does not describe {what} ({exc})")
    try:
        system, horizon = system_from_json(ckpt["system"], trust_factory=trust_factory)
    except ValueError as exc:  # includes UnknownSystemError
        fail(f"the system cannot be rebuilt: {exc}")
    if config.horizon != horizon:
        fail(f"config.horizon is {config.horizon} but the system JSON says {horizon}")
    if list(config.periodic) != list(system.periodic):
        fail(f"config.periodic {list(config.periodic)} does not match the system's {list(system.periodic)}")
    return state, config, system


def load_policy(source: str | os.PathLike | dict, device: torch.device | str = "cpu", *,
                trust_factory: str | Callable[..., Any] | None = None,
                fallback: str | Fallback = Fallback.NEAREST) -> MLPPolicy:
    """A ready :class:`MLPPolicy` from a checkpoint path or an already loaded dict; errors are clear.

    The file is read with ``torch.load(weights_only=True)`` and its system is rebuilt from the registry or from
    ``trust_factory`` (see :func:`~cuniform_torch.systems.system_from_json`): nothing it names is imported. A file's
    ``content_sha256`` is checked first (module docstring; a dict is checked for its structure only). Every
    field has one source of truth, checked against the others: the actions (system, top level, state_dict),
    the feature scales (config, state_dict), the horizon and angle dimensions (config, system); weights must
    be finite and within :data:`MAX_ABS_WEIGHT`, the config within the limits of
    :mod:`~cuniform_torch.policies.mlp`, and the network may not be larger than the weights the file holds. An optional ``support`` dict
    (``cells``, ``level_offsets``: :class:`MLPSupport`) must describe cells per level of the system's grid.
    """
    where = str(source) if not isinstance(source, dict) else "checkpoint dict"
    if isinstance(source, dict):
        ckpt = source
    else:
        path = Path(source)
        if not path.is_file():
            raise PolicyCheckpointError(f"{path}: no checkpoint file there")
        ckpt = read_checkpoint_file(path, PolicyCheckpointError, "policy checkpoint")

    def fail(msg: str) -> None:
        raise PolicyCheckpointError(f"{where}: {msg}")

    if not isinstance(ckpt, dict):
        fail(f"a checkpoint must be a dict, got {type(ckpt).__name__}")
    fmt = ckpt.get("format")
    if fmt != POLICY_FORMAT:
        fail(f"unknown policy format {fmt!r}; this reader knows {POLICY_FORMAT!r}")
    if not isinstance(source, dict):  # a file's integrity; a dict in memory is the caller's
        check_checkpoint_digest(ckpt, where, PolicyCheckpointError)
    missing = [k for k in ("state_dict", "config", "system", "actions") if k not in ckpt]
    if missing:
        fail(f"missing key(s) {', '.join(missing)}")
    state, config, system = read_network_keys(ckpt, MLPConfig, "a policy", trust_factory, fail)
    region = _read_region(ckpt.get("start_region"), config, system, fail)  # before the sizes: it explains them
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
    support = _read_support(ckpt.get("support"), Grid.of(system), config.horizon, fail)
    try:
        if region is None:
            policy = MLPPolicy(config, system, actions, support=support, fallback=fallback)
        else:
            policy = StartMLPPolicy(config, system, actions, region, support=support, fallback=fallback)
        policy.load_state_dict(state, strict=True)
    except (RuntimeError, TypeError, ValueError, AttributeError) as exc:
        fail(f"state_dict does not match the network of its config ({str(exc)[:300]})")
    return policy.to(device).eval()


def _read_support(value: Any, grid: Grid, horizon: int, fail: Callable[[str], None]) -> MLPSupport | None:
    """The checkpoint's optional ``support`` (None when absent); ``fail`` names what is wrong with it."""
    if value is None:
        return None
    if not isinstance(value, dict) or set(value) != {"cells", "level_offsets"}:
        fail(f"support must be a dict of cells and level_offsets, got "
             f"{sorted(value) if isinstance(value, dict) else type(value).__name__}")
    support = MLPSupport(value["cells"], value["level_offsets"])
    try:
        support.check(grid, horizon)
    except ValueError as exc:
        fail(str(exc))
    return support


def _read_region(value: Any, config: MLPConfig, system: Any, fail: Callable[[str], None]) -> StartRegion | None:
    """The checkpoint's optional ``start_region`` (None when absent, as for a pi(u | x, t) policy); it and
    ``config.start_dims`` come together or not at all."""
    if value is None:
        if config.start_dims:
            fail(f"config.start_dims is {config.start_dims} but the checkpoint has no start_region")
        return None
    if not isinstance(value, dict) or set(value) != {"starts", "dims"}:
        fail(f"start_region must be a dict of starts and dims, got "
             f"{sorted(value) if isinstance(value, dict) else type(value).__name__}")
    dims = value["dims"]
    if not isinstance(dims, list) or dims != list(config.start_dims):
        fail(f"start_region dims {dims!r} differ from config.start_dims {config.start_dims}")
    region = StartRegion(value["starts"], dims)
    try:
        region.check(system)
    except ValueError as exc:
        fail(str(exc))
    return region
