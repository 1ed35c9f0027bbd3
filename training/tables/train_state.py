"""The distillation's training state (``<out>.train.pt``): written after every epoch, read back by ``--resume``."""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any

import torch

from cuniform_torch.common.fileio import write_bytes

__all__ = ["TRAIN_STATE_FORMAT", "RESUME_KEYS", "UsageError", "save_train_state", "load_train_state"]

TRAIN_STATE_FORMAT = "cuniform-distill-state/1"
# the settings a training state must share with the run that resumes it (the others change no weight)
RESUME_KEYS = ("hidden", "layers", "frequencies", "epochs", "lr", "batch_size", "seed", "jitter", "val_points",
               "patience")


class UsageError(ValueError):
    """A bad flag, an inconsistent set of tables, or a refused resume: reported as ``error: ...``, exit code 2."""


def save_train_state(path: Path, state: dict[str, Any]) -> None:
    """Write the training state atomically (a dict of plain types and tensors: ``weights_only`` loadable)."""
    buf = io.BytesIO()
    torch.save(state, buf)
    write_bytes(path, buf.getvalue())


def load_train_state(path: Path, fingerprint: dict[str, Any], fmt: str = TRAIN_STATE_FORMAT) -> dict[str, Any]:
    """The saved training state of format ``fmt``, after checking it belongs to this config and these inputs
    (:class:`UsageError`)."""
    if not path.exists():  # something there that is not a file is said by the reader
        raise UsageError(f"--resume: no training state at {path} (run without --resume first)")
    from cuniform_torch.policies.checkpoint import MAX_CHECKPOINT_BYTES, read_checkpoint_file

    state = read_checkpoint_file(path, UsageError, "training state (--resume)",  # the optimizer's moments: 3x
                                 max_bytes=4 * MAX_CHECKPOINT_BYTES)
    if not isinstance(state, dict) or state.get("format") != fmt:
        raise UsageError(f"--resume: {path} is not a training state of format {fmt!r}")
    saved = state.get("fingerprint", {})
    differ = [k for k in fingerprint if saved.get(k) != fingerprint[k]]
    if differ:
        detail = "; ".join(f"{k}: saved {saved.get(k)!r}, now {fingerprint[k]!r}" for k in differ)
        raise UsageError(f"--resume: {path} was written by a different run ({detail})")
    return state
