"""Content digests of the arrays and tensors a file holds: the integrity check of every file the project writes.

A digest is the sha256 of the named arrays in sorted name order; each array contributes its name, its dtype
string, its shape and its C-order bytes, so a flipped byte, a reshaped array, a renamed key or a changed dtype
all change it. It is computed from the arrays (not the file's bytes), so the same content written through
another zip or pickle layout keeps its digest, and a reader can check it after parsing, before using a value.

Writers store the hex digest beside the arrays (``content_sha256``); readers call :func:`check_digest`, which
raises :class:`DigestError` naming the file on a mismatch and returns ``False`` (after a one-line note on
stderr, once per file) when an old file has none.
"""

from __future__ import annotations

import hashlib
import sys
from collections.abc import Mapping
from typing import Any

import numpy as np

__all__ = ["DIGEST_KEY", "DigestError", "content_digest", "check_digest"]

DIGEST_KEY = "content_sha256"
"""the key under which a file stores the digest of its other arrays"""

_NOTED: set[str] = set()


class DigestError(ValueError):
    """A file's content does not match the digest stored in it (a damaged or edited file)."""


def _as_numpy(value: Any) -> np.ndarray:
    if hasattr(value, "detach"):  # a torch tensor, without importing torch here
        value = value.detach().cpu()
        if str(value.dtype) == "torch.bfloat16":
            value = value.float()
        value = value.numpy()
    return np.ascontiguousarray(np.asarray(value))


def content_digest(arrays: Mapping[str, Any]) -> str:
    """sha256 (hex) of ``arrays`` (name -> numpy array or torch tensor), in sorted name order; the
    :data:`DIGEST_KEY` entry itself is left out, so a dict that holds its digest can be checked in place."""
    h = hashlib.sha256()
    for name in sorted(arrays):
        if name == DIGEST_KEY:
            continue
        a = _as_numpy(arrays[name])
        h.update(name.encode())
        h.update(b"\0" + a.dtype.str.encode() + b"\0" + repr(a.shape).encode() + b"\0")
        h.update(a.tobytes())
    return h.hexdigest()


def check_digest(arrays: Mapping[str, Any], stored: str | None, what: str) -> bool:
    """Check ``arrays`` against the ``stored`` digest of the file ``what``: :class:`DigestError` naming it on a
    mismatch; ``True`` when it matches; ``False``, after a one-line note (once per file), when ``stored`` is None
    (a file written before digests were recorded)."""
    if stored is None:
        if what not in _NOTED:
            _NOTED.add(what)
            print(f"note: {what} has no content digest (written by an older version); its integrity is not checked",
                  file=sys.stderr)
        return False
    if not (isinstance(stored, str) and len(stored) == 64 and all(c in "0123456789abcdef" for c in stored)):
        raise DigestError(f"{what}: its content digest {stored!r} is not a 64-digit hex sha256")
    actual = content_digest(arrays)
    if actual != stored:
        raise DigestError(f"{what} is damaged: its content does not match the digest stored in it "
                          f"({actual[:12]}... != {stored[:12]}...); rebuild or re-download it")
    return True
