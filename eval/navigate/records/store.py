"""The navigation benchmark's output folder: its settings and its episode records, resumable.

``DIR/settings.json`` holds every setting that changes what an episode does (the robot, the cost, the suite's
parameters, the seeds). ``DIR/episodes.jsonl`` holds one JSON record per finished episode, appended and
flushed to disk as each finishes. A rerun into the same folder with the same settings runs only the episodes
whose key is not there yet (more tasks, methods, budgets or repeats extend a run); with different settings it
is refused, naming the settings that differ, since its records would not be comparable. The digests of the
files the methods read (:data:`MERGED`) merge: a method that reads a new file (the MLP, say) may join later,
but a different file under the same name is refused. A line cut short by a
crash (the last one) is dropped with a warning by a run, left out with a one-line note on stderr by a read-only
reader; a bad line elsewhere is an error.

It reads without torch (:mod:`eval.navigate.records.files`); :meth:`EpisodeStore.open`, the run's, writes
``settings.json`` with ``cuniform_torch.common.fileio.write_json`` (atomic), imported there.

This is the one parser of the folder: the run, and the read-only readers (replay, compare, failures) through
:meth:`EpisodeStore.load`. Records without settings are refused (what they were run with is unknown), and so is
any settings field or record of the wrong shape: a field missing or of the wrong type, a NaN or infinite number,
a key given twice, a record whose key disagrees with its fields (:data:`SETTINGS`, :data:`RECORD`).
"""

from __future__ import annotations

import difflib
import json
import math
import os
import re
import stat
import sys
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any, BinaryIO, cast

from eval.navigate.records.files import (
    MAX_JSONL_BYTES,
    MAX_SMALL_JSON_BYTES,
    file_kind,
    read_capped_bytes,
    read_capped_text,
)
from eval.navigate.records.keys import episode_key

__all__ = ["EpisodeStore", "StoreError", "load_folder", "load_episode", "SETTINGS", "RECORD", "OUTCOMES", "check_settings", "check_record"]


class StoreError(ValueError):
    """An output folder whose settings or records cannot be used for this run."""


MERGED = "sources"
"""the settings key whose entries (file digests of the methods' sources) merge: a source a run does not use is
None and matches anything, so a run that adds a method reading a new file extends the folder"""

OUTCOMES = ("goal", "collision", "timeout")
"""a record's ``outcome``"""


def _int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _num(v: Any) -> bool:  # finiteness is checked for every number of a file, before the shapes
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _positive(v: Any) -> bool:
    return _num(v) and v > 0


def _nonneg(v: Any) -> bool:
    return _num(v) and v >= 0


def _nonneg_int(v: Any) -> bool:
    return _int(v) and v >= 0


def _str(v: Any) -> bool:
    return isinstance(v, str)


_DIGEST = re.compile(r"[0-9a-f]{16}")


def _digest(v: Any) -> bool:
    """A file's digest as the run writes it (``eval.navigate.run.input_digest``): 16 hex digits of its sha256, or
    None (no such file)."""
    return v is None or (isinstance(v, str) and _DIGEST.fullmatch(v) is not None)


def _widths(v: Any) -> bool:
    """The gap sweep's widths as the run writes them: numbers > 0, sorted and distinct."""
    return (isinstance(v, list) and bool(v) and all(_positive(w) for w in v)
            and all(a < b for a, b in zip(v, v[1:])))


def _robot(v: Any) -> bool:
    keys = {"system", "params", "radius", "horizon"}
    return (isinstance(v, dict) and keys <= set(v) <= keys | {"starts"} and _str(v["system"])
            and isinstance(v["params"], dict) and _nonneg(v["radius"]) and _int(v["horizon"]) and v["horizon"] >= 1
            and _str(v.get("starts", "")))


Check = tuple[str, Callable[[Any], bool], bool]
"""``(what it must be, the test, required)``"""

