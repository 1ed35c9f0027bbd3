"""The navigation benchmark's output folder: its settings and its episode records, resumable.

``DIR/settings.json`` holds every setting that changes what an episode does (the robot, the cost, the suite's
parameters, the seeds). ``DIR/episodes.jsonl`` holds one JSON record per finished episode, appended and
flushed to disk as each finishes. A rerun into the same folder with the same settings runs only the episodes
whose key is not there yet (more tasks, methods, budgets or repeats extend a run); with different settings it
is refused, naming the settings that differ, since its records would not be comparable. The digests of the
files the methods read (:data:`MERGED`) merge: a method that reads a new file (the MLP, say) may join later,
but a different file under the same name is refused. A line cut short by a
crash (the last one) is dropped with a warning; a bad line elsewhere is an error.
"""

from __future__ import annotations

import json
import os
import warnings
from pathlib import Path
from typing import Any

from cuniform_torch.common.fileio import write_json

__all__ = ["EpisodeStore", "StoreError"]


class StoreError(ValueError):
    """An output folder whose settings or records cannot be used for this run."""


MERGED = "sources"
"""the settings key whose entries (file digests of the methods' sources) merge: a source a run does not use is
None and matches anything, so a run that adds a method reading a new file extends the folder"""


def _merge_files(old: dict, new: dict) -> tuple[dict, list[str]]:
    """``old`` updated with ``new``'s non-None entries, and the keys where both are set and differ."""
    clash = sorted(k for k in set(old) & set(new) if None not in (old[k], new[k]) and old[k] != new[k])
    return {**old, **{k: v for k, v in new.items() if v is not None}}, clash


def _get(settings: dict, key: str):
    head, _, sub = key.partition(".")
    return (settings.get(head) or {}).get(sub) if sub else settings.get(head)


class EpisodeStore:
    """``settings.json`` + ``episodes.jsonl`` under ``folder`` (module docstring)."""

    def __init__(self, folder: str | os.PathLike):
        self.folder = Path(folder)
        self.settings_file = self.folder / "settings.json"
        self.records_file = self.folder / "episodes.jsonl"

    def open(self, settings: dict[str, Any]) -> dict[str, dict]:
        """Check or write the settings; the records already there, by key."""
        self.folder.mkdir(parents=True, exist_ok=True)
        settings = json.loads(json.dumps(settings))  # JSON types: tuples compare as the lists they are stored as
        if self.settings_file.exists():
            try:
                old = json.loads(self.settings_file.read_text())
            except (OSError, ValueError) as err:
                raise StoreError(f"{self.settings_file}: unreadable ({err}); use another --out") from None
            differ = sorted(k for k in set(old) | set(settings) if k != MERGED and old.get(k) != settings.get(k))
            merged, clash = _merge_files(old.get(MERGED) or {}, settings.get(MERGED) or {})
            differ += [f"{MERGED}.{k}" for k in clash]
            if differ:
                shown = "; ".join(f"{k}: {_get(old, k)!r} there, {_get(settings, k)!r} now" for k in differ[:4])
                raise StoreError(f"{self.folder} holds episodes run with other settings ({shown}); "
                                 f"use another --out, or delete {self.folder} to start over")
            if merged != (old.get(MERGED) or {}):  # a method read a file for the first time: remember it
                write_json(self.settings_file, {**old, MERGED: merged})
        else:
            write_json(self.settings_file, settings)
        return self._read()

    def read(self) -> dict[str, dict]:
        """The records by key, read only: a last line cut short (a run may be writing it now) is left out and left
        alone; a bad line elsewhere is a :class:`StoreError`."""
        return self._parse()[0]

    def _read(self) -> dict[str, dict]:
        records, good, cut = self._parse()
        if cut:  # the last write, cut short: dropped so that appends start on a fresh line
            warnings.warn(f"{self.records_file}: dropping an incomplete last line ({cut} bytes)", stacklevel=2)
            with open(self.records_file, "r+b") as f:
                f.truncate(good)
        return records

    def _parse(self) -> tuple[dict[str, dict], int, int]:
        """``(records by key, bytes of the complete lines, bytes of a cut-short last line or 0)``."""
        if not self.records_file.exists():
            return {}, 0, 0
        lines = self.records_file.read_bytes().split(b"\n")
        records: dict[str, dict] = {}
        good = 0  # bytes of complete, parsed lines
        for i, line in enumerate(lines):
            if not line.strip():
                good += len(line) + 1
                continue
            try:
                rec = json.loads(line)
                key = rec["key"]
            except (ValueError, KeyError, TypeError):
                if i == len(lines) - 1:
                    return records, good, len(line)
                raise StoreError(f"{self.records_file}: line {i + 1} is not a record; fix or delete the file") from None
            records[key] = rec
            good += len(line) + 1
        return records, good, 0

    def append(self, record: dict) -> None:
        """Append one record and flush it to disk."""
        with open(self.records_file, "ab") as f:
            f.write(json.dumps(record, separators=(",", ":")).encode() + b"\n")
            f.flush()
            os.fsync(f.fileno())
