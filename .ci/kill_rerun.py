"""Kill and rerun: every long command, signalled at several moments, then rerun, must end where an uninterrupted run
ends, with nothing duplicated, lost or left behind.

``python .ci/kill_rerun.py [--quick] [--commands build,distill,maps,navigate] [--out FILE.json] [--keep]``: a
developer tool (not shipped), like ``.ci/attack.py``.

For each command (a table-set build with ``--workers 2``, a distillation, a map-policy training, a navigation
benchmark with ``--workers 2``; each at small settings, inputs made first by the project's own commands) it:

1. runs the command twice, uninterrupted: a warm-up (caches filled) and the reference, which must agree; W is the
   reference's wall time;
2. for each signal (SIGKILL as the out-of-memory killer sends it, SIGTERM, SIGINT as Ctrl-C sends it), each moment
   (early / middle / late: 15 % / 50 % / 85 % of W after the start) and each target (the whole process group, as
   the OOM killer's victim's workers die with it and Ctrl-C reaches the terminal's group; or only the parent, whose
   workers must then end by themselves), starts the command in a fresh folder, sends the signal at that moment,
   waits for it to end (30 s; else it hangs), then reruns it to completion the way a user would (the training
   commands with ``--resume`` when a training state was saved);
3. checks: the result equals the reference's (table bytes and the index / checkpoint tensors and metrics / the
   benchmark's records, apart from timing fields), no record or member duplicated or lost, no process of the
   killed run or the rerun left (every process the harness starts carries a token in its environment, read from
   ``/proc``), no lock, temporary or ``.stale`` file left in the output, the inputs or the cache.

It prints one markdown table: command, signal, target, moment, how the killed run ended, equal to the reference
(yes / no: what differs), left behind. ``--quick`` tries each signal and target once, the moments taking turns (6
cases per command instead of 18). Exit code 1 when a case is not equal or left something behind.

Every run uses the same relative output name (``out``) in its own folder, so paths written into results agree.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
TOKEN_VAR = "CUNIFORM_KILL_RERUN"
IGNORED = {"seconds", "wall_seconds", "train_seconds", "wall_s", "cycle_hist", "run", "run_name", "content_sha256",
           "size_guide", "resume"}
"""keys whose values differ between two uninterrupted runs (wall times, the run's unix-time name, a digest over
them, the machine's free memory) or record how the command was called (``resume``: the rerun's ``--resume``); left
out of every comparison"""
MOMENTS = {"early": 0.15, "middle": 0.5, "late": 0.85}
SIGNALS = {"SIGKILL": signal.SIGKILL, "SIGTERM": signal.SIGTERM, "SIGINT": signal.SIGINT}
TARGETS = ("group", "parent")
LEFTOVER_SUFFIXES = (".lock", ".tmp", ".stale")
EXIT_WAIT_S = 30.0


# --------------------------------------------------------------------------------------------------- processes

def _own_token_pids(token: str) -> list[int]:
    """Pids of live processes whose environment holds ``TOKEN_VAR=token`` (this harness's jobs and their workers)."""
    needle = f"{TOKEN_VAR}={token}".encode()
    found = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit() or int(entry) == os.getpid():
            continue
        try:
            with open(f"/proc/{entry}/environ", "rb") as fh:
                env = fh.read()
            with open(f"/proc/{entry}/stat", "rb") as fh:
                state = fh.read().rsplit(b")", 1)[1].split()[0]
        except OSError:  # gone meanwhile, or not ours to read
            continue
        if needle in env.split(b"\0") and state != b"Z":
            found.append(int(entry))
    return found


def _describe(pid: int) -> str:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as fh:
            cmd = fh.read().replace(b"\0", b" ").decode(errors="replace").strip()
    except OSError:
        cmd = "?"
    return f"{pid} ({cmd[:60]})"


def _left_processes(token: str, grace: float = 3.0) -> list[str]:
    """Processes of ``token`` still alive after ``grace`` s (workers poll for a dead parent every 0.25 s); each is
    then SIGKILLed so it cannot disturb the next case."""
    deadline = time.time() + grace
    while True:
        pids = _own_token_pids(token)
        if not pids or time.time() > deadline:
            break
        time.sleep(0.1)
    left = [_describe(p) for p in pids]
    for p in pids:
        try:
            os.kill(p, signal.SIGKILL)
        except ProcessLookupError:
            pass
    return left


@dataclasses.dataclass
class Ran:
    """How one run of a command ended."""

    rc: int | None  # None: still running when it was given up on
    seconds: float
    stderr: str


def _start(argv: list[str], cwd: Path, token: str, log: Path) -> subprocess.Popen:
    env = {**os.environ, TOKEN_VAR: token, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO),
                                                                                   os.environ.get("PYTHONPATH")])),
           "PYTHONUNBUFFERED": "1"}
    cwd.mkdir(parents=True, exist_ok=True)
    with open(log, "wb") as err:
        return subprocess.Popen([sys.executable, "-m", *argv], cwd=cwd, env=env, stdout=subprocess.DEVNULL,
                                stderr=err, start_new_session=True)  # its own group: a group signal hits it alone