SETTINGS: dict[str, Check] = {
    "suite": ("a string", _str, True),
    "seed": ("an integer", _int, True),
    "sensing_range": ("a number > 0", _positive, True),
    "horizon": ("an integer >= 1", lambda v: _int(v) and v >= 1, True),
    "lambda_": ("a number > 0", _positive, True),
    "collision_penalty": ("a number > 0", _positive, True),
    "cost_resolution": ("a number > 0", _positive, True),
    "robot": ("an object {system: str, params: object, radius: number >= 0, horizon: int >= 1[, starts: str]}",
              _robot, True),
    "time_limit": ("a number > 0", _positive, True),
    "barn_file": ("a digest (16 hex digits) or null", _digest, True),
    MERGED: ("an object of digests (16 hex digits) or nulls",
             lambda v: isinstance(v, dict) and all(_digest(d) for d in v.values()), True),
    "cost_to_go": ("a number > 0", _positive, False),
    "dynamics": ("'learned' (absent: the robot's own)", lambda v: v == "learned", False),
    "gap_widths": ("a list of numbers > 0, non-empty, sorted and distinct", _widths, False),
}
"""``settings.json``'s fields (``eval.navigate.run.settings_record`` writes them): another field is refused"""

RECORD: dict[str, Check] = {
    "key": ("a string", _str, True),
    "suite": ("a string", _str, True),
    "task_id": ("an integer >= 0", _nonneg_int, True),
    "method": ("a string", _str, True),
    "budget": ("an integer >= 1", lambda v: _int(v) and v >= 1, True),
    "seed": ("an integer >= 0", _nonneg_int, True),
    "repeat": ("an integer >= 0", _nonneg_int, True),
    "outcome": (" or ".join(map(repr, OUTCOMES)), lambda v: v in OUTCOMES, True),
    "success": ("true or false", lambda v: isinstance(v, bool), True),
    "time": ("a number >= 0", _nonneg, True),
    "path_length": ("a number >= 0", _nonneg, True),
    "steps": ("an integer >= 0", _nonneg_int, True),
    "cycles": ("an integer >= 0", _nonneg_int, True),
    "cycle_hist": ("an object of integer counts >= 0",
                   lambda v: isinstance(v, dict) and all(_nonneg_int(c) for c in v.values()), True),
    "wall_s": ("a number >= 0", _nonneg, True),
    "path": ("a list of [x, y] numbers",
             lambda v: isinstance(v, list) and all(isinstance(p, list) and len(p) == 2 and all(map(_num, p))
                                                   for p in v), False),
}
"""an ``episodes.jsonl`` record's fields (``eval.navigate.episode.run_nav_episode`` writes them); other fields
are kept unchecked (a reader ignores what it does not know)"""


def _nonfinite(obj: Any, where: str = "") -> str | None:
    """The path (``time``, ``cycle_hist.12``) of the first NaN or infinite number in ``obj``, else None."""
    if isinstance(obj, float):
        return None if math.isfinite(obj) else where
    items = obj.items() if isinstance(obj, dict) else enumerate(obj) if isinstance(obj, list) else ()
    for k, v in items:
        bad = _nonfinite(v, f"{where}.{k}" if where else str(k))
        if bad is not None:
            return bad
    return None


def _problem(obj: Any, fields: dict[str, Check], strict: bool) -> str | None:
    """What is wrong with the JSON object ``obj`` against ``fields`` (None: nothing)."""
    if not isinstance(obj, dict):
        return f"not a JSON object but a {type(obj).__name__}"
    bad = _nonfinite(obj)
    if bad is not None:
        return f"field {bad!r} is not a finite number"
    missing = [k for k, (_, _, required) in fields.items() if required and k not in obj]
    if missing:
        return f"field(s) {', '.join(map(repr, missing))} missing"
    if strict:
        other = sorted(set(obj) - set(fields))
        if other:
            return f"unknown field(s) {', '.join(map(repr, other))} (known: {', '.join(fields)})"
    for k, (what, test, _) in fields.items():
        if k in obj and not test(obj[k]):
            return f"field {k!r} must be {what}, got {obj[k]!r}"
    return None


def check_settings(settings: Any) -> str | None:
    """What is wrong with a ``settings.json`` object (:data:`SETTINGS`), or None."""
    problem = _problem(settings, SETTINGS, strict=True)
    if problem is None and settings["suite"] != "barn" and settings["barn_file"] is not None:
        problem = f"field 'barn_file' must be null outside the barn suite, got {settings['barn_file']!r}"
    return problem


