"""The library's training jobs as typed functions: ``from training import DistillConfig, distill_policy``.

* :func:`distill_policy`: tables (or one table-set folder) -> a distilled MLP policy, checkpointed;
* :func:`train_map_policy`: map-table data sets -> a map-conditioned policy, checkpointed.

``python -m training.distill`` and ``python -m training.maps.distill`` are shells over these: they parse their
flags into the same configs and call them with ``progress=True``. From Python the progress bars are off by
default, nothing calls ``sys.exit``, and a bad setting is one ``ValueError`` naming the field by its flag.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import TYPE_CHECKING, Any

from precompute.cli import CLIError
from training.maps.distill import MapDistillConfig, check_map_config, distill_maps
from training.tables.config import DistillConfig

if TYPE_CHECKING:
    from cuniform_torch.maps.policy import MapPolicy

__all__ = ["DistillConfig", "MapDistillConfig", "distill_policy", "train_map_policy"]


def _library_errors(run: Any) -> Any:
    """``run()`` with the command layer's :class:`CLIError` (an unwritable output, a held lock) as ValueError."""
    try:
        return run()
    except CLIError as exc:
        raise ValueError(str(exc)) from None


def distill_policy(config: DistillConfig, *, progress: bool = False) -> Any:
    """Distil ``config.tables`` into an MLP (module :mod:`training.distill`): pi(u | x, t) from table files, or
    the start-conditioned pi(u | x, t, x0) from one table-set folder. Writes the checkpoint ``config.out``
    (default ``out/<first table stem>.policy.pt``) atomically, its training state and comparison JSON beside it,
    and a TensorBoard run under ``config.logdir``. ``progress``: the epoch bar (``config.quiet=True`` keeps it off).

    :return: the trained policy, read back from its checkpoint (:func:`cuniform_torch.load_policy`)
    """
    from cuniform_torch.policies.checkpoint import load_policy
    from training.distill import check_config, distill

    if not isinstance(config, DistillConfig):
        raise ValueError(f"config must be a DistillConfig, got {type(config).__name__}")
    cfg = dataclasses.replace(config, quiet=config.quiet or not progress)

    def run() -> str:
        checked = check_config(dataclasses.replace(cfg, tables=[str(t) for t in cfg.tables]))  # out filled
        distill(checked)
        assert checked.out is not None
        return checked.out

    if not cfg.tables:
        raise ValueError("DistillConfig.tables is empty: give table files, or one table-set folder")
    out = _library_errors(run)
    return load_policy(out, device=cfg.device)


def train_map_policy(config: MapDistillConfig, *, progress: bool = False) -> MapPolicy:
    """Train a map-conditioned policy on ``config.maps`` (map-table data sets, :mod:`training.maps.distill`).
    Writes the checkpoint ``config.out`` (default ``out/<first data set>.map_policy.pt``) atomically, the
    training state beside it and a TensorBoard run under ``config.logdir``. ``progress``: the epoch bar and the
    summary lines (``config.quiet=True`` keeps them off).

    :return: the trained policy, read back from its checkpoint (:func:`cuniform_torch.maps.load_map_policy`)
    """
    from cuniform_torch.maps.checkpoint import load_map_policy

    if not isinstance(config, MapDistillConfig):
        raise ValueError(f"config must be a MapDistillConfig, got {type(config).__name__}")
    cfg = dataclasses.replace(config, quiet=config.quiet or not progress)

    def run() -> str:
        checked = check_map_config(cfg)
        distill_maps(checked)
        assert checked.out is not None
        return checked.out

    out = _library_errors(run)
    return load_map_policy(Path(out), device=cfg.device)