def _wait(proc: subprocess.Popen, timeout: float) -> int | None:
    try:
        return proc.wait(timeout)
    except subprocess.TimeoutExpired:
        return None


def run_to_end(argv: list[str], cwd: Path, token: str, timeout: float = 600.0) -> Ran:
    """Run ``python -m argv`` in ``cwd`` to its end (SIGKILLed after ``timeout``)."""
    log = cwd.parent / f"{cwd.name}.stderr"
    t0 = time.time()
    proc = _start(argv, cwd, token, log)
    rc = _wait(proc, timeout)
    if rc is None:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    return Ran(rc, time.time() - t0, log.read_text(errors="replace"))


def run_and_signal(argv: list[str], cwd: Path, token: str, sig: int, after: float, group: bool) -> tuple[Ran, str]:
    """Start ``python -m argv``, send ``sig`` after ``after`` s (to its process group or to the parent only), wait
    for it to end; ``(how it ran, "signalled" | "finished first" | "hung: SIGKILLed")``."""
    log = cwd.parent / f"{cwd.name}.killed.stderr"
    t0 = time.time()
    proc = _start(argv, cwd, token, log)
    rc = _wait(proc, after)
    what = "finished first"
    if rc is None:
        (os.killpg if group else os.kill)(proc.pid, sig)
        what = "signalled"
        rc = _wait(proc, EXIT_WAIT_S)
        if rc is None:
            what = "hung: SIGKILLed"
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    return Ran(rc, time.time() - t0, log.read_text(errors="replace")), what


# --------------------------------------------------------------------------------------------------- comparing

def _strip(obj: Any) -> Any:
    """``obj`` without the :data:`IGNORED` keys, at any depth."""
    if isinstance(obj, dict):
        return {k: _strip(v) for k, v in obj.items() if k not in IGNORED}
    if isinstance(obj, (list, tuple)):
        return [_strip(v) for v in obj]
    return obj


def _digest(obj: Any) -> str:
    """sha256 of a nested structure (tensors and arrays by dtype, shape and bytes): the attack harness's
    ``fingerprint``, loaded from the file beside this one (this script is also loaded by path from the tests)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("ci_attack", Path(__file__).with_name("attack.py"))
    assert spec is not None and spec.loader is not None
    if "ci_attack" not in sys.modules:
        module = importlib.util.module_from_spec(spec)
        sys.modules["ci_attack"] = module
        spec.loader.exec_module(module)
    return sys.modules["ci_attack"].fingerprint(obj)


def _json(path: Path) -> Any:
    return _strip(json.loads(path.read_text()))


def fp_table_set(out: Path) -> dict[str, str]:
    """Every member's bytes, the index's bytes, each member's report apart from its timings."""
    fp = {}
    for f in sorted(out.iterdir()):
        if f.name.endswith(".npz") or f.name == "tables.json":
            fp[f.name] = hashlib.sha256(f.read_bytes()).hexdigest()[:16]
        elif f.name.endswith(".report.json"):
            fp[f.name] = _digest(_json(f))
    index = json.loads((out / "tables.json").read_text())
    files = [t["file"] for t in index["tables"]]
    if len(set(files)) != len(files):
        fp["duplicated members"] = str(sorted({f for f in files if files.count(f) > 1}))
    return fp


def _fp_checkpoint(path: Path) -> dict[str, str]:
    import torch

    ckpt = _strip(torch.load(path, weights_only=True))
    return {f"{path.name}:{k}": _digest(v) for k, v in ckpt.items()}