def check_record(record: Any) -> str | None:
    """What is wrong with one ``episodes.jsonl`` record (:data:`RECORD`; its key must be its fields'), or None."""
    problem = _problem(record, RECORD, strict=False)
    if problem is not None:
        return problem
    r = record
    key = episode_key(r["suite"], r["task_id"], r["method"], r["budget"], r["repeat"])
    if r["key"] != key:
        return f"its key {r['key']!r} is not its fields' ({key!r})"
    if r["success"] != (r["outcome"] == "goal"):
        return f"success {r['success']} contradicts outcome {r['outcome']!r}"
    hist = r["cycle_hist"]  # eval.navigate.records.cycle_hist.cycle_histogram: one count per command timed
    if not all(_BIN.fullmatch(b) and int(b) <= 279 and c >= 1 for b, c in hist.items()):
        return f"field 'cycle_hist' must map bins '0'..'279' to counts >= 1, got {hist!r}"
    if sum(hist.values()) != r["cycles"]:
        return f"cycle_hist counts {sum(hist.values())} commands, but cycles is {r['cycles']}"
    return None


_BIN = re.compile(r"0|[1-9]\d{0,2}")


class _Whole(ValueError):
    """A line that parsed far enough to be whole, yet is not a record: never a line cut short."""


class _Twice(_Whole):
    """A name given twice in one JSON object."""


def _unique_names(pairs: list[tuple[str, Any]]) -> dict:
    """json object hook: a name given twice in one object is an error (json keeps the last one silently)."""
    out = dict(pairs)
    if len(out) != len(pairs):
        names = [k for k, _ in pairs]
        raise _Twice(f"field {next(k for k in names if names.count(k) > 1)!r} given twice")
    return out


