"""Attack run: every file reader and every ``python -m`` entry point against damaged, forged and hostile input.

``python .ci/attack.py [--quick] [--out FILE.json] [--families a,b] [--keep]``: a developer tool (not shipped).

For each file family (table, table set, MLP / start-MLP / map-policy checkpoint, map data set, local map,
benchmark folder) it writes a small valid original with the project's own writers, makes mutated copies (flipped
bytes, truncation, crafted ``.npy`` headers, wrong dtypes and shapes, NaN / inf / 1e38, missing and extra keys,
pickle payloads, JSON of the wrong types, duplicates, symlink loops, FIFOs and links to devices, ...) and reads each copy through the
family's reader API in a forked child of this process (torch and the package already imported, one thread), so
each case is a fresh process whose memory peak is its own. Each ``python -m`` command is run the same way (its
module run as ``__main__`` in a forked child, in an empty folder) with bad flag values: the bad-input classes of
tests/test_entry_points.py (imported, so a new command or flag is covered), a missing file and a folder where a
file is expected. In full mode one case per command also runs as a real ``python -m`` subprocess, to check that
the forked runs classify the same way.

Outcomes (per case):

* ``clear error``: the reader raised the family's error class (the command: exit code 2 and one ``error:`` line
  on stderr, no traceback);
* ``traceback``: any other exception (the command: any other exit code, a traceback, or more than the one line);
* ``code ran``: a marker file that the attack's payload (a pickle ``__reduce__``, a factory module) would write
  exists afterwards;
* ``crash/hang``: the child died by a signal or did not finish in time;
* ``silent wrong``: the reader accepted the copy and what it returned differs from what it returns for the
  original (the arrays / tables / records read, a policy's weights and its action probabilities at fixed probe
  states); a command exited 0 or kept running on a bad value;
* ``harmless accepted``: the reader accepted the copy and returned exactly what it returns for the original
  (e.g. an unknown extra key, a flipped byte in a member the reader never reads);
* ``left out, said``: the reader returned less than for the original and said so: exactly one line on stderr
  that names the file and says what it ``left out`` (a benchmark folder's cut-short last record, which a run
  may be writing now: docs/formats.md). Anything else returned differently is ``silent wrong``.

Memory: each child resets its peak RSS (``/proc/self/clear_refs``) when it starts; its peak over the RSS it
started with is the reader's own cost ("peak MB"). The baseline (a fresh ``python`` that imports torch and the
readers) is measured once and reported beside it. A case of a file under 10 MB whose peak exceeds 256 MB is listed.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import hashlib
import io
import json
import math
import os
import resource
import shutil
import signal
import struct
import subprocess
import sys
import tempfile
import time
import traceback
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
OUTCOMES = ("clear error", "silent wrong", "traceback", "code ran", "crash/hang", "harmless accepted",
            "left out, said")
BAD = ("silent wrong", "traceback", "code ran", "crash/hang")
PEAK_LIMIT_MB = 256
SMALL_FILE = 10 << 20


# --------------------------------------------------------------------------------------------------- cases

@dataclasses.dataclass
class Case:
    """One attack: ``reader`` applied to ``target`` (a file or folder), or a command line (``argv``)."""

    family: str
    mutation: str
    target: str = ""
    reader: str = ""
    argv: list[str] | None = None  # an entry-point case: [module, *flags]
    size: int = 0
    outcome: str = ""
    detail: str = ""
    peak_mb: float = 0.0
    seconds: float = 0.0
    lost: list[str] = dataclasses.field(default_factory=list)  # files that existed before and changed or went
    left: list[str] = dataclasses.field(default_factory=list)  # processes of the case alive after it ended
    extra: dict[str, Any] = dataclasses.field(default_factory=dict)


class Evil:
    """A pickle payload: unpickling it calls ``open(marker, "w")``, which creates the marker file."""

    def __init__(self, marker: Path):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


def _tree_size(path: Path) -> int:
    try:
        if path.is_symlink() or not path.exists():
            return 0
        if path.is_file():
            return path.stat().st_size
        return sum(p.stat().st_size for p in path.rglob("*") if p.is_file() and not p.is_symlink())
    except (OSError, RuntimeError):
        return 0


def _cases() -> Any:
    """tests/cases.py: the case tables the hardening tests and this run share (a case added there is tried by both;
    imported late: it imports the package, which a fork-free ``--help`` does not need)."""
    if str(REPO / "tests") not in sys.path:
        sys.path.insert(0, str(REPO / "tests"))
    import cases

    return cases


# --------------------------------------------------------------------------------------------------- fingerprints

def fingerprint(obj: Any) -> str:
    """sha256 of a nested structure of dicts, lists, arrays, tensors and plain values (dtype, shape and bytes of
    every array): two reads agree on everything that matters iff their fingerprints agree."""
    import numpy as np
    import torch

    h = hashlib.sha256()

    def walk(o: Any, at: str) -> None:
        if isinstance(o, torch.Tensor):
            o = o.detach().cpu().float().numpy() if o.dtype == torch.bfloat16 else o.detach().cpu().numpy()
        if isinstance(o, np.ndarray):
            a = np.ascontiguousarray(o)
            h.update(f"{at}:{a.dtype.str}:{a.shape}:".encode())
            h.update(a.tobytes())
        elif isinstance(o, dict):
            for k in sorted(o, key=str):
                walk(o[k], f"{at}/{k}")
        elif isinstance(o, (list, tuple)):
            h.update(f"{at}:len{len(o)}".encode())
            for i, v in enumerate(o):
                walk(v, f"{at}/{i}")
        elif isinstance(o, float) and math.isnan(o):
            h.update(f"{at}=nan".encode())
        else:
            h.update(f"{at}={o!r}".encode())

    walk(obj, "")
    return h.hexdigest()


def _policy_view(policy: Any, patch: Any = None) -> dict:
    """What a policy hands its user: its weights, config, actions, and its action probabilities at probe states
    of every level (for a map policy, after ``set_map(patch)``)."""
    import torch

    view: dict[str, Any] = {"state_dict": dict(policy.state_dict()), "actions": policy.actions,
                            "config": dataclasses.asdict(policy.config) if dataclasses.is_dataclass(policy.config)
                            else policy.config, "system": repr(getattr(policy.system, "name", None))}
    d = policy.config.state_dim
    gen = torch.Generator().manual_seed(0)
    x = (torch.rand(16, d, generator=gen) * 2 - 1).to(policy.dtype)  # [16, d] within a metre / a radian
    if patch is not None:
        policy.set_map(patch)
    for t in range(policy.horizon):
        view[f"probs/{t}"] = policy.action_probs(x, t)
    return view


# --------------------------------------------------------------------------------------------------- readers

def _readers() -> dict[str, tuple[Callable[[Path], Any], tuple[type, ...]]]:
    """reader name -> (read the target and return its fingerprint, the family's error classes)."""
    import numpy as np
    import torch

    import cuniform_torch
    from cuniform_torch.envs.occupancy import OccupancyGrid
    from cuniform_torch.maps.checkpoint import MapCheckpointError, load_map_policy
    from cuniform_torch.policies.checkpoint import PolicyCheckpointError, load_policy
    from cuniform_torch.policies.table_set import load_table_set
    from cuniform_torch.tables.file import TableError, read_table
    from eval.navigate.records.store import EpisodeStore, StoreError
    from precompute.levels.safe_map import MapError, read_map_file
    from precompute.maps.dataset import MapDatasetError, read_map_dataset

    def table(p: Path) -> str:
        return fingerprint(read_table(p).to_arrays())

    def table_policy(p: Path) -> str:  # what a controller loads: cuniform_torch.load_table (graph=False)
        return fingerprint(cuniform_torch.load_table(p).table.to_arrays())

    def table_set(p: Path) -> str:
        pol = load_table_set(p, lazy=False)
        return fingerprint({"starts": pol.starts, "members": [m.table.to_arrays() for m in pol.members]})

    def policy(p: Path) -> str:
        return fingerprint(_policy_view(load_policy(p)))

    def map_policy(p: Path) -> str:
        pol = load_map_policy(p)
        spec = pol.patch_spec
        occ = torch.zeros(spec.shape, dtype=torch.bool)
        occ[: spec.shape[0] // 3, :] = True
        grid = OccupancyGrid(occupied=occ, origin=tuple(spec.origin), resolution=spec.resolution)
        return fingerprint(_policy_view(pol, grid))

    def map_dataset(p: Path) -> str:
        ds = read_map_dataset(p, load=True)
        meta = {k: v for k, v in ds.meta.items() if k not in ("entries", "shards")}  # sha256s: storage, not content
        shards = [{k: v for k, v in ds.shard(i).arrays.items() if k != "content_sha256"}
                  for i in range(len(ds.shards))]
        return fingerprint({"meta": meta, "poses": [e.get("pose") for e in ds.entries], "horizon": ds.horizon,
                            "radius": ds.radius, "shards": shards})

    def local_map(p: Path) -> str:
        m = read_map_file(p)
        return fingerprint({"occupied": np.asarray(m.occupied), "origin": m.origin, "resolution": m.resolution})

    def bench(p: Path) -> str:
        settings, records = EpisodeStore(p).load()
        return fingerprint({"settings": settings, "records": records})

    def bench_append(p: Path) -> str:  # what a run does to its folder: open it with its settings, add a record
        import warnings

        store = EpisodeStore(p)
        with warnings.catch_warnings(record=True) as said:  # what a run says (the attack ignores warnings)
            warnings.simplefilter("always")
            store.open(BENCH_SETTINGS)
        for w in said:
            print(f"warning: {w.message}", file=sys.stderr)
        store.append({**BENCH_RECORD, "key": "gaps/5/mppi_1.0/16/0", "task_id": 5})
        settings, records = store.load()
        return fingerprint({"settings": settings, "records": records})

    return {"table": (table, (TableError,)), "table_policy": (table_policy, (TableError,)),
            "table_set": (table_set, (TableError,)), "policy": (policy, (PolicyCheckpointError,)),
            "map_policy": (map_policy, (MapCheckpointError,)), "map_dataset": (map_dataset, (MapDatasetError,)),
            "local_map": (local_map, (MapError,)), "bench": (bench, (StoreError,)),
            "bench_append": (bench_append, (StoreError,))}


# --------------------------------------------------------------------------------------------------- lost, left

SYSTEM_FILES = ("/dev/null", "/dev/zero", "/dev/urandom", "/dev/full", "/dev/stdout")
"""watched in every case: a write through a link (or a rename over one) must never replace them"""
CASE_VAR = "CUNIFORM_ATTACK_CASE"
"""set in each case's child: every process the case starts inherits it, so one left running is found in /proc"""


def _entry_state(path: str, st: os.stat_result) -> tuple:
    import stat as st_

    if st_.S_ISLNK(st.st_mode):
        return ("link", os.readlink(path))
    if st_.S_ISREG(st.st_mode):
        if st.st_size > 64 << 20:  # a huge (sparse) case file: its size and time, not its bytes
            return ("file", st.st_size, st.st_mtime_ns)
        h = hashlib.sha256()
        with open(path, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
        return ("file", st.st_size, h.hexdigest())
    if st_.S_ISDIR(st.st_mode):
        return ("folder",)
    return ("special", st_.S_IFMT(st.st_mode), st.st_rdev)


def snapshot(paths: list[Path]) -> dict[str, tuple]:
    """Every file, folder and link under ``paths`` (links not followed, special files by kind): what a case may
    not change."""
    out: dict[str, tuple] = {}
    todo = [str(p) for p in paths] + list(SYSTEM_FILES)
    while todo:
        path = todo.pop()
        try:
            st = os.lstat(path)
            out[path] = _entry_state(path, st)
        except OSError:
            continue
        if out[path] == ("folder",):
            try:
                todo += [os.path.join(path, name) for name in os.listdir(path)]
            except OSError:
                pass
    return out


def lost_since(before: dict[str, tuple]) -> list[str]:
    """What existed in ``before`` and is now changed or gone (a new file is not a loss)."""
    now = snapshot([])  # the system files
    lost = []
    for path, state in before.items():
        try:
            current = now.get(path) or _entry_state(path, os.lstat(path))
        except OSError:
            current = None
        if current != state:
            lost.append(f"{path}: {'gone' if current is None else 'changed'}")
    return lost


def _pids() -> set[int]:
    return {int(e) for e in os.listdir("/proc") if e.isdigit()}


def left_processes(token: str, before: set[int], grace: float = 1.0) -> list[str]:
    """Processes started since ``before`` whose environment holds ``CASE_VAR=token``, alive ``grace`` s after the
    case ended (a pool's workers notice a dead parent within 0.25 s); each is then SIGKILLed."""
    needle = f"{CASE_VAR}={token}".encode()
    deadline = time.time() + grace
    while True:
        found = []
        for pid in _pids() - before:
            try:
                with open(f"/proc/{pid}/environ", "rb") as fh:
                    env = fh.read().split(b"\0")
                with open(f"/proc/{pid}/stat", "rb") as fh:
                    zombie = fh.read().rsplit(b")", 1)[1].split()[0] == b"Z"
            except OSError:
                continue
            if needle in env and not zombie:
                found.append(pid)
        if not found or time.time() > deadline:
            break
        time.sleep(0.05)
    for pid in found:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)
    return [str(pid) for pid in found]


# --------------------------------------------------------------------------------------------------- the forked child

def _status(key: str) -> int:
    """A ``/proc/self/status`` field in kB."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(key + ":"):
                return int(line.split()[1])
    return 0


def _child_start(workdir: Path) -> int:
    """In a fresh child: stdout / stderr to files, the peak RSS reset, an address-space cap; the RSS at start."""
    out = os.open(workdir / "stdout", os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    err = os.open(workdir / "stderr", os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    os.dup2(out, 1)
    os.dup2(err, 2)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    cap = _status("VmSize") * 1024 + (6 << 30)  # a reader that allocates wildly fails here, not the machine
    resource.setrlimit(resource.RLIMIT_AS, (cap, cap))
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
    except OSError:
        pass
    return _status("VmRSS")


_LEFT: list[str] = []
"""the processes the last :func:`_fork` left running"""


def _fork(run: Callable[[], int], workdir: Path, timeout: float) -> tuple[str, int, float, float]:
    """Run ``run()`` in a forked child (its return value: the exit code); ``(how, code, peak_mb, seconds)`` where
    how is "exit", "signal" or "timeout". The processes it left running are in :data:`_LEFT`."""
    workdir.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    sys.stdout.flush()
    sys.stderr.flush()
    token, before = f"{os.getpid()}-{time.time_ns()}", _pids()
    pid = os.fork()
    if pid == 0:  # the child
        code = 70
        try:
            os.environ[CASE_VAR] = token  # inherited by every process the case starts
            rss0 = _child_start(workdir)
            try:
                code = run()
            finally:
                (workdir / "peak").write_text(str(max(0, _status("VmHWM") - rss0)))
        except BaseException:  # noqa: BLE001 - nothing may escape the child
            traceback.print_exc()
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(code if isinstance(code, int) and 0 <= code < 256 else 1)
    deadline = t0 + timeout
    while True:
        done, status, _ = os.wait4(pid, os.WNOHANG)
        if done:
            break
        if time.time() > deadline:
            os.kill(pid, signal.SIGKILL)
            os.wait4(pid, 0)
            _LEFT[:] = left_processes(token, before)
            return "timeout", -9, _peak(workdir), time.time() - t0
        time.sleep(0.005)
    seconds = time.time() - t0
    _LEFT[:] = left_processes(token, before)
    if os.WIFSIGNALED(status):
        return "signal", -os.WTERMSIG(status), _peak(workdir), seconds
    return "exit", os.WEXITSTATUS(status), _peak(workdir), seconds


def _peak(workdir: Path) -> float:
    try:
        return int((workdir / "peak").read_text()) / 1024
    except (OSError, ValueError):
        return float("nan")


def run_reader_case(case: Case, readers: dict, original: dict[str, str], workdir: Path, timeout: float,
                    watch: list[Path] | None = None) -> None:
    """Read ``case.target`` with its reader in a forked child and classify the outcome (module docstring); what
    changed under the target or ``watch`` (other than by a writing reader in its own target) is ``lost``."""
    read, errors = readers[case.reader]
    before = snapshot([*(watch or []), *([] if case.reader in WRITING_READERS else [Path(case.target)])])
    result = workdir / "result.json"
    marker = workdir.parent / "marker"
    if marker.exists():
        marker.unlink()
    if result.exists():
        result.unlink()

    def child() -> int:
        sys.path.insert(0, str(workdir.parent))  # where the attack's factory module lies (never to be imported)
        try:
            out = {"status": "accepted", "fp": read(Path(case.target))}
        except BaseException as exc:  # noqa: BLE001 - classified by the parent
            out = {"status": "raised", "type": f"{type(exc).__module__}.{type(exc).__qualname__}",
                   "family": isinstance(exc, errors), "message": str(exc)[:3000],
                   "traceback": traceback.format_exc()[-4000:]}
        result.write_text(json.dumps(out))
        return 0

    how, code, case.peak_mb, case.seconds = _fork(child, workdir, timeout)
    case.left, case.lost = list(_LEFT), lost_since(before)
    stderr = (workdir / "stderr").read_text(errors="replace")[-2000:]
    ran = marker.exists()
    if how != "exit" or not result.exists():
        case.outcome = "crash/hang"
        case.detail = f"{how} {code}; stderr: {stderr[-500:]}"
    else:
        out = json.loads(result.read_text())
        if out["status"] == "raised":
            message = out["message"]
            case.extra["error"] = out["type"]
            if out["family"]:
                case.outcome = "clear error"
                case.detail = message.splitlines()[0][:300] if message else ""
                name = Path(case.target).name
                case.extra["names_file"] = bool(name) and name in message
                case.extra["one_line"] = "\n" not in message.strip()
            else:
                case.outcome = "traceback"
                case.detail = f"{out['type']}: {message[:300]}"
                case.extra["traceback"] = out["traceback"]
        else:
            case.extra["fp"] = out["fp"]
            said = [ln for ln in stderr.splitlines() if ln.strip()]
            if out["fp"] == original.get(case.reader):
                case.outcome = "harmless accepted"
            elif len(said) == 1 and case.target in said[0] and any(w in said[0] for w in LEFT_OUT_WORDS):
                case.outcome = "left out, said"
            else:
                case.outcome = "silent wrong"
            case.detail = "accepted" + (f"; stderr: {stderr.strip()[:200]}" if stderr.strip() else "")
    if ran:
        case.outcome = "code ran"
        case.detail = "the payload's marker file exists; " + case.detail


def run_command_case(case: Case, workdir: Path, timeout: float, real: bool = False,
                     watch: list[Path] | None = None) -> None:
    """Run ``python -m <case.argv>`` (forked: the module run as ``__main__``; ``real``: a fresh interpreter) in an
    empty folder and classify its exit code and stderr; what changed under ``watch`` is ``lost``."""
    import runpy

    name, *args = case.argv or []
    before = snapshot(watch or [])
    cwd = workdir / "cwd"
    shutil.rmtree(cwd, ignore_errors=True)
    cwd.mkdir(parents=True)
    if real:
        env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
        t0 = time.time()
        try:
            proc = subprocess.run([sys.executable, "-m", name, *args], cwd=cwd, env=env, capture_output=True,
                                  text=True, timeout=timeout)
            how, code, stderr = "exit", proc.returncode, proc.stderr
        except subprocess.TimeoutExpired as exc:
            how, code = "timeout", -9
            stderr = exc.stderr.decode(errors="replace") if isinstance(exc.stderr, bytes) else (exc.stderr or "")
        case.seconds = time.time() - t0
        case.peak_mb = float("nan")
    else:
        def child() -> int:
            os.chdir(cwd)
            sys.argv = [name, *args]
            try:
                runpy.run_module(name, run_name="__main__", alter_sys=True)
            except SystemExit as exc:
                return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
            return 0

        how, code, case.peak_mb, case.seconds = _fork(child, workdir, timeout)
        stderr = (workdir / "stderr").read_text(errors="replace")
        case.left = list(_LEFT)
    case.lost = lost_since(before)
    lines = [ln for ln in stderr.splitlines() if ln.strip()]
    case.extra["rc"] = code
    built = [a for a in args if "/missing_" in a and Path(a).exists()]
    if built and how != "signal":  # the flag's documented build-when-missing (a cache path): not a bad value
        case.outcome = "harmless accepted"
        case.detail = f"built the missing {Path(built[0]).name} (the flag builds a missing file); exit {code}"
        return
    case.extra["stderr"] = stderr[-1500:]
    if how == "timeout":
        case.outcome = "silent wrong"
        case.detail = f"no refusal within {timeout:.0f} s: the value was taken and the command went to work"
    elif how == "signal":
        case.outcome = "crash/hang"
        case.detail = f"killed by signal {-code}"
    elif code == 0:
        case.outcome = "silent wrong"
        case.detail = "exit 0: the bad value was accepted"
    elif code == 2 and "Traceback" not in stderr and len(lines) == 1 and lines[0].startswith("error: "):
        case.outcome = "clear error"
        case.detail = lines[0][:300]
    else:
        case.outcome = "traceback"
        case.detail = f"exit {code}; stderr: " + " | ".join(lines[-3:])[:400]


# --------------------------------------------------------------------------------------------------- npz crafting

def npz_members(path: Path) -> list[tuple[str, bytes]]:
    """The ``(name, .npy bytes)`` members of a zip, in order."""
    with zipfile.ZipFile(path) as zf:
        return [(info.filename, zf.read(info)) for info in zf.infolist()]


def zip_write(path: Path, members: list[tuple[str, bytes]], compression: int = zipfile.ZIP_DEFLATED) -> None:
    """A zip of exactly ``members`` (a name may repeat: zipfile warns, the attack wants it)."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with zipfile.ZipFile(path, "w", compression=compression) as zf:
            for name, data in members:
                zf.writestr(zipfile.ZipInfo(name, date_time=(1980, 1, 1, 0, 0, 0)), data, compress_type=compression)


def npy_bytes(arr: Any, allow_pickle: bool = False) -> bytes:
    import numpy as np

    buf = io.BytesIO()
    np.lib.format.write_array(buf, np.asanyarray(arr), allow_pickle=allow_pickle)
    return buf.getvalue()


def npy_recrafted(npy: bytes, **header: Any) -> bytes:
    """``npy`` with its header's ``descr``, ``shape`` or ``fortran_order`` replaced (the data left as it is)."""
    import numpy as np

    fh = io.BytesIO(npy)
    version = np.lib.format.read_magic(fh)
    reader = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
    shape, fortran, dtype = reader(fh)
    data = npy[fh.tell():]
    d = {"descr": np.lib.format.dtype_to_descr(dtype), "fortran_order": fortran, "shape": shape, **header}
    out = io.BytesIO()
    np.lib.format.write_array_header_2_0(out, d) if version == (2, 0) else np.lib.format.write_array_header_1_0(out, d)
    return out.getvalue() + data


def member_spans(path: Path) -> list[tuple[str, int, int]]:
    """``(name, offset of its stored data, stored length)`` of each zip member."""
    raw = path.read_bytes()
    spans = []
    with zipfile.ZipFile(path) as zf:
        for info in zf.infolist():
            off = info.header_offset
            n, m = struct.unpack("<HH", raw[off + 26:off + 30])
            spans.append((info.filename, off + 30 + n + m, info.compress_size))
    return spans


def raw_mutations(src: Path, quick: bool) -> list[tuple[str, Callable[[Path], None]]]:
    """Byte-level damage of a zip file (an ``.npz`` or a ``.pt``): flipped bytes in each member's stored data
    (start, middle, end), in the zip's own headers, truncations, zero length, garbage."""
    raw = src.read_bytes()

    def put(data: bytes) -> Callable[[Path], None]:
        return lambda dst: dst.write_bytes(data)

    def flipped(at: int) -> bytes:
        b = bytearray(raw)
        b[at] ^= 0x10
        return bytes(b)

    out: list[tuple[str, Callable[[Path], None]]] = []
    spans = member_spans(src)
    for i, (name, start, length) in enumerate(spans):
        if length == 0 or (quick and i % 3):
            continue
        positions = sorted({start, start + length // 2, start + length - 1})
        for at in positions if not quick else positions[1:2]:
            out.append((f"flip byte {at - start} of {name}'s stored data", put(flipped(at))))
    cd = raw.rfind(b"PK\x01\x02")
    eocd = raw.rfind(b"PK\x05\x06")
    out += [("flip the local header's CRC byte of the first member", put(flipped(14))),
            ("flip a byte of the last central-directory entry's size", put(flipped(cd + 20))),
            ("flip the end record's central-directory offset", put(flipped(eocd + 16)))]
    for label, keep in (("zero-length file", 0), ("truncated to 1 byte", 1), ("truncated to half", len(raw) // 2),
                        ("truncated to 90%", len(raw) * 9 // 10), ("last byte cut", len(raw) - 1),
                        ("end record cut off", len(raw) - 22)):
        out.append((label, put(raw[:keep])))
    out += [("garbage appended (1000 bytes)", put(raw + os.urandom(1000))),
            ("garbage prepended (100 bytes)", put(os.urandom(100) + raw)),
            ("random bytes of the same length", put(os.urandom(len(raw)))),
            ("a text file", put(b"this is not an npz file\n" * 10))]
    return out


def value_variants(arr: Any, quick: bool) -> list[tuple[str, Any]]:
    """Wrong values, dtypes and shapes of one array: ``(label, new array)``."""
    import numpy as np

    a = np.asarray(arr)
    out: list[tuple[str, Any]] = []
    kind = a.dtype.kind
    if a.size:
        def at0(v: Any, where: int = 0) -> Any:
            b = a.copy()
            b.reshape(-1)[where] = v
            return b

        if kind == "f":
            out += [("NaN", at0(np.nan)), ("inf", at0(np.inf)), ("1e38", at0(1e38 if a.dtype.itemsize > 2 else
                                                                         np.inf))]
            if not quick:
                out += [("-inf", at0(-np.inf)), ("-1e38", at0(-1e38 if a.dtype.itemsize > 2 else -np.inf)),
                        ("negative", at0(-abs(float(a.reshape(-1)[0])) - 1.0)),
                        ("all zero", np.zeros_like(a)), ("last value +1", at0(a.reshape(-1)[-1] + 1, -1))]
        elif kind in "iu":
            info = np.iinfo(a.dtype)
            out += [("-1", at0(-1 if kind == "i" else info.max)), ("max int", at0(info.max))]
            if not quick:
                out += [("last value +1", at0(a.reshape(-1)[-1] + 1, -1)), ("all zero", np.zeros_like(a)),
                        ("min int", at0(info.min))]
        elif kind == "b":
            out += [("a flag flipped", at0(not a.reshape(-1)[0]))]
    if kind == "U":
        out += [("empty string", np.array("")), ("another string", np.array(str(a[()]) + "x"))]
        if not quick:
            out += [("a 2 MB string", np.array("x" * (2 << 20))), ("bytes, not str", np.array(str(a[()]).encode()))]
    # dtypes
    swaps = {"f8": "f4", "f4": "f8", "f2": "f4", "i8": "i4", "i4": "i8", "u1": "i4", "b1": "u1"}
    code = f"{kind}{a.dtype.itemsize}"
    if code in swaps:
        out.append((f"dtype {swaps[code]}", a.astype(swaps[code])))
    if kind in "iub" and not quick:
        out.append(("dtype f8", a.astype("f8")))
    if kind == "f" and not quick:
        out.append(("dtype i8", a.astype("i8") if np.isfinite(a).all() else np.zeros(a.shape, "i8")))
    # shapes
    if a.ndim >= 1 and len(a) >= 1:
        out.append(("one row short", a[:-1]))
    out.append(("an extra leading axis", a[None]))
    if not quick:
        if a.ndim == 0:
            out.append(("1-d instead of a scalar", a.reshape(1)))
        if a.ndim == 2:
            out.append(("flattened", a.reshape(-1)))
            if a.shape[0] != a.shape[1]:
                out.append(("transposed", np.ascontiguousarray(a.T)))
        if a.ndim >= 1:
            out.append(("empty", a[:0]))
            out.append(("one row more", np.concatenate([a, a[-1:]]) if len(a) else a))
    return out


def header_variants(npy: bytes, quick: bool) -> list[tuple[str, bytes]]:
    """Crafted ``.npy`` headers over the member's own data: huge shapes, reinterpreting dtypes, byte order,
    Fortran order."""
    import numpy as np

    fh = io.BytesIO(npy)
    version = np.lib.format.read_magic(fh)
    reader = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
    shape, fortran, dtype = reader(fh)
    out = [("header claims a huge array", npy_recrafted(npy, shape=(1 << 40,) + tuple(shape[1:]) if shape
                                                           else (1 << 40,)))]
    if not quick:
        out.append(("header claims 2^31 x 2^31", npy_recrafted(npy, shape=(1 << 31, 1 << 31))))
    same = {"<f8": "<i8", "<i8": "<f8", "<f4": "<i4", "<i4": "<f4", "|u1": "|i1", "|b1": "|u1", "<f2": "<i2"}
    descr = np.lib.format.dtype_to_descr(dtype)
    if isinstance(descr, str) and descr in same:
        out.append((f"header dtype {descr} -> {same[descr]} (same size, data reinterpreted)",
                    npy_recrafted(npy, descr=same[descr])))
    if isinstance(descr, str) and descr[0] == "<" and not quick:
        out.append(("header byte order flipped", npy_recrafted(npy, descr=">" + descr[1:])))
    if len(shape) == 2 and shape[0] > 1 and shape[1] > 1:
        out.append(("header fortran_order flipped", npy_recrafted(npy, fortran_order=not fortran)))
    if not quick:
        out.append(("header shape one element short", npy_recrafted(npy, shape=(shape[0] - 1,) + tuple(shape[1:])
                                                                     if shape and shape[0] else (0,))))
    return out


def npz_mutations(src: Path, redigest: Callable[[dict], dict], marker: Path, quick: bool,
                  keys: list[str] | None = None, allowed: Callable[[str, Any], bool] | None = None,
                  family: str = "") -> list[tuple[str, Callable[[Path], None]]]:
    """Every mutation of one ``.npz`` (raw bytes, crafted members and headers, wrong values / dtypes / shapes,
    missing, extra and duplicated keys, pickle payloads). ``redigest(arrays)`` returns the arrays with their
    digest(s) recomputed (a forger's copy, or a buggy writer's); each value change is made both with the old
    digest kept ("stale": what damage on disk does) and with a fresh one ("fresh": only the content checks can
    refuse it). ``keys``: the arrays to change (default: all)."""
    import numpy as np

    from cuniform_torch.common.fileio import write_npz

    members = npz_members(src)
    with np.load(src, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    muts = list(raw_mutations(src, quick))

    def arrays_to(new: dict, mode: str) -> Callable[[Path], None]:
        def write(dst: Path) -> None:
            write_npz(dst, redigest(dict(new)) if mode == "fresh" else new)
        return write

    def crafted(new_members: list[tuple[str, bytes]]) -> Callable[[Path], None]:
        return lambda dst: zip_write(dst, new_members)

    digest_keys = [k for k in arrays if k.startswith("content_sha256")]
    for key in [k for k in (keys or list(arrays)) if k in arrays]:
        if key in digest_keys:
            continue
        for label, value in value_variants(arrays[key], quick):
            for mode in ("stale", "fresh"):
                if mode == "fresh" and allowed is not None and allowed(key, value):
                    SKIPPED[family] = SKIPPED.get(family, 0) + 1  # a valid file of other content
                    continue
                muts.append((f"{key}: {label} ({mode} digest)", arrays_to({**arrays, key: value}, mode)))
        for mode in ("stale", "fresh"):
            if mode == "fresh" and allowed is not None and allowed(key, MISSING):
                SKIPPED[family] = SKIPPED.get(family, 0) + 1  # an optional key left out: a valid file
                continue
            muts.append((f"{key}: missing ({mode} digest)",
                         arrays_to({k: v for k, v in arrays.items() if k != key}, mode)))
        idx = next(i for i, (n, _) in enumerate(members) if n == f"{key}.npy")
        for label, npy in header_variants(members[idx][1], quick):
            muts.append((f"{key}: {label}", crafted(members[:idx] + [(f"{key}.npy", npy)] + members[idx + 1:])))
        evil = npy_bytes(np.array([Evil(marker)], dtype=object), allow_pickle=True)
        muts.append((f"{key}: an object array with a pickle payload",
                     crafted(members[:idx] + [(f"{key}.npy", evil)] + members[idx + 1:])))
        if not quick or key == next(iter(arrays)):
            other = value_variants(arrays[key], True)[0][1]
            muts.append((f"{key}: a second member of the same name (changed)",
                         crafted(members + [(f"{key}.npy", npy_bytes(other))])))
    evil = npy_bytes(np.array([Evil(marker)], dtype=object), allow_pickle=True)
    muts += [("an extra object-array member with a pickle payload", crafted(members + [("zz_evil.npy", evil)])),
             ("an extra unknown key (stale digest)", arrays_to({**arrays, "zz_extra": np.arange(3.0)}, "stale")),
             ("an extra unknown key (fresh digest)", arrays_to({**arrays, "zz_extra": np.arange(3.0)}, "fresh")),
             ("a member that is not .npy", crafted(members + [("notes.txt", b"hello")])),
             ("stored instead of deflated", lambda dst: zip_write(dst, members, zipfile.ZIP_STORED))]
    if digest_keys:
        muts += [("digest(s) removed (an old file)", arrays_to({k: v for k, v in arrays.items()
                                                                if k not in digest_keys}, "stale")),
                 ("digest malformed", arrays_to({**arrays, **{k: np.array("0" * 63 + "g") for k in digest_keys}},
                                                "stale")),
                 ("digest of another file", arrays_to({**arrays, **{k: np.array("0" * 64) for k in digest_keys}},
                                                      "stale"))]
    return muts


# --------------------------------------------------------------------------------------------------- JSON crafting

JSON_VALUES: list[tuple[str, Any]] = [("null", None), ("a string", "x"), ("a list", []), ("an object", {}),
                                      ("true", True), ("NaN", math.nan), ("inf", math.inf), ("-1", -1), ("0", 0),
                                      ("1e38", 1e38), ("10^30", 10**30), ("-1e38", -1e38)]
QUICK_JSON_VALUES = ("null", "a string", "NaN", "-1", "1e38")


def json_paths(obj: Any, depth: int = 3, at: tuple = ()) -> list[tuple]:
    """Paths (keys / indices) into ``obj``: every key of every object, index 0 (and the last) of every list."""
    out: list[tuple] = []
    if depth == 0:
        return out
    if isinstance(obj, dict):
        for k, v in obj.items():
            out.append(at + (k,))
            out += json_paths(v, depth - 1, at + (k,))
    elif isinstance(obj, list) and obj:
        for i in sorted({0, len(obj) - 1}):
            out.append(at + (i,))
            out += json_paths(obj[i], depth - 1, at + (i,))
    return out


def json_edit(obj: Any, path: tuple, value: Any = None, delete: bool = False) -> Any:
    obj = json.loads(json.dumps(obj))
    parent = obj
    for k in path[:-1]:
        parent = parent[k]
    if delete:
        del parent[path[-1]]
    else:
        parent[path[-1]] = value
    return obj


MISSING = object()
"""an oracle's value for a deleted key"""
SKIPPED: dict[str, int] = {}
"""per family: the edits its contract allows (a valid file of other content), not tried"""


def json_mutations(obj: Any, quick: bool, allowed: Callable[[tuple, Any], bool] | None = None,
                   family: str = "") -> list[tuple[str, bytes]]:
    """Wrong types and values at every path of a JSON document, and damaged texts: ``(label, file bytes)``.
    ``allowed(path, value)`` (value :data:`MISSING` for a deletion) is the family's contract (docs/formats.md):
    an edit it allows makes a valid document of other content, which no reader can refuse: it is not tried."""
    text = json.dumps(obj, indent=2)
    out: list[tuple[str, bytes]] = []
    values = [(n, v) for n, v in JSON_VALUES if not quick or n in QUICK_JSON_VALUES]
    ok = allowed or (lambda path, value: False)
    for path in json_paths(obj):
        where = "/".join(map(str, path))
        old = obj
        for k in path:
            old = old[k]
        edits = [("missing", MISSING)] + [(label, v) for label, v in values
                                          if not (v == old and (type(v) is type(old) or _same_number(v, old)))]
        if isinstance(old, list) and old:
            edits.append(("first item duplicated", [old[0], *old]))
        for label, value in edits:
            if ok(path, value):
                SKIPPED[family] = SKIPPED.get(family, 0) + 1
                continue
            new = json_edit(obj, path, delete=True) if value is MISSING else json_edit(obj, path, value)
            out.append((f"{where}: {label}", json.dumps(new).encode()))
    raw = text.encode()
    out += [("zero-length file", b""), ("truncated to half", raw[: len(raw) // 2]), ("not JSON", b"garbage{\n"),
            ("a JSON list, not an object", b"[1, 2, 3]"), ("a JSON string", b'"x"'),
            ("nested 100000 deep", b"[" * 100000 + b"]" * 100000), ("invalid UTF-8", raw[:-2] + b"\xff\xfe}"),
            ("a byte-order mark first", b"\xef\xbb\xbf" + raw)]
    if isinstance(obj, dict) and obj:
        first = next(iter(obj))
        out.append((f"{first!r} given twice (the second changed)", raw.rstrip()[:-1] + f', "{first}": "zz"}}'.encode()))
        out.append((f"{first!r} given twice (the first changed)", b'{"' + first.encode() + b'": "zz", ' + raw[1:]))
    return out


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _same_number(a: Any, b: Any) -> bool:
    """JSON has one number type: 0 and 0.0 are the same number (an edit that changes nothing)."""
    return all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in (a, b)) and a == b


def _is_num(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def settings_allowed(path: tuple, v: Any, doc: dict | None = None) -> bool:
    """What docs/formats.md allows in a benchmark folder's settings.json (the edits that stay valid); ``doc``: the
    document edited (gap widths must stay sorted and distinct)."""
    head = path[0]
    if head == "robot" and len(path) >= 2 and path[1] == "params":
        return len(path) > 2 or isinstance(v, dict)  # the params object is free-form; params must stay an object
    if head == "sources" and len(path) == 2:
        return v is MISSING or v is None  # a null source matches anything; a value is a 16-hex-digit prefix
    if path == ("sources",):  # an object of 16-hex-digit digests or nulls (an empty one: every source null)
        return isinstance(v, dict) and all(d is None or (isinstance(d, str) and len(d) == 16 and
                                                         all(c in "0123456789abcdef" for c in d)) for d in v.values())
    if head in ("gap_widths", "cost_to_go") and len(path) == 1 and v is MISSING:
        return True
    if head == "gap_widths" and len(path) == 2:
        widths = list((doc or {}).get("gap_widths", []))
        if v is MISSING:
            return len(widths) > 1  # one width fewer: a shorter sweep; none at all is not a sweep
        if not (_is_num(v) and v > 0) or doc is None:
            return False
        widths[path[1]] = v
        return all(a < b for a, b in zip(widths, widths[1:]))
    if isinstance(v, list) or v is MISSING:
        return False
    if head == "seed" and len(path) == 1:
        return _is_int(v)
    if path in (("horizon",), ("robot", "horizon")):
        return _is_int(v) and v >= 1
    if path == ("robot", "system"):
        return isinstance(v, str)
    if path == ("robot", "radius"):
        return _is_num(v) and v >= 0
    if head in ("sensing_range", "lambda_", "collision_penalty", "cost_resolution", "time_limit") and len(path) == 1:
        return _is_num(v) and v > 0
    return False


def record_allowed(path: tuple, v: Any) -> bool:
    """What docs/formats.md allows in an episodes.jsonl record without breaking its key or its outcome."""
    head = path[0]
    if head == "path":
        if len(path) == 1:
            return v is MISSING or (isinstance(v, list) and all(
                isinstance(q, list) and len(q) == 2 and all(map(_is_num, q)) for q in v))
        if len(path) == 2:
            return v is MISSING or (isinstance(v, list) and len(v) == 2 and all(map(_is_num, v)))
        return _is_num(v)
    if isinstance(v, list) or v is MISSING or len(path) != 1:
        return False
    if head in ("time", "path_length", "wall_s"):
        return _is_num(v) and v >= 0
    if head in ("seed", "steps", "cycles"):
        return _is_int(v) and v >= 0
    return False


def dataset_allowed(path: tuple, v: Any) -> bool:
    """dataset.json: the seed and an entry's source label are free; everything else must match the shards."""
    if path == ("seed",):
        return _is_int(v)
    return len(path) == 3 and path[0] == "entries" and path[2] == "source" and isinstance(v, str)


def index_allowed(path: tuple, v: Any) -> bool:
    """tables.json: a set with one table fewer is a valid (smaller) set."""
    return len(path) == 2 and path[0] == "tables" and v is MISSING


def system_json_variants(system_json: str, marker_module: str) -> list[tuple[str, str]]:
    """Hostile or wrong system JSON strings (the ``system`` key of tables, checkpoints, the data set)."""
    s = json.loads(system_json)
    return [("system: unknown name", json.dumps({**s, "name": "no_such_system"})),
            ("system: unknown name with a factory module", json.dumps({**s, "name": "evil_system",
                                                                        "factory": f"{marker_module}:make"})),
            ("system: its own name with a factory module", json.dumps({**s, "factory": f"{marker_module}:make"})),
            ("system: horizon 0", json.dumps({**s, "horizon": 0})),
            ("system: horizon 10^9", json.dumps({**s, "horizon": 10**9})),
            ("system: horizon + 1", json.dumps({**s, "horizon": s["horizon"] + 1})),
            ("system: params a list", json.dumps({**s, "params": [1, 2]})),
            ("system: an unknown param", json.dumps({**s, "params": {**s["params"], "zz": 1}})),
            ("system: a NaN param", json.dumps({**s, "params": {**s["params"], "dt": math.nan}})),
            ("system: dt 1e38", json.dumps({**s, "dt": 1e38})),
            *((f"system: {text[:60]}", text) for text, _ in _cases().SYSTEM_JSON_MALFORMED),
            ("system: nested 100000 deep", _cases().DEEP)]


def write_marker_module(folder: Path, marker: Path) -> str:
    """A module whose import writes ``marker`` (what a reader that imported a file's ``factory`` would run)."""
    (folder / "attack_evil_factory.py").write_text(f"open({str(marker)!r}, 'w').close()\n\ndef make(**kw):\n"
                                                   "    raise RuntimeError('never')\n")
    return "attack_evil_factory"


# --------------------------------------------------------------------------------------------------- families

@dataclasses.dataclass
class Family:
    """A family's original (``target``), its readers and its mutated copies."""

    name: str
    readers: list[str]
    target: Path
    cases: list[Case]


def _file_cases(name: str, folder: Path, original: Path, readers: list[str],
                muts: list[tuple[str, Callable[[Path], None]]]) -> list[Case]:
    """Each mutation written to its own copy of the file ``original``; one case per (mutation, reader)."""
    cases = []
    for i, (label, write) in enumerate(muts):
        dst = folder / f"{i:04d}{original.suffix}"
        try:
            write(dst)
        except Exception as exc:  # noqa: BLE001 - a mutation the writers cannot even make is left out, said
            print(f"  ({name}: could not make {label!r}: {type(exc).__name__}: {exc})")
            continue
        for reader in readers:
            cases.append(Case(name, label, str(dst), reader, size=_tree_size(dst)))
    return cases


def _folder_cases(name: str, folder: Path, original: Path, reader: str,
                  muts: list[tuple[str, Callable[[Path], None]]]) -> list[Case]:
    """Each mutation applied to its own copy of the folder ``original``."""
    cases = []
    folder.mkdir(parents=True, exist_ok=True)
    for i, (label, change) in enumerate(muts):
        dst = folder / f"{i:04d}"
        shutil.copytree(original, dst, symlinks=True)
        try:
            change(dst)
        except Exception as exc:  # noqa: BLE001
            print(f"  ({name}: could not make {label!r}: {type(exc).__name__}: {exc})")
            continue
        cases.append(Case(name, label, str(dst), reader, size=_tree_size(dst)))
    return cases


def _symlink_loop(path: Path) -> None:
    """``path`` replaced by a symlink that points at itself."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    elif path.exists() or path.is_symlink():
        path.unlink()
    path.symlink_to(path.name)


def _replace_by_folder(path: Path) -> None:
    if path.exists():
        path.unlink()
    path.mkdir()


def _replace_by_special(path: Path, target: str) -> None:
    """``path`` replaced by a FIFO (``target`` ``"fifo"``) or by a symlink to ``target`` (a device)."""
    if path.exists() or path.is_symlink():
        path.unlink()
    if target == "fifo":
        os.mkfifo(path)
    else:
        path.symlink_to(target)


def _broken(name: str, label: str | None = None, missing: bool = True) -> list[tuple[str, Callable[[Path], None]]]:
    """The file ``name`` of a folder missing (when ``missing``), a folder, a symlink loop, a FIFO, a symlink to
    ``/dev/zero`` or ``/dev/urandom``: the damaged-folder cases (labelled ``label``, default the name)."""
    label = label or name
    cases: list[tuple[str, Callable[[Path], None]]] = [(f"{label} missing", lambda dst: (dst / name).unlink())]
    return (cases if missing else []) + [
        (f"{label} is a folder", lambda dst: _replace_by_folder(dst / name)),
        (f"{label} is a symlink loop", lambda dst: _symlink_loop(dst / name)),
        (f"{label} is a FIFO", lambda dst: _replace_by_special(dst / name, "fifo")),
        (f"{label} links to /dev/zero", lambda dst: _replace_by_special(dst / name, "/dev/zero")),
        (f"{label} links to /dev/urandom", lambda dst: _replace_by_special(dst / name, "/dev/urandom"))]


def table_family(work: Path, quick: bool) -> Family:
    import numpy as np

    from cuniform_torch.systems import make_system
    from cuniform_torch.tables.file import table_digests, write_table
    from precompute.flow.builder import BuildConfig, build_table

    folder = work / "table"
    folder.mkdir()
    original = folder / "original.npz"
    write_table(original, build_table(make_system("dubins"), BuildConfig(horizon=2))[0])
    module = write_marker_module(folder, folder / "marker")

    def redigest(arrays: dict) -> dict:
        core = {k: v for k, v in arrays.items() if not k.startswith("content_sha256")}
        return {**core, **table_digests(core)}

    keys = ["format", "system", "actions", "level_offsets", "cells", "action_probs", "cell_probs", "start"] \
        if quick else None
    def allowed(key: str, a: Any) -> bool:  # docs/formats.md, table file: optional keys
        if key == "method":
            return a is MISSING  # optional; a present method must be a known one
        if key == "build_info":  # optional, "not checked": any string
            return a is MISSING or (np.asarray(a).dtype.kind == "U" and np.asarray(a).shape == ())
        return False

    muts = npz_mutations(original, redigest, folder / "marker", quick, keys, allowed, "table (.npz)")
    with np.load(original, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    from cuniform_torch.common.fileio import write_npz

    for label, text in system_json_variants(str(arrays["system"][()]), module):
        for mode in ("stale", "fresh"):
            new = {**arrays, "system": np.array(text)}
            muts.append((f"{label} ({mode} digest)",
                         (lambda n, m: lambda dst: write_npz(dst, redigest(n) if m == "fresh" else n))(new, mode)))
    core = {k: v for k, v in arrays.items() if not k.startswith("content_sha256")}

    def corrupted(mutate: Callable[[dict], None]) -> Callable[[Path], None]:
        def write(dst: Path) -> None:
            new = {k: np.array(v, copy=True) for k, v in core.items()}
            mutate(new)
            write_npz(dst, redigest(new))
        return write

    for label, mutate, _ in _cases().TABLE_CORRUPTIONS:  # tests/test_files_tables.py::test_corrupt_content's table
        muts.append((f"content: {label} (fresh digest)", corrupted(mutate)))
    for label, make, _ in _cases().UNREADABLE_TABLES:  # ...::test_an_unreadable_table_file_is_one_error's table
        muts.append((f"file: {label}", (lambda m: lambda dst: m(dst, original))(make)))
    readers = ["table", "table_policy"]
    return Family("table (.npz)", readers, original, _file_cases("table (.npz)", folder, original, readers, muts))


def local_map_family(work: Path, quick: bool) -> Family:
    import numpy as np

    from cuniform_torch.common.digest import DIGEST_KEY, content_digest
    from precompute.levels.safe_map import LocalMap, write_map_file

    folder = work / "local_map"
    folder.mkdir()
    original = folder / "original.npz"
    occ = np.zeros((30, 40), np.uint8)
    occ[10:14, 5:30] = 1
    write_map_file(original, LocalMap(occ, (-1.5, -2.0), 0.1))

    def redigest(arrays: dict) -> dict:
        core = {k: v for k, v in arrays.items() if k != DIGEST_KEY}
        return {**core, DIGEST_KEY: np.array(content_digest(core))}

    def allowed(key: str, a: Any) -> bool:  # docs/formats.md, local map file
        a = np.asarray(a)
        if key == "occupied":
            return a.dtype == np.uint8 and a.ndim == 2 and all(1 <= n <= 4096 for n in a.shape) and \
                bool(np.isin(a, (0, 1)).all())
        if key == "origin":
            return a.dtype == np.float64 and a.shape == (2,) and bool(np.isfinite(a).all())
        if key == "resolution":
            return a.dtype == np.float64 and a.shape == () and bool(np.isfinite(a)) and float(a) > 0
        return False

    muts = npz_mutations(original, redigest, folder / "marker", quick, allowed=allowed, family="local map (.npz)")
    return Family("local map (.npz)", ["local_map"], original,
                  _file_cases("local map (.npz)", folder, original, ["local_map"], muts))


# --- checkpoints

def _checkpoints() -> dict[str, tuple[Callable[[], dict], Callable[[Path, dict], None], str]]:
    """family -> (make a checkpoint dict, its saver, its reader): small networks of each policy kind."""
    import torch

    from cuniform_torch.maps.checkpoint import map_policy_checkpoint, save_map_policy
    from cuniform_torch.maps.encoder import PatchSpec
    from cuniform_torch.maps.policy import MapPolicy, MapPolicyConfig
    from cuniform_torch.policies.checkpoint import policy_checkpoint, save_policy
    from cuniform_torch.policies.mlp import MLPConfig, MLPPolicy
    from cuniform_torch.policies.start_mlp import StartMLPPolicy, StartRegion
    from cuniform_torch.systems import RandomWalk1D, make_system, system_to_json

    walk = RandomWalk1D()
    dubins = make_system("dubins", speed=1.0, dt=0.2, num_actions=5, max_omega=math.pi / 2,
                         cell_size=[0.1, 0.1, 2 * math.pi / 16])

    def mlp_config(**over: Any) -> MLPConfig:
        return MLPConfig(**{"state_dim": 1, "num_actions": 5, "horizon": 8, "periodic": [False],
                            "feature_scale": [4.0], "hidden": 8, "layers": 2, **over})

    def mlp() -> dict:
        torch.manual_seed(0)
        return policy_checkpoint(MLPPolicy(mlp_config(), walk, walk.action_set()), system_to_json(walk, 8))

    def start_mlp() -> dict:
        torch.manual_seed(0)
        region = StartRegion(torch.tensor([[-1.0], [0.0], [1.0]], dtype=torch.float64), [0])
        policy = StartMLPPolicy(mlp_config(start_dims=[0]), walk, walk.action_set(), region)
        return policy_checkpoint(policy, system_to_json(walk, 8))

    def map_policy() -> dict:
        torch.manual_seed(0)
        spec = PatchSpec((24, 24), 0.1, (-1.2, -1.2))
        config = MapPolicyConfig(state_dim=3, num_actions=5, horizon=4, periodic=[False, False, True],
                                 feature_scale=[0.8, 0.6, 1.0], patch=spec.to_dict(), hidden=16, layers=2, embed=8,
                                 channels=4)
        return map_policy_checkpoint(MapPolicy(config, dubins, dubins.action_set()), system_to_json(dubins, 4))

    return {"MLP policy (.pt)": (mlp, save_policy, "policy"),
            "start-MLP policy (.pt)": (start_mlp, save_policy, "policy"),
            "map policy (.pt)": (map_policy, save_map_policy, "map_policy")}


def _tensor_paths(ckpt: dict, at: tuple = ()) -> list[tuple]:
    import torch

    out = []
    for k, v in ckpt.items():
        if isinstance(v, torch.Tensor):
            out.append(at + (k,))
        elif isinstance(v, dict):
            out += _tensor_paths(v, at + (k,))
    return out


def _get(obj: Any, path: tuple) -> Any:
    for k in path:
        obj = obj[k]
    return obj


def _set(obj: Any, path: tuple, value: Any, delete: bool = False) -> Any:
    """A copy of the nested dict ``obj`` (dicts copied along ``path``) with ``value`` at ``path``."""
    out = dict(obj)
    if len(path) == 1:
        if delete:
            out.pop(path[0], None)
        else:
            out[path[0]] = value
        return out
    out[path[0]] = _set(obj[path[0]], path[1:], value, delete)
    return out


def tensor_allowed(path: tuple, old: Any, new: Any) -> bool:
    """docs/formats.md: a weight (not ``actions`` nor ``inv_scale``, which must match the system) of the same
    dtype and shape, finite and within MAX_ABS_WEIGHT, is another valid network; a start-MLP's starts of the same
    dtype and shape, finite and within MAX_ABS_START, another valid start region."""
    import numpy as np

    weight = len(path) == 2 and path[0] == "state_dict" and path[1] not in ("actions", "inv_scale")
    start = path == ("start_region", "starts")  # another valid region: finite starts within MAX_ABS_START (1e6)
    return ((weight or start) and new.dtype == old.dtype and new.shape == old.shape and bool(np.isfinite(new).all())
            and float(np.abs(new).max(initial=0)) <= 1e6)


def plain_allowed(path: tuple, v: Any) -> bool:
    """``source`` is free-form; ``metrics`` holds finite numbers or strings."""
    if path[0] == "source" and len(path) == 2:
        return True
    return path[0] == "metrics" and len(path) == 2 and (isinstance(v, str) or _is_num(v))


def checkpoint_family(name: str, work: Path, quick: bool) -> Family:
    import numpy as np
    import torch

    from cuniform_torch.common.digest import DIGEST_KEY

    make, save, reader = _checkpoints()[name]
    folder = work / name.split()[0].lower().replace("-", "_")
    folder.mkdir()
    original = folder / "original.pt"
    base = make()
    save(original, base)
    saved = torch.load(original, weights_only=True)
    module = write_marker_module(folder, folder / "marker")
    marker = folder / "marker"
    muts: list[tuple[str, Callable[[Path], None]]] = list(raw_mutations(original, quick))

    def dict_to(ckpt: dict, mode: str) -> Callable[[Path], None]:
        def write(dst: Path) -> None:
            if mode == "fresh":
                save(dst, {k: v for k, v in ckpt.items() if k != DIGEST_KEY})
            else:
                torch.save(ckpt, dst)
        return write

    tensor_paths = _tensor_paths(saved)
    if quick:
        tensor_paths = tensor_paths[:2] + tensor_paths[-2:]
    for path in tensor_paths:
        where = "/".join(path)
        value = _get(saved, path).numpy()
        for label, new in value_variants(value, quick):
            if np.asarray(new).dtype.kind not in "biuf":
                continue
            t = torch.from_numpy(np.ascontiguousarray(new))
            for mode in ("stale", "fresh"):
                if mode == "fresh" and tensor_allowed(path, value, np.asarray(new)):
                    SKIPPED[name] = SKIPPED.get(name, 0) + 1  # another valid network
                    continue
                muts.append((f"{where}: {label} ({mode} digest)", dict_to(_set(saved, path, t), mode)))
        for mode in ("stale", "fresh"):
            muts.append((f"{where}: missing ({mode} digest)", dict_to(_set(saved, path, None, delete=True), mode)))
    plain = [(k,) for k, v in saved.items() if not isinstance(v, (dict, torch.Tensor)) and k != DIGEST_KEY]
    plain += [("config", k) for k in saved["config"]]
    plain += [(k, kk) for k in ("source", "metrics") if isinstance(saved.get(k), dict) for kk in saved[k]][:4]
    if "start_region" in saved:
        plain.append(("start_region", "dims"))
    values = [(n, v) for n, v in JSON_VALUES if not quick or n in QUICK_JSON_VALUES]
    for path in plain:
        where = "/".join(path)
        for label, value in values:
            for mode in ("stale", "fresh"):
                if mode == "fresh" and plain_allowed(path, value):
                    SKIPPED[name] = SKIPPED.get(name, 0) + 1
                    continue
                muts.append((f"{where}: {label} ({mode} digest)", dict_to(_set(saved, path, value), mode)))
        muts.append((f"{where}: missing (fresh digest)", dict_to(_set(saved, path, None, delete=True), "fresh")))
    for label, text in system_json_variants(saved["system"], module):
        for mode in ("stale", "fresh"):
            muts.append((f"{label} ({mode} digest)", dict_to({**saved, "system": text}, mode)))
    for key in [k for k in saved if k != DIGEST_KEY]:
        if isinstance(saved[key], dict):
            muts.append((f"{key}: missing (fresh digest)", dict_to({k: v for k, v in saved.items() if k != key},
                                                                   "fresh")))
    muts += [
        ("an extra top-level key (fresh digest)", dict_to({**saved, "zz_extra": 1}, "fresh")),
        ("an extra state_dict tensor (fresh digest)",
         dict_to(_set(saved, ("state_dict", "zz.weight"), torch.zeros(2, 2)), "fresh")),
        ("config: hidden 8192, layers 32 (fresh digest)",
         dict_to(_set(_set(saved, ("config", "hidden"), 8192), ("config", "layers"), 32), "fresh")),
        ("a list, not a dict", dict_to([1, 2, 3], "stale")),  # type: ignore[arg-type]
        ("a tensor, not a dict", dict_to(torch.zeros(3), "stale")),  # type: ignore[arg-type]
        ("digest removed (an old file)", dict_to({k: v for k, v in saved.items() if k != DIGEST_KEY}, "stale")),
        ("digest malformed", dict_to({**saved, DIGEST_KEY: "0" * 63 + "g"}, "stale")),
        ("digest of another file", dict_to({**saved, DIGEST_KEY: "0" * 64}, "stale")),
        ("pickle payload in metrics", lambda dst: torch.save({**saved, "metrics": Evil(marker)}, dst)),
        ("pickle payload as the whole file", lambda dst: torch.save(Evil(marker), dst)),
        ("pickle payload, legacy (non-zip) torch format",
         lambda dst: torch.save({**saved, "metrics": Evil(marker)}, dst, _use_new_zipfile_serialization=False)),
        ("a plain pickle with a payload", lambda dst: dst.write_bytes(__import__("pickle").dumps(Evil(marker)))),
        ("a bfloat16 state_dict tensor (fresh digest)",
         dict_to(_set(saved, tensor_paths[0], _get(saved, tensor_paths[0]).to(torch.bfloat16)), "fresh")),
        ("a sparse state_dict tensor (stale digest)",
         dict_to(_set(saved, tensor_paths[0], _get(saved, tensor_paths[0]).to_sparse()), "stale")),
    ]
    return Family(name, [reader], original, _file_cases(name, folder, original, [reader], muts))


# --- folders

def map_dataset_family(work: Path, quick: bool) -> Family:
    import numpy as np

    from cuniform_torch.common.digest import DIGEST_KEY, content_digest
    from precompute.maps.dataset import file_sha256
    from precompute.maps.farm import main as farm_main

    folder = work / "map_dataset"
    folder.mkdir()
    original = folder / "original"
    rc = farm_main(["--suite", "barn", "--count", "2", "--poses-per-map", "2", "--split", "train", "--seed", "0",
                    "--horizon", "3", "--patch", "20", "20", "--quiet", "--out", str(original)])
    assert rc == 0, "the farm failed to write the original data set"
    (original / "farm-progress.json").unlink(missing_ok=True)
    meta = json.loads((original / "dataset.json").read_text())
    shard = "shard-00000.npz"

    def redigest(arrays: dict) -> dict:
        core = {k: v for k, v in arrays.items() if k != DIGEST_KEY}
        return {**core, DIGEST_KEY: np.array(content_digest(core))}

    def index_sha(dst: Path, k: int = 0) -> None:
        m = json.loads((dst / "dataset.json").read_text())
        m["shards"][k]["sha256"] = file_sha256(dst / m["shards"][k]["file"])
        (dst / "dataset.json").write_text(json.dumps(m))

    muts: list[tuple[str, Callable[[Path], None]]] = []
    for label, data in json_mutations(meta, quick, dataset_allowed, "map data set (folder)"):
        muts.append((f"dataset.json {label}", (lambda d: lambda dst: (dst / "dataset.json").write_bytes(d))(data)))
    module = write_marker_module(folder, folder / "marker")
    for label, text in system_json_variants(meta["system"], module):
        muts.append((f"dataset.json {label}",
                     (lambda t: lambda dst: (dst / "dataset.json").write_text(json.dumps({**meta, "system": t})))(text)))
    shard_muts = npz_mutations(original / shard, redigest, folder / "marker", quick)
    for label, write in shard_muts:
        def change(dst: Path, write: Callable[[Path], None] = write) -> None:
            write(dst / shard)
            index_sha(dst)
        muts.append((f"{shard} {label} (index sha256 updated)", change))
    for label, write in raw_mutations(original / shard, True)[:6]:
        muts.append((f"{shard} {label} (index sha256 kept)",
                     (lambda w: lambda dst: w(dst / shard))(write)))

    def swap_shards(dst: Path) -> None:
        a, b = dst / "shard-00000.npz", dst / "shard-00001.npz"
        tmp = dst / "tmp"
        a.rename(tmp)
        b.rename(a)
        tmp.rename(b)
        index_sha(dst, 0)
        index_sha(dst, 1)

    def entries_twice(dst: Path) -> None:
        m = json.loads((dst / "dataset.json").read_text())
        m["shards"] = m["shards"] + [dict(m["shards"][0])]
        m["entries"] = m["entries"] + [dict(e, shard=len(m["shards"]) - 1) for e in m["entries"]
                                       if e["shard"] == 0]
        (dst / "dataset.json").write_text(json.dumps(m))

    def foreign_shard(dst: Path) -> None:
        shutil.copy(work / "table" / "original.npz", dst / shard) if (work / "table").exists() else \
            (dst / shard).write_bytes(b"")
        index_sha(dst)

    muts += [("the two shards swapped (index sha256s updated)", swap_shards),
             ("a shard listed twice (entries duplicated)", entries_twice),
             ("a table file in place of a shard (sha256 updated)", foreign_shard),
             *_broken(shard, "a shard"), *_broken("dataset.json"),
             ("an unknown file in the folder", lambda dst: (dst / "notes.txt").write_text("hello")),
             ("the folder is a symlink loop", lambda dst: _symlink_loop(dst))]
    return Family("map data set (folder)", ["map_dataset"], original,
                  _folder_cases("map data set (folder)", folder, original, "map_dataset", muts))


def table_set_family(work: Path, quick: bool) -> Family:
    import numpy as np

    from cuniform_torch.systems import make_system
    from precompute.flow.builder import BuildConfig
    from precompute.one_table import TableJob
    from precompute.table_set import build_table_set

    folder = work / "table_set"
    folder.mkdir()
    original = folder / "original"
    walk = make_system("random_walk_1d")
    build_table_set(TableJob(system=walk, out=folder / "x.npz", build=BuildConfig(horizon=3), report=False,
                             quiet=True), np.array([[0.0], [0.5], [-0.5]]), original)
    for p in original.glob("*.report.json"):
        p.unlink()
    (original / ".lock").unlink(missing_ok=True)
    index = json.loads((original / "tables.json").read_text())
    other = folder / "other"
    build_table_set(TableJob(system=make_system("random_walk_1d", dt=0.2), out=folder / "y.npz",
                             build=BuildConfig(horizon=3), report=False, quiet=True), np.array([[0.5]]), other)

    def put(name: str, data: bytes) -> Callable[[Path], None]:
        return lambda dst: (dst / name).write_bytes(data)

    def edit(**entry0: Any) -> Callable[[Path], None]:
        return put("tables.json", json.dumps({**index, "tables": [{**index["tables"][0], **entry0},
                                                                   *index["tables"][1:]]}).encode())

    muts: list[tuple[str, Callable[[Path], None]]] = [(f"tables.json {label}", put("tables.json", data))
                                                      for label, data in json_mutations(index, quick, index_allowed,
                                                                                        "table set (folder)")]
    member = "start_0001.npz"
    for label, write in raw_mutations(original / member, True):
        muts.append((f"{member} {label}", (lambda w: lambda dst: w(dst / member))(write)))
    starts = [e["start"] for e in index["tables"]]
    muts += [
        ("entry 0's file '../original/start_0000.npz'", edit(file="../original/start_0000.npz")),
        ("entry 0's file an absolute path", edit(file=str((original / "start_0000.npz").resolve()))),
        ("entry 0's file '..'", edit(file="..")),
        ("entry 0's file '.'", edit(file=".")),
        ("entry 0's file the index itself", edit(file="tables.json")),
        ("entry 0 lists start_0001.npz (twice listed)", edit(file="start_0001.npz")),
        ("entry 0's start 1e38", edit(start=[1e38])),
        ("entry 0's start NaN", edit(start=[math.nan])),
        ("entry 0's start a string", edit(start="0")),
        ("entry 0's start nested", edit(start=[[0.0]])),
        ("entry 0's start has 2 dimensions", edit(start=[0.0, 0.0])),
        ("entries 0 and 1 swap starts", put("tables.json", json.dumps({**index, "tables": [
            {**index["tables"][0], "start": starts[1]}, {**index["tables"][1], "start": starts[0]},
            *index["tables"][2:]]}).encode())),
        ("an entry listed twice", put("tables.json", json.dumps({**index, "tables": index["tables"] +
                                                                  index["tables"][:1]}).encode())),
        ("member 0 replaced by member 1's file", lambda dst: shutil.copy(dst / member, dst / "start_0000.npz")),
        ("member 1 replaced by a table of another system (dt 0.2)",
         lambda dst: shutil.copy(other / "start_0000.npz", dst / member)),
        *_broken(member, "member 1"), *_broken("tables.json"),
        ("the folder is a symlink loop", lambda dst: _symlink_loop(dst)),
        ("an unknown file in the folder", lambda dst: (dst / "notes.txt").write_text("hello")),
    ]
    return Family("table set (folder)", ["table_set"], original,
                  _folder_cases("table set (folder)", folder, original, "table_set", muts))


BENCH_SETTINGS = dict(suite="gaps", seed=0, sensing_range=3.0, horizon=6, lambda_=0.5, collision_penalty=1e6,
                      cost_resolution=0.01,
                      robot=dict(system="dubins", params=dict(speed=0.5, dt=0.2), radius=0.2, horizon=6),
                      time_limit=30.0, barn_file=None,
                      sources=dict(table="0123456789abcdef", coverage_table=None, policy=None), gap_widths=[0.6, 1.2])
"""the benchmark family's settings.json"""
BENCH_RECORD = dict(key="gaps/0/mppi_1.0/16/0", suite="gaps", task_id=0, method="mppi_1.0", budget=16, seed=7,
                    repeat=0, outcome="goal", success=True, time=3.2, path_length=1.6, steps=16, cycles=16,
                    cycle_hist={"120": 16}, wall_s=0.4, path=[[0.0, 0.0], [0.1, 0.0]])
"""a record of the benchmark family"""
LEFT_OUT_WORDS = ("left out", "dropping an incomplete last line")
"""how a reader says what it left out (a reader: ``left out``; a run opening its folder drops a cut-short last line,
whose episode it then runs again)"""
WRITING_READERS = {"bench_append"}
"""readers that write into what they are given: the original is probed on a copy of its own"""


def bench_family(work: Path, quick: bool) -> Family:
    from eval.navigate.records.store import EpisodeStore

    folder = work / "bench"
    folder.mkdir()
    original = folder / "original"
    settings = BENCH_SETTINGS
    store = EpisodeStore(original)
    store.open(settings)

    def record(task: int, method: str = "mppi_1.0", outcome: str = "goal") -> dict:
        return {**BENCH_RECORD, "key": f"gaps/{task}/{method}/16/0", "task_id": task, "method": method,
                "seed": 7 + task, "outcome": outcome, "success": outcome == "goal"}

    records = [record(0), record(1, outcome="collision"), record(0, method="cu_table")]
    for r in records:
        store.append(r)
    lines = (original / "episodes.jsonl").read_bytes().split(b"\n")[:-1]

    def put(name: str, data: bytes) -> Callable[[Path], None]:
        return lambda dst: (dst / name).write_bytes(data)

    def with_line(line: bytes, at: int = 1, replace: bool = True) -> bytes:
        new = list(lines)
        new[at:at + 1] = [line] if replace else [lines[at], line]
        return b"\n".join(new) + b"\n"

    muts: list[tuple[str, Callable[[Path], None]]] = [(f"settings.json {label}", put("settings.json", data))
                                                      for label, data in json_mutations(
                                                          settings, quick, lambda p, v: settings_allowed(p, v, settings),
                                                          "benchmark folder")]
    for label, data in json_mutations(records[1], quick, record_allowed, "benchmark folder"):
        if label.startswith("zero-length"):
            continue  # an empty line: the record deleted, a valid folder of fewer episodes
        if label.startswith(("truncated", "not JSON", "invalid UTF-8", "a byte-order", "nested")):
            data = data.replace(b"\n", b" ")
        elif not label.startswith(("a JSON", "'")):
            data = json.dumps(json.loads(data), separators=(",", ":")).encode()
        muts.append((f"episodes.jsonl line 2 {label}", put("episodes.jsonl", with_line(data.replace(b"\n", b" ")))))
    muts += [
        ("episodes.jsonl line 2 exactly twice", put("episodes.jsonl", with_line(lines[1], replace=False))),
        ("episodes.jsonl line 2 twice, the copy another outcome", put("episodes.jsonl", with_line(
            json.dumps({**records[1], "outcome": "timeout"}, separators=(",", ":")).encode(), replace=False))),
        ("episodes.jsonl a record of another suite", put("episodes.jsonl", with_line(json.dumps(
            {**records[1], "suite": "barn", "key": "barn/1/mppi_1.0/16/0"}, separators=(",", ":")).encode()))),
        ("episodes.jsonl line 2 cut short", put("episodes.jsonl", with_line(lines[1][:40]))),
        ("episodes.jsonl the last line cut short", put("episodes.jsonl", b"\n".join(lines[:-1]) + b"\n" +
                                                       lines[-1][:40])),
        ("episodes.jsonl CRLF line ends", put("episodes.jsonl", b"\r\n".join(lines) + b"\r\n")),
        ("episodes.jsonl a NUL byte in a line", put("episodes.jsonl", with_line(lines[1][:20] + b"\0" +
                                                                            lines[1][20:]))),
        ("episodes.jsonl time 1e999", put("episodes.jsonl", with_line(lines[1].replace(b'"time":3.2',
                                                                                       b'"time":1e999')))),
        *_broken("episodes.jsonl", missing=False),
        ("settings.json missing (records left)", lambda dst: (dst / "settings.json").unlink()),
        *_broken("settings.json", missing=False),
        ("the folder is a symlink loop", lambda dst: _symlink_loop(dst)),
        ("episodes.jsonl links into another benchmark folder",
         lambda dst: _replace_by_special(dst / "episodes.jsonl", str((original / "episodes.jsonl").resolve()))),
        ("settings.json links into another benchmark folder",
         lambda dst: _replace_by_special(dst / "settings.json", str((original / "settings.json").resolve()))),
        ("episodes.jsonl links to /dev/null", lambda dst: _replace_by_special(dst / "episodes.jsonl", "/dev/null")),
        ("an unknown file in the folder", lambda dst: (dst / "notes.txt").write_text("hello")),
    ]
    return Family("benchmark folder", ["bench", "bench_append"], original,
                  [case for reader in ("bench", "bench_append")
                   for case in _folder_cases("benchmark folder", folder / reader, original, reader, muts)])


FAMILIES: dict[str, Callable[[Path, bool], Family]] = {
    "table": table_family,
    "table_set": table_set_family,
    "mlp": lambda w, q: checkpoint_family("MLP policy (.pt)", w, q),
    "start_mlp": lambda w, q: checkpoint_family("start-MLP policy (.pt)", w, q),
    "map_policy": lambda w, q: checkpoint_family("map policy (.pt)", w, q),
    "map_dataset": map_dataset_family,
    "local_map": local_map_family,
    "bench": bench_family,
}


# --------------------------------------------------------------------------------------------------- entry points

PATH_FLAGS = {"--table", "--table15", "--coverage-table", "--policy", "--map-policy", "--barn-file", "--barn-worlds",
              "--set", "--checkpoint", "--maps", "--tables", "--map"}
"""flags that name an input file or folder"""
INPUT_FOLDER_OUT = {"eval.navigate.compare", "eval.navigate.failures", "eval.navigate.replay"}
"""commands whose ``--out`` is a benchmark folder to read"""


def entry_cases(work: Path, quick: bool) -> list[Case]:
    """tests/test_entry_points.py's bad-value cases (every command, every flag of the bad-input classes), then
    a missing path, an empty folder, an empty file, a FIFO and a link to ``/dev/zero`` for every flag (and
    positional) that names an input, and a link to ``/dev/null`` for every ``--out`` / ``--json`` output."""
    sys.path.insert(0, str(REPO / "tests"))
    import pytest
    import test_entry_points as tep

    folder = work / "entry"
    folder.mkdir()
    (folder / "empty_folder").mkdir()
    (folder / "empty_file.npz").write_bytes(b"")
    bad_paths = [("a missing path", str(folder / "missing.npz")), ("an empty folder", str(folder / "empty_folder")),
                 ("an empty file", str(folder / "empty_file.npz"))]
    os.mkfifo(folder / "fifo.npz")
    (folder / "zero.npz").symlink_to("/dev/zero")
    (folder / "null.json").symlink_to("/dev/null")  # never /dev/null itself: a regression run as root replaces it
    special = [("a FIFO", str(folder / "fifo.npz")), ("a link to /dev/zero", str(folder / "zero.npz"))]
    cases = []
    for i, param in enumerate(tep.CASES):
        name, option, value = param.values
        if quick and i % 3:
            continue
        known = " (a known xfail of tests/test_entry_points.py)" if param.marks else ""
        cases.append(Case("entry points", f"{name} {option} {value}{known}", argv=[name, option, value]))
    mp = pytest.MonkeyPatch()
    try:
        for name in tep.COMMANDS:
            for action in tep.parser_of(name, mp)._actions:
                flags = [o for o in action.option_strings if o in PATH_FLAGS or
                         (o == "--out" and name in INPUT_FOLDER_OUT)]
                positional = not action.option_strings and action.dest not in ("help",)
                outputs = [o for o in action.option_strings if o == "--json" or
                           (o == "--out" and name not in INPUT_FOLDER_OUT)]
                if outputs:  # an output naming a device: refused before any work, never replaced
                    argv = [name, outputs[0], str(folder / "null.json")]
                    cases.append(Case("entry points", f"{' '.join(argv[:-1])} <a link to /dev/null>", argv=argv))
                if not flags and not positional:
                    continue
                for label, value in (bad_paths[:1] if quick else bad_paths) + special:
                    if label == "a missing path":  # its own: a command that builds a missing file (a cache) may
                        value = str(folder / f"missing_{len(cases)}.npz")  # not serve the next case from it
                    argv = [name, flags[0], value] if flags else [name, value]
                    cases.append(Case("entry points", f"{' '.join(argv[:-1])} <{label}>", argv=argv))
    finally:
        mp.undo()
    return cases


# --------------------------------------------------------------------------------------------------- issue 38's calls

def run_call_case(case: Case, call: Callable[[], Any], errors: tuple[type, ...], match: str | None, workdir: Path,
                  timeout: float, watch: list[Path]) -> None:
    """``call()`` in a forked child: raising one of ``errors`` (whose message matches ``match``) is a clear error,
    another exception a traceback, returning a silent wrong (every call here is one that must be refused)."""
    import re

    result = workdir / "result.json"
    if result.exists():
        result.unlink()
    before = snapshot(watch)

    def child() -> int:
        try:
            call()
            out = {"status": "accepted"}
        except BaseException as exc:  # noqa: BLE001 - classified by the parent
            out = {"status": "raised", "type": f"{type(exc).__module__}.{type(exc).__qualname__}",
                   "family": isinstance(exc, errors) and (match is None or re.search(match, str(exc)) is not None),
                   "message": str(exc)[:3000]}
        result.write_text(json.dumps(out))
        return 0

    how, code, case.peak_mb, case.seconds = _fork(child, workdir, timeout)
    case.left, case.lost = list(_LEFT), lost_since(before)
    if how != "exit" or not result.exists():
        case.outcome, case.detail = "crash/hang", f"{how} {code}"
        return
    out = json.loads(result.read_text())
    if out["status"] == "accepted":
        case.outcome, case.detail = "silent wrong", "accepted"
    elif out["family"]:
        case.outcome, case.detail = "clear error", out["message"].splitlines()[0][:300]
    else:
        case.outcome, case.detail = "traceback", f"{out['type']}: {out['message'][:300]}"


def _parametrized(test: Any) -> list[tuple]:
    """The argument tuples of a test's ``pytest.mark.parametrize`` (its table of cases)."""
    (mark,) = [m for m in getattr(test, "pytestmark", []) if m.name == "parametrize"]
    names = mark.args[0] if isinstance(mark.args[0], (list, tuple)) else mark.args[0].split(",")
    rows = [v.values if type(v).__name__ == "ParameterSet" else v for v in mark.args[1]]
    return [tuple(v) if len(names) > 1 else (v,) for v in rows]


def issue38_calls(work: Path, quick: bool) -> list[tuple[Case, Callable[[], Any], tuple[type, ...], str | None]]:
    """Issue 38's runaway counts, edited cards, misbehaving user systems and gymnasium actions, as calls; the user
    systems and the gymnasium actions are the tables of tests/test_user_step_probe.py and tests/test_gym_env.py."""
    import torch

    import cuniform_torch.maps.pretrained as pretrained
    from cuniform_torch import MPPI
    from cuniform_torch.envs.environment import Environment
    from cuniform_torch.envs.sim import simulate
    from cuniform_torch.maps import load_map_policy
    from cuniform_torch.policies.table_set import MAX_SET_TABLES, load_table_set
    from cuniform_torch.systems import make_system
    from cuniform_torch.tables.file import TableError

    sys.path.insert(0, str(REPO / "tests"))
    import test_user_step_probe as probe

    folder = work / "calls"
    folder.mkdir()
    calls: list[tuple[Case, Callable[[], Any], tuple[type, ...], str | None]] = []

    def add(family: str, label: str, call: Callable[[], Any], errors: tuple[type, ...], match: str | None = None,
            target: Path | None = None) -> None:
        size = _tree_size(target) if target is not None else 0
        calls.append((Case(family, label, str(target or ""), "call", size=size), call, errors, match))

    def index(name: str, entries: list[dict]) -> Path:
        dst = folder / name
        dst.mkdir()
        (dst / "tables.json").write_text(json.dumps({"format": "cuniform-table-set/1", "system": "random_walk_1d",
                                                     "tables": entries}))
        return dst

    counts = "runaway counts"
    cases = _cases()
    big = index("index-too-many", cases.too_many_entries(MAX_SET_TABLES))
    add(counts, f"tables.json of {MAX_SET_TABLES + 1:,} entries", lambda: load_table_set(big), (TableError,),
        "more than the", big)
    dup = index("index-one-member-20000-times", cases.one_member_repeated(20_000))
    (dup / "start_0000.npz").write_bytes(b"not read")
    add(counts, "tables.json listing one member 20,000 times", lambda: load_table_set(dup), (TableError,),
        "listed more than once", dup)
    for label, name, said in cases.SET_MEMBER_NAMES:  # tests/test_files_sets.py's member names
        named = index(f"index-name-{label}", [{"file": name, "start": [0.0]}])
        add(counts, f"a member name: {label}", (lambda d: lambda: load_table_set(d))(named), (TableError,), said,
            named)

    class Zero:
        def command(self, state: Any) -> Any:
            return state.new_zeros(1)

    def runaway() -> Any:
        return simulate(system=make_system("dubins"), controller=Zero(), x0=torch.zeros(3), env=Environment([]),
                        goal=(50.0, 50.0), goal_tolerance=0.1, time_limit=1e9)

    add(counts, "simulate(time_limit=1e9), an unreachable goal", runaway, (ValueError,), "more than the limit")

    cards = "shipped policy card"
    shipped = "unicycle-0.5"

    def shelf(name: str, edit: Callable[[Path], None]) -> Path:
        dst = folder / name
        dst.mkdir()
        for path in pretrained.PRETRAINED_DIR.glob(f"{shipped}*"):
            shutil.copy(path, dst / path.name)
        edit(dst)
        return dst

    def card_edit(**robot: Any) -> Callable[[Path], None]:
        def edit(dst: Path) -> None:
            cases.edit_card(dst / f"{shipped}.json", **robot)
        return edit

    def sparse(dst: Path) -> None:
        with open(dst / f"{shipped}.map_policy.pt", "r+b") as fh:
            fh.truncate(2 << 30)

    def load_from(dst: Path) -> Callable[[], Any]:
        def load() -> Any:
            pretrained.PRETRAINED_DIR = dst  # the child's own copy of the module: the original is untouched
            return load_map_policy(shipped)
        return load

    edits: list[tuple[str, Callable[[Path], None]]] = [  # tests/test_files_policies.py's card edits
        (f"the card's {', '.join(f'{k} edited to {v}' for k, v in robot.items())}", card_edit(**robot))
        for robot, _ in cases.CARD_EDITS]
    for label, edit in (*edits, ("the weights file 2 GB (sparse)", sparse)):
        dst = shelf(f"card-{len(calls)}", edit)
        add(cards, label, load_from(dst), (pretrained.PretrainedError,), None, dst)

    systems = "user System"
    for label, system, error, match in probe.CASES:
        def make(system: Any = system) -> Any:
            return MPPI(system, probe._cost, num_samples=16, horizon=4, seed=0)
        add(systems, f"MPPI of a system whose {label}", make, (error,), match)

    try:
        sys.path.insert(0, str(REPO / "tests"))
        import test_gym_env as gym_tests

        from eval.navigate.gym_env import NavigationEnv, make_env
    except ImportError:  # gymnasium is an extra
        return calls
    gym = "gymnasium environment"

    def stepped(action: Any) -> Callable[[], Any]:
        def step() -> Any:
            env = make_env("gaps", index=0)
            env.reset(seed=0)
            return env.step(action)
        return step

    for action, message in _parametrized(gym_tests.test_bad_action_raises):
        add(gym, f"step({action!r})", stepped(action), (ValueError,), message)
    for (options,) in _parametrized(gym_tests.test_unknown_reset_options_are_refused):
        def reset(options: Any = options) -> Any:
            return make_env("gaps", index=0).reset(options=options)
        add(gym, f"reset(options={options!r})", reset, (ValueError,), "reset options may hold")
    assert NavigationEnv is not None
    return calls


def issue38_commands(work: Path) -> tuple[list[Case], list[Path]]:
    """Commands of issue 38 that must be refused before any work: --starts grids over the limit, a benchmark
    run into a folder whose records link into another folder or to /dev/null; ``(cases, folders to watch)``."""
    from eval.navigate.records.store import EpisodeStore

    folder = work / "commands"
    other = folder / "other-benchmark"
    store = EpisodeStore(other)
    store.open(BENCH_SETTINGS)
    store.append(BENCH_RECORD)
    shared = _cases()
    cases = [Case("commands", f"precompute.build --starts {spec} ({count} members)",
                  argv=["precompute.build", "set", "--system", "random_walk_1d", "--horizon", "3", "--quiet", "--starts",
                        spec, "--out", str(folder / f"huge-set-{i}")])
             for i, (spec, count) in enumerate(shared.STARTS_GRIDS)]  # tests/test_entry_build.py's grids
    links = [(("links into another benchmark folder", other / "episodes.jsonl") if target == "other" else
              (f"links to {target}", Path(target))) for target in shared.RECORD_LINK_TARGETS]
    watch = []
    for label, target in links:  # tests/test_files_bench.py's record links
        out = folder / f"bench-{len(cases)}"
        watch.append(out)
        out.mkdir()
        (out / "episodes.jsonl").symlink_to(target)
        cases.append(Case("commands", f"eval.navigate --out FOLDER whose episodes.jsonl {label}",
                          argv=["eval.navigate", "--suite", "gaps", "--tasks", "1", "--methods", "mppi_1.0",
                                "--budgets", "16", "--quiet", "--cache", str(folder / "cache"), "--out", str(out)]))
    return cases, [other, *watch]


# --------------------------------------------------------------------------------------------------- the run

def baseline_mb() -> float:
    """Peak RSS of a fresh interpreter that imports torch and every reader (what each case starts from)."""
    code = ("import resource, torch, cuniform_torch, cuniform_torch.maps.checkpoint, precompute.maps.dataset, "
            "precompute.levels.safe_map, eval.navigate.records.store, cuniform_torch.policies.table_set; "
            "print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)")
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    return int(out.stdout.split()[-1]) / 1024


def summarize(cases: list[Case]) -> dict[str, dict[str, Any]]:
    """Per family: cases tried, per outcome, cases that lost a file (``lost``) or left a process (``left
    processes``), and the largest peak (MB over the case's own start)."""
    empty = {"tried": 0, **{o: 0 for o in OUTCOMES}, "lost": 0, "left processes": 0, "max_peak_mb": 0.0}
    rows: dict[str, dict[str, Any]] = {}
    for c in cases:
        row = rows.setdefault(c.family, dict(empty))
        row["tried"] += 1
        row[c.outcome] += 1
        row["lost"] += bool(c.lost)
        row["left processes"] += bool(c.left)
        if not math.isnan(c.peak_mb):
            row["max_peak_mb"] = max(row["max_peak_mb"], round(c.peak_mb, 1))
    total = dict(empty)
    for row in rows.values():
        for k in total:
            total[k] = max(total[k], row[k]) if k == "max_peak_mb" else total[k] + row[k]
    rows["TOTAL"] = total
    return rows


COLUMNS = ["tried", "clear error", "silent wrong", "traceback", "code ran", "crash/hang", "lost", "left processes",
           "harmless accepted", "left out, said", "max_peak_mb"]
HEADS = ["tried", "clear error", "silent wrong", "traceback", "code ran", "hang/crash", "lost", "left procs",
         "harmless acc.", "left out,said", "peak MB"]


def print_table(rows: dict[str, dict[str, Any]]) -> None:
    width = max(len(k) for k in rows) + 2
    print(f"{'family':<{width}}" + "".join(f"{h:>14}" for h in HEADS))
    for name, row in rows.items():
        if name == "TOTAL":
            print("-" * (width + 14 * len(COLUMNS)))
        print(f"{name:<{width}}" + "".join(f"{row[c]:>14}" for c in COLUMNS))


def markdown_table(rows: dict[str, dict[str, Any]]) -> str:
    """The summary as a markdown table (the docs' copy); peak MB is each case's own, over the RSS it started with."""
    heads = [h.replace("peak MB", "peak MB over start") for h in HEADS]
    lines = ["| family | " + " | ".join(heads) + " |", "|---|" + "---:|" * len(heads)]
    for name, row in rows.items():
        cells = [f"{row[c]:.0f}" if c == "max_peak_mb" else str(row[c]) for c in COLUMNS]
        lines.append(f"| {'**total**' if name == 'TOTAL' else name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python .ci/attack.py", description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="a smaller sample of every class (a few minutes)")
    p.add_argument("--out", type=Path, default=None, help="write every case and the summary as JSON here")
    p.add_argument("--families", default=",".join([*FAMILIES, "issue38", "entry"]),
                   help=f"comma-separated subset of {', '.join([*FAMILIES, 'issue38', 'entry'])}")
    p.add_argument("--timeout", type=float, default=None, help="seconds per case (default 60, quick 30)")
    p.add_argument("--keep", action="store_true", help="keep the folder of mutated files")
    p.add_argument("--markdown", action="store_true", help="print the summary as a markdown table too")
    args = p.parse_args(argv)
    chosen = [f.strip() for f in args.families.split(",") if f.strip()]
    unknown = sorted(set(chosen) - {*FAMILIES, "issue38", "entry"})
    if unknown:
        p.error(f"--families: unknown {', '.join(unknown)}")
    timeout = args.timeout or (30.0 if args.quick else 60.0)
    sys.path.insert(0, str(REPO))
    import warnings

    import torch

    warnings.simplefilter("ignore")
    torch.set_num_threads(1)  # forked children: one thread each (OpenMP pools do not survive fork)
    t_start = time.time()
    base = baseline_mb()
    print(f"baseline: a fresh python importing torch and the readers peaks at {base:.0f} MB; peaks below are each "
          f"case's own, above that")
    readers = _readers()
    work = Path(tempfile.mkdtemp(prefix="cuniform-attack-"))
    all_cases: list[Case] = []
    try:
        for key in [k for k in FAMILIES if k in chosen]:
            t0 = time.time()
            fam = FAMILIES[key](work, args.quick)
            original: dict[str, str] = {}
            for reader in fam.readers:
                target = fam.target
                if reader in WRITING_READERS:  # probed on copies: the original stays what the cases compare with
                    target = work / key / f"probe-{reader}"
                    shutil.copytree(fam.target, target, symlinks=True)
                    readers[reader][0](target)  # warm-up
                    shutil.rmtree(target)
                    shutil.copytree(fam.target, target, symlinks=True)
                else:
                    readers[reader][0](target)  # warm-up in this process (lazy imports, JIT): children inherit it
                probe = Case(fam.name, "original", str(target), reader)
                run_reader_case(probe, readers, {}, work / key / "run", timeout)
                if probe.outcome != "silent wrong":  # no fingerprint to compare with: the original must read
                    raise SystemExit(f"error: the original {fam.name} does not read with {reader}: {probe.detail}")
                original[reader] = probe.extra["fp"]
            built = time.time() - t0
            for case in fam.cases:  # the original watched too: a case's links may lead into it
                run_reader_case(case, readers, original, work / key / "run", timeout, watch=[fam.target])
            all_cases += fam.cases
            print(f"{fam.name}: {len(fam.cases)} cases in {time.time() - t0:.0f} s (originals and copies made in "
                  f"{built:.0f} s)", flush=True)
        if "issue38" in chosen:
            t0 = time.time()
            calls = issue38_calls(work, args.quick)
            for case, call, errors, match in calls:
                run_call_case(case, call, errors, match, work / "calls" / "run", timeout,
                              watch=[Path(case.target)] if case.target else [])
            commands, watched = issue38_commands(work)
            for case in commands:
                run_command_case(case, work / "commands" / "run", timeout, watch=watched)
            all_cases += [c for c, *_ in calls] + commands
            print(f"issue 38 calls and commands: {len(calls) + len(commands)} cases in {time.time() - t0:.0f} s",
                  flush=True)
        if "entry" in chosen:
            t0 = time.time()
            cases = entry_cases(work, args.quick)
            fixtures = [p for p in (work / "entry").iterdir() if p.name not in ("run", "real")]
            for case in cases:  # the folders, links and FIFOs the flags name: never written through or replaced
                run_command_case(case, work / "entry" / "run", timeout, watch=fixtures)
            if not args.quick:  # the forked runs against real interpreters: one case per command
                seen: set[str] = set()
                for case in cases:
                    name = (case.argv or [""])[0]
                    if name in seen:
                        continue
                    seen.add(name)
                    real = Case("entry points (real python -m)", case.mutation, argv=case.argv)
                    run_command_case(real, work / "entry" / "real", timeout, real=True)
                    real.extra["forked_outcome"] = case.outcome
                    cases.append(real)
            all_cases += cases
            print(f"entry points: {len(cases)} cases in {time.time() - t0:.0f} s", flush=True)
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)
        else:
            print(f"mutated files kept in {work}")
    rows = summarize(all_cases)
    print()
    print_table(rows)
    if args.markdown:
        print()
        print(markdown_table(rows))
    if SKIPPED:
        print("not tried, as the contract allows them (valid files of other content): " +
              ", ".join(f"{k}: {v}" for k, v in SKIPPED.items()))
    bad = [c for c in all_cases if c.outcome in BAD or c.lost or c.left]
    special = ("a FIFO", "a link to /dev/")  # an entry case's input that is a special file
    big = [c for c in all_cases if c.peak_mb > PEAK_LIMIT_MB and (
        (c.argv is None and c.size < SMALL_FILE) or any(w in c.mutation for w in special))]
    unnamed = [c for c in all_cases if c.outcome == "clear error" and c.extra.get("names_file") is False]
    disagree = [c for c in all_cases if "forked_outcome" in c.extra and c.extra["forked_outcome"] != c.outcome]
    said = [c for c in all_cases if c.outcome == "left out, said"]
    for title, group in (("silent wrong / traceback / code ran / crash or hang / lost / left processes", bad),
                         ("left out and said on stderr (not failures; listed to be seen)", said),
                         (f"peak over {PEAK_LIMIT_MB} MB for a file under 10 MB or a special file", big),
                         ("clear errors that do not name the file or folder", unnamed),
                         ("real python -m runs classified otherwise than their forked runs", disagree)):
        if group:
            print(f"\n{title} ({len(group)}):")
            for c in group:
                print(f"  [{c.family}] {c.mutation} ({c.reader or 'cli'}): {c.outcome}: {c.detail}"
                      + (f"; lost: {', '.join(c.lost[:3])}" if c.lost else "")
                      + (f"; left processes: {', '.join(c.left)}" if c.left else ""))
    seconds = time.time() - t_start
    print(f"\n{len(all_cases)} cases in {seconds:.0f} s; baseline {base:.0f} MB")
    if args.out is not None:
        for c in all_cases:
            c.extra.pop("fp", None)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps({"mode": "quick" if args.quick else "full", "seconds": round(seconds, 1),
                                        "baseline_mb": round(base, 1), "peak_limit_mb": PEAK_LIMIT_MB,
                                        "summary": rows, "allowed_edits_not_tried": SKIPPED,
                                        "cases": [dataclasses.asdict(c) for c in all_cases]},
                                       indent=1, default=str))
        print(f"wrote {args.out}")
    return 1 if bad or big else 0


if __name__ == "__main__":
    sys.exit(main())