def fp_distill(out: Path) -> dict[str, str]:
    """The policy checkpoint (tensors, config, metrics), the comparison file, the count of TensorBoard runs."""
    fp = _fp_checkpoint(out / "p.pt")
    fp["p.comparison.json"] = _digest(_json(out / "p.comparison.json"))
    fp["TensorBoard runs"] = str(len(list((out / "runs").iterdir())))
    return fp


def fp_maps(out: Path) -> dict[str, str]:
    """The map-policy checkpoint (tensors, config, metrics) and the count of TensorBoard runs."""
    fp = _fp_checkpoint(out / "p.map_policy.pt")
    fp["TensorBoard runs"] = str(len(list((out / "runs").iterdir())))
    return fp


def fp_navigate(out: Path) -> dict[str, str]:
    """Each record by its key (apart from timings), duplicated keys, settings.json."""
    fp = {"settings.json": _digest(_json(out / "settings.json"))}
    keys: list[str] = []
    for line in (out / "episodes.jsonl").read_text().splitlines():
        if line.strip():
            rec = json.loads(line)
            keys.append(rec["key"])
            fp[f"record {rec['key']}"] = _digest(_strip(rec))
    dup = sorted({k for k in keys if keys.count(k) > 1})
    if dup:
        fp["duplicated records"] = ", ".join(dup)
    return fp


def differences(ref: dict[str, str], got: dict[str, str]) -> list[str]:
    """What ``got`` lacks, adds or changes against ``ref``."""
    out = [f"lost {k}" for k in ref if k not in got]
    out += [f"extra {k}: {got[k]}" if k.startswith("duplicated") else f"extra {k}" for k in got if k not in ref]
    out += [f"{k} differs" for k in ref if k in got and ref[k] != got[k]]
    return out


def leftover_files(*folders: Path) -> list[str]:
    """Lock, temporary and stale-lock files under ``folders``."""
    found = []
    for folder in folders:
        if folder.exists():
            for p in folder.rglob("*"):
                if p.name.endswith(LEFTOVER_SUFFIXES) or p.name == ".lock":
                    found.append(str(p.relative_to(folder.parent)))
    return sorted(found)


# --------------------------------------------------------------------------------------------------- commands

@dataclasses.dataclass
class Command:
    """A command of the table: made inputs, its argv (output ``out`` relative to the run's folder), its rerun's."""

    name: str
    label: str
    setup: Callable[[Path, str], list[Path]]  # make the inputs under the folder; returns folders to check for leftovers
    argv: Callable[[Path], list[str]]  # inputs folder -> argv
    fingerprint: Callable[[Path], dict[str, str]]
    rerun_extra: Callable[[Path], list[str]] = lambda out: []


def _must(argv: list[str], cwd: Path, token: str) -> None:
    ran = run_to_end(argv, cwd, token)
    if ran.rc != 0:
        raise SystemExit(f"error: setting up with python -m {' '.join(argv)} failed (exit {ran.rc}):\n"
                         f"{ran.stderr[-2000:]}")


def _setup_none(inputs: Path, token: str) -> list[Path]:
    return []


def _setup_table(inputs: Path, token: str) -> list[Path]:
    _must(["precompute.build", "maxflow", "--system", "dubins", "--horizon", "5", "--no-report", "--quiet", "--out",
           str(inputs / "table.npz")], inputs, token)
    return [inputs]


def _setup_maps(inputs: Path, token: str) -> list[Path]:
    _must(["precompute.maps.farm", "--suite", "clutter", "--count", "2", "--poses-per-map", "2", "--split", "train",
           "--horizon", "5", "--quiet", "--out", str(inputs / "maps")], inputs, token)
    return [inputs]


NAV = ["eval.navigate", "--suite", "clutter", "--budgets", "32", "--quiet"]


def _setup_cache(inputs: Path, token: str) -> list[Path]:
    """The navigation robot's max-flow table, built into the cache by a one-episode run (not part of the job)."""
    _must([*NAV, "--tasks", "1", "--methods", "cu_table", "--cache", str(inputs / "cache"), "--out",
           str(inputs / "warm")], inputs, token)
    return [inputs / "cache"]


def _resume_when_saved(state: str) -> Callable[[Path], list[str]]:
    def extra(out: Path) -> list[str]:  # what a user does: --resume once a training state exists
        return ["--resume"] if (out / state).exists() else []
    return extra