def _loads(text: str | bytes) -> Any:
    try:
        return json.loads(text, object_pairs_hook=_unique_names)
    except RecursionError:  # the json module's own limit: arrays or objects nested thousands deep
        raise _Whole("nested too deeply to be a record") from None


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
        self._noted_cut = False  # a read-only load said once that it left a cut-short last line out

    def open(self, settings: dict[str, Any]) -> dict[str, dict]:
        """Check or write the settings; the records already there, by key."""
        from cuniform_torch.common.fileio import write_json  # only a run writes: it has the runtime loaded anyway

        settings = json.loads(json.dumps(settings))  # JSON types: tuples compare as the lists they are stored as
        problem = check_settings(settings)
        if problem is not None:  # a settings_record out of step with SETTINGS: a bug, said before any write
            raise ValueError(f"the run's settings for {self.settings_file}: {problem}")
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
        except OSError as err:  # a symlink loop, a file in the way: FileExistsError / NotADirectoryError, raw before
            raise StoreError(f"{self.folder}: cannot be used as a benchmark folder ({err.strerror or err}); use "
                             "another --out") from None
        self._check_own_files()
        if self.settings_file.exists():
            old = self.read_settings()
            differ = sorted(k for k in set(old) | set(settings) if k != MERGED and old.get(k) != settings.get(k))
            merged, clash = _merge_files(old[MERGED], settings[MERGED])
            differ += [f"{MERGED}.{k}" for k in clash]
            if differ:
                shown = "; ".join(f"{k}: {_get(old, k)!r} there, {_get(settings, k)!r} now" for k in differ[:4])
                raise StoreError(f"{self.folder} holds episodes run with other settings ({shown}); "
                                 f"use another --out, or delete {self.folder} to start over")
            if merged != old[MERGED]:  # a method read a file for the first time: remember it
                write_json(self.settings_file, {**old, MERGED: merged})
        elif self._has_records():  # what these episodes ran with is unknown: they would pass for this run's
            raise self._no_settings()
        else:
            write_json(self.settings_file, settings)
        return self._read(settings["suite"])

    def check(self) -> None:
        """Refuse early, before the work that makes a run's settings (the source files' digests), a folder that
        :meth:`open` refuses whatever the settings: records without settings, settings or records of the wrong
        shape, files that are links or not regular files. A folder without either passes (a new run)."""
        self._check_own_files()
        if self.settings_file.exists() or self._has_records():
            self._load(note=False)  # the run's open() warns about a cut-short last line, and drops it

    def _check_own_files(self) -> None:
        """A :class:`StoreError` when ``settings.json`` or ``episodes.jsonl`` is a symlink (a run would write
        through it, into another folder or ``/dev/null``; a reader would report another folder's episodes) or not a
        regular file (a FIFO, a device): a run and a reader use only the folder's own files."""
        for path in (self.settings_file, self.records_file):
            try:
                mode = os.lstat(path).st_mode
            except FileNotFoundError:
                continue
            except OSError as err:
                raise StoreError(f"{path}: cannot be checked ({err.strerror or err}); use another --out") from None
            if stat.S_ISLNK(mode):
                raise StoreError(f"{path} is a symlink (to {os.readlink(path)}); a benchmark folder's files are its "
                                 "own: replace the link with a copy of the file, or use another --out")
            if not stat.S_ISREG(mode):
                raise StoreError(f"{path} is {file_kind(mode)}, not a regular file; remove it, or use another --out")

    def _no_settings(self) -> StoreError:
        return StoreError(f"{self.folder} holds episode records ({self.records_file.name}) but no settings.json, so "
                          f"what they were run with is unknown; use another --out, or delete {self.records_file} "
                          "to start over")

    def read_settings(self) -> dict[str, Any]:
        """The folder's settings, checked (:data:`SETTINGS`); a :class:`StoreError` naming the file otherwise."""
        if not os.path.lexists(self.settings_file):  # something there that is not a file is said below
            if self._has_records():
                raise self._no_settings()
            raise StoreError(f"{self.folder} is not a benchmark folder: it has no settings.json "
                             "(python -m eval.navigate --out)")
        try:
            settings = _loads(read_capped_text(self.settings_file, MAX_SMALL_JSON_BYTES, "the benchmark settings"))
        except (OSError, ValueError) as err:
            raise StoreError(f"{self.settings_file}: unreadable ({err}); use another --out") from None
        problem = check_settings(settings)
        if problem is not None:
            raise StoreError(f"{self.settings_file}: {problem}; restore the folder's settings, or use another --out")
        return settings

    def load(self) -> tuple[dict[str, Any], dict[str, dict]]:
        """``(settings, records by key)``, read only (:meth:`read`)."""
        return self._load(note=True)

    def _load(self, note: bool) -> tuple[dict[str, Any], dict[str, dict]]:
        self._check_own_files()  # a link: whose records these are is unknown (and a run would write through it)
        settings = self.read_settings()
        records, _, cut, line = self._parse(settings["suite"])
        if cut and note and not self._noted_cut:  # never silently: the reader's numbers lack that episode
            self._noted_cut = True
            print(f"note: {self.records_file}: line {line} is cut short ({cut} bytes, not a record; a run may "
                  f"be writing it now): left out, the file left as it is", file=sys.stderr)
        return settings, records

    def read(self) -> dict[str, dict]:
        """The records by key, read only: a last line cut short (a run may be writing it now) is left out and left
        alone, said once on stderr (one line naming the file and the line); a bad line elsewhere is a
        :class:`StoreError`. Needs the settings (:meth:`load`)."""
        return self.load()[1]

    def _has_records(self) -> bool:
        data = self._records_bytes()
        return data is not None and bool(data.strip())

    def _records_bytes(self) -> bytes | None:
        """``episodes.jsonl``'s bytes; None when there is none; a :class:`StoreError` when something is there but
        cannot be read (a folder, a symlink loop or one to nothing: never taken for a folder without records; a FIFO
        or a device; a file over :data:`~eval.navigate.records.files.MAX_JSONL_BYTES`)."""
        if not (self.records_file.exists() or self.records_file.is_symlink()):
            return None
        try:
            return read_capped_bytes(self.records_file, MAX_JSONL_BYTES, "the episode records")
        except OSError as err:
            raise StoreError(f"{self.records_file}: unreadable ({err.strerror or err}); fix or delete it") from None
        except ValueError as err:
            raise StoreError(f"{err}; fix or delete it") from None

    def _read(self, suite: str) -> dict[str, dict]:
        records, good, cut, _ = self._parse(suite)
        if cut:  # the last write, cut short: dropped so that appends start on a fresh line
            warnings.warn(f"{self.records_file}: dropping an incomplete last line ({cut} bytes)", stacklevel=2)
            with self._open_own("r+b") as f:
                f.truncate(good)
        elif self.records_file.exists() and self.records_file.stat().st_size:
            with self._open_own("r+b") as f:
                f.seek(-1, os.SEEK_END)
                if f.read(1) != b"\n":  # a whole last record cut before its newline: appends start on a fresh line
                    f.write(b"\n")
        return records

    def _parse(self, suite: str) -> tuple[dict[str, dict], int, int, int]:
        """``(records by key, bytes of the complete lines, bytes of a cut-short last line or 0, its line number or
        0)``: every record checked (:func:`check_record`, of ``suite``), a key twice refused."""
        data = self._records_bytes()
        if data is None:
            return {}, 0, 0, 0
        lines = data.split(b"\n")
        records: dict[str, dict] = {}
        first: dict[str, int] = {}  # the line of each key
        good = 0  # bytes of complete, parsed lines
        for i, line in enumerate(lines):
            if not line.strip():
                good += len(line) + 1
                continue
            try:
                rec = _loads(line)
            except ValueError as err:
                if i == len(lines) - 1 and not isinstance(err, _Whole):
                    return records, good, len(line), i + 1
                raise StoreError(f"{self.records_file}: line {i + 1} is not a record ({err}); fix or delete the "
                                 "file") from None
            problem = check_record(rec)
            if problem is None and rec["suite"] != suite:
                problem = f"suite {rec['suite']!r} in a folder of the {suite!r} suite"
            if problem is None and rec["key"] in first:
                problem = (f"episode {rec['key']!r} again (first on line {first[rec['key']]}): which outcome holds "
                           "is unknown")
            if problem is not None:
                raise StoreError(f"{self.records_file}: line {i + 1}: {problem}; fix or delete the file")
            records[rec["key"]] = rec
            first[rec["key"]] = i + 1
            good += len(line) + 1
        return records, good, 0, 0

    def _open_own(self, mode: str) -> BinaryIO:
        """``episodes.jsonl`` opened for writing (``"ab"``: appends, created when missing; ``"r+b"``), never through a
        symlink (``O_NOFOLLOW``: an ``OSError`` naming it) and only when it is a regular file."""
        flags = (os.O_WRONLY | os.O_APPEND | os.O_CREAT) if mode == "ab" else os.O_RDWR
        fd = os.open(self.records_file, flags | os.O_NOFOLLOW | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0), 0o644)
        try:
            st_mode = os.fstat(fd).st_mode
            if not stat.S_ISREG(st_mode):
                raise StoreError(f"{self.records_file} is {file_kind(st_mode)}, not a regular file; remove it, or "
                                 "use another --out")
            os.set_blocking(fd, True)
            return cast(BinaryIO, os.fdopen(fd, mode))  # a str mode types as IO[Any]; it is "ab" or "r+b"
        except BaseException:
            os.close(fd)
            raise

    def append(self, record: dict) -> None:
        """Append one record and flush it to disk."""
        with self._open_own("ab") as f:
            f.write(json.dumps(record, separators=(",", ":")).encode() + b"\n")
            f.flush()
            os.fsync(f.fileno())


def load_folder(out: Path) -> tuple[dict, dict[str, dict]]:
    """``(settings, every record by key)`` of the benchmark folder ``out`` (read only; checked by
    :meth:`EpisodeStore.load`, the folder's one parser)."""
    return EpisodeStore(out).load()


def load_episode(out: Path, key: str) -> tuple[dict, dict, dict[str, dict]]:
    """``(settings, record, every record by key)`` of the benchmark folder ``out``; a ValueError naming a few keys
    present when ``key`` is not there."""
    settings, records = load_folder(out)
    if key not in records:
        keys = sorted(records)
        near = difflib.get_close_matches(key, keys, n=3, cutoff=0.5) or keys[:3]
        held = f"it holds {len(keys)} episodes, e.g. {', '.join(near)}" if keys else "it holds no episode"
        raise ValueError(f"no episode {key!r} in {EpisodeStore(out).records_file} ({held})")
    return settings, records[key], records