COMMANDS = {
    "build": Command(
        "build", "precompute.build --starts (4 members, --workers 2)", _setup_none,
        lambda inputs: ["precompute.build", "set", "--system", "ks_speed", "--horizon", "4", "--starts", "3=0:1:4",
                        "--workers", "2", "--quiet", "--out", "out"],
        fp_table_set),
    "distill": Command(
        "distill", "training.distill (400 epochs, hidden 16)", _setup_table,
        lambda inputs: ["training.distill", "--tables", str(inputs / "table.npz"), "--out", "out/p.pt", "--logdir",
                        "out/runs", "--quiet", "--hidden", "16", "--layers", "2", "--jitter", "2", "--batch-size",
                        "32", "--lr", "1e-2", "--epochs", "400", "--eval-samples", "64", "--eval-every", "1000"],
        fp_distill, _resume_when_saved("p.pt.train.pt")),
    "maps": Command(
        "maps", "training.maps.distill (150 epochs, 4 entries)", _setup_maps,
        lambda inputs: ["training.maps.distill", "--maps", str(inputs / "maps"), "--out", "out/p.map_policy.pt",
                        "--logdir", "out/runs", "--hidden", "16", "--layers", "2", "--embed", "4", "--channels", "2",
                        "--epochs", "150", "--jitter", "1", "--batch-size", "128", "--lr", "1e-2", "--val-fraction",
                        "0.25", "--quiet", "--skip-deep-checks"],
        fp_maps, _resume_when_saved("p.map_policy.pt.train.pt")),
    "navigate": Command(
        "navigate", "eval.navigate (4 tasks x 2 methods, --workers 2)", _setup_cache,
        lambda inputs: [*NAV, "--tasks", "4", "--methods", "mppi_1.0", "cu_table", "--workers", "2", "--cache",
                        str(inputs / "cache"), "--out", "out"],
        fp_navigate),
}


# --------------------------------------------------------------------------------------------------- the run

@dataclasses.dataclass
class Case:
    command: str
    signal: str
    target: str
    moment: str
    after_s: float = 0.0
    killed: str = ""
    killed_stderr: str = ""  # the killed run's last stderr lines (the JSON only)
    equal: str = ""
    left: list[str] = dataclasses.field(default_factory=list)
    rerun_rc: int | None = None

    @property
    def ok(self) -> bool:
        return self.equal == "yes" and not self.left and self.rerun_rc == 0


def plan(quick: bool) -> list[tuple[str, str, str]]:
    """(signal, target, moment) of every case: all 18, or (quick) each signal and target once, moments in turn."""
    full = [(s, t, m) for s in SIGNALS for t in TARGETS for m in MOMENTS]
    if not quick:
        return full
    moments = list(MOMENTS)
    return [(s, t, moments[i % len(moments)]) for i, (s, t) in enumerate((s, t) for s in SIGNALS for t in TARGETS)]


def _killed_said(ran: Ran, what: str) -> str:
    if what != "signalled":
        return what
    if ran.rc is None:
        return "?"
    how = f"signal {signal.Signals(-ran.rc).name}" if ran.rc < 0 else f"exit {ran.rc}"
    return how + (", traceback" if "Traceback" in ran.stderr else "")


def run_command(cmd: Command, work: Path, quick: bool, say: Callable[[str], None]) -> tuple[float, list[Case]]:
    """The reference, then every planned case of ``cmd``; (reference wall s, cases)."""
    token = f"{os.getpid()}-{cmd.name}-{time.time_ns()}"
    base = work / cmd.name
    inputs = base / "inputs"
    inputs.mkdir(parents=True)
    watched = cmd.setup(inputs, token)
    argv = cmd.argv(inputs)
    runs = []
    for name in ("warm-up", "reference"):  # the first also fills numba's and Python's caches: the reference's wall
        ran = run_to_end(argv, base / name, token)  # time is a warm run's, as every later run's is
        if ran.rc != 0:
            raise SystemExit(f"error: the {name} run of {cmd.name} failed (exit {ran.rc}):\n{ran.stderr[-2000:]}")
        runs.append((ran, cmd.fingerprint(base / name / "out")))
    (_, warm), (ref, reference) = runs
    same = differences(reference, warm)
    if same:  # two uninterrupted runs must agree, or no kill can be judged
        raise SystemExit(f"error: two uninterrupted runs of {cmd.name} differ: {'; '.join(same[:4])}")
    say(f"{cmd.name}: reference {ref.seconds:.1f} s (warm-up {runs[0][0].seconds:.1f} s, equal), {len(reference)} "
        "items compared")
    cases = []
    for sig, target, moment in plan(quick):
        case = Case(cmd.name, sig, target, moment, after_s=round(MOMENTS[moment] * ref.seconds, 2))
        folder = base / f"{sig}-{target}-{moment}"
        killed, what = run_and_signal(argv, folder, token, SIGNALS[sig], case.after_s, target == "group")
        case.killed = _killed_said(killed, what)
        case.killed_stderr = "\n".join(killed.stderr.strip().splitlines()[-3:])[-600:]
        left_after_kill = _left_processes(token)
        rerun = run_to_end(argv + cmd.rerun_extra(folder / "out"), folder, token)
        case.rerun_rc = rerun.rc
        left = [f"process after the kill: {p}" for p in left_after_kill]
        left += [f"process after the rerun: {p}" for p in _left_processes(token, grace=1.0)]
        left += leftover_files(folder / "out", *watched)
        case.left = left
        if rerun.rc != 0:
            case.equal = f"no: the rerun exited {rerun.rc}: {rerun.stderr.strip().splitlines()[-1:]}"
        else:
            try:
                diff = differences(reference, cmd.fingerprint(folder / "out"))
            except (OSError, ValueError, KeyError) as exc:
                diff = [f"unreadable: {type(exc).__name__}: {exc}"]
            case.equal = "yes" if not diff else "no: " + "; ".join(diff[:4]) + (" ..." if len(diff) > 4 else "")
        say(f"  {sig:<7} {target:<6} {moment:<6} at {case.after_s:5.1f} s: killed run {case.killed}; "
            f"equal {case.equal}; left {len(case.left)}")
        cases.append(case)
    return ref.seconds, cases


def markdown(rows: list[Case], refs: dict[str, float]) -> str:
    lines = ["| command | signal | sent to | moment | killed run | equal to uninterrupted | left behind |",
             "|---|---|---|---|---|---|---|"]
    for c in rows:
        label = COMMANDS[c.command].label
        lines.append(f"| {label} | {c.signal} | {c.target} | {c.moment} ({c.after_s:.1f} s of "
                     f"{refs[c.command]:.1f} s) | {c.killed} | {c.equal} | {'; '.join(c.left) or 'nothing'} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python .ci/kill_rerun.py", description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="each signal and target once, moments in turn (6 per command)")
    p.add_argument("--commands", default=",".join(COMMANDS), help=f"comma-separated subset of {', '.join(COMMANDS)}")
    p.add_argument("--out", type=Path, default=None, help="write the cases as JSON here")
    p.add_argument("--keep", action="store_true", help="keep the work folder")
    args = p.parse_args(argv)
    chosen = [c.strip() for c in args.commands.split(",") if c.strip()]
    unknown = sorted(set(chosen) - set(COMMANDS))
    if unknown or not chosen:
        p.error(f"--commands: unknown {', '.join(unknown) or '(none given)'}; choose from {', '.join(COMMANDS)}")
    # A harness started in the background of a non-interactive shell has SIGINT ignored, and an ignored signal
    # stays ignored across exec: its commands would then never see the SIGINT sent to them (Python installs no
    # KeyboardInterrupt handler where it starts with SIGINT ignored). A handler is reset to the default at exec.
    signal.signal(signal.SIGINT, signal.default_int_handler)
    t0 = time.time()
    work = Path(tempfile.mkdtemp(prefix="cuniform-kill-rerun-"))
    rows: list[Case] = []
    refs: dict[str, float] = {}
    load0 = os.getloadavg()[0]
    try:
        for name in chosen:
            refs[name], cases = run_command(COMMANDS[name], work, args.quick, lambda s: print(s, flush=True))
            rows += cases
    finally:
        if args.keep:
            print(f"work folder kept: {work}")
        else:
            shutil.rmtree(work, ignore_errors=True)
    print()
    print(markdown(rows, refs))
    bad = [c for c in rows if not c.ok]
    print(f"\n{len(rows)} cases in {time.time() - t0:.0f} s (1-min load {load0:.2f} at the start, "
          f"{os.getloadavg()[0]:.2f} at the end); {len(bad)} not equal or leaving something behind")
    if args.out is not None:
        args.out.write_text(json.dumps({"references_s": refs, "cases": [dataclasses.asdict(c) for c in rows]},
                                       indent=1))
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
