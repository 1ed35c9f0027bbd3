"""Every ``python -m`` entry point refuses bad flag values as it parses, in one ``error: ...`` line and exit code 2
(never a traceback, never a value silently used), and exits 130 in one line on Ctrl-C, even while it imports.

The entry points are one list, derived from the source (:func:`test_docs.cli_modules`: every module with a
``__main__`` guard, or a package with a ``__main__.py``), so a new command is covered without editing this file.
Each entry point's parser is introspected (its ``make_parser()``, else the parser its ``main`` builds, caught at
``parse_args``) and every flag it has among the bad-input classes below is tried, in-process: argv = the bad flag
alone. A bad value must stop the parse (the parse is stopped right after it succeeds, so nothing runs when a value
is wrongly accepted). The checks that come after parsing (flags that do not apply to the chosen mode, counts that
multiply past :data:`precompute.cli.MAX_WORK`, an ``--entries`` past the data set) are tried on the commands
that have them. Ctrl-C runs each command in a subprocess, interrupted at a known point during its imports
(``CUNIFORM_IMPORT_PAUSE``, :mod:`precompute.startup`).
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import select
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from test_cli_config import command_parsers
from test_cli_errors import _one_error
from test_docs import cli_modules, command_module

from precompute import cli

REPO = Path(__file__).resolve().parents[1]

COMMANDS = sorted(cli_modules())
"""every ``python -m`` name of the project (``eval.navigate``, ``precompute.build``, ...)"""

OWNED_ELSEWHERE: dict[str, str] = {}
"""commands this change may not edit (their parsers still check some values after parsing, or not at all): their
cases are strict xfails, so that the refactor that fixes them must drop them from here"""

CUDA_BEYOND = f"cuda:{max(7, torch.cuda.device_count())}"
"""a CUDA index this machine does not have"""

ZERO_IS_BAD = {"--samples", "--seeds", "--repeats", "--commands", "--tasks", "--positions", "--starts", "--epochs",
               "--budget", "--budgets", "--num-samples", "--workers", "--random", "--probe-samples", "--rollouts",
               "--batch-size", "--seeds-per-start", "--max-steps", "--rollout-repeats", "--sample-every",
               "--refresh", "--bank-size", "--hidden", "--layers", "--levels", "--repeat", "--embed", "--channels",
               "--horizons"}
"""integer flags whose 0 (and below) means nothing: counts, sizes, budgets"""
NEGATIVE_IS_BAD = {"--warmup", "--entries", "--threads", "--seed", "--networkx-max-nodes", "--jitter",
                   "--local-features"}
"""integer flags where 0 means something (none, all, torch's choice) but a negative value does not"""


def bad_values(option: str) -> list[str]:
    """The bad-input classes for one flag: its bad values (empty when the flag is none of the classes)."""
    if option == "--device":
        return ["banana", CUDA_BEYOND]
    if option == "--horizon":
        return ["0", "100000"]
    if option in ZERO_IS_BAD:
        return ["0", "-1"]
    if option in NEGATIVE_IS_BAD:
        return ["-1"]
    return []


class _Parsed(BaseException):
    """Raised right after a parse succeeds (a BaseException: ``cli_main`` does not turn it into exit 2)."""


class _Captured(BaseException):
    """Carries the parser a ``main`` built, caught at its ``parse_args``."""

    def __init__(self, parser: argparse.ArgumentParser):
        super().__init__()
        self.parser = parser


def entry_module(name: str):
    return importlib.import_module(command_module(name))


def parser_of(name: str, monkeypatch) -> argparse.ArgumentParser:
    """The parser of the command ``name``: its module's ``make_parser()``, else the one its ``main`` builds."""
    module = entry_module(name)
    if callable(getattr(module, "make_parser", None)):
        return module.make_parser()

    def capture(self, args=None, namespace=None):
        raise _Captured(self)

    with monkeypatch.context() as m:
        m.setattr(argparse.ArgumentParser, "parse_args", capture)
        try:
            module.main([])
        except _Captured as caught:
            return caught.parser
    raise AssertionError(f"python -m {name}: main never parsed its flags")


def _option_is_int(action: argparse.Action) -> bool:
    try:
        return isinstance(action.type("5"), int) if action.type is not None else False
    except (argparse.ArgumentTypeError, ValueError, TypeError):
        return True  # a validator that refuses 5 (a range above it) is an int validator too


def cases() -> list:
    """(command, flag, bad value) for every flag of every command among the bad-input classes."""
    out = []
    mp = pytest.MonkeyPatch()
    try:
        for name in COMMANDS:
            for sub, parser in command_parsers(parser_of(name, mp)).items():  # each subcommand's flags too
                for action in parser._actions:
                    for option in action.option_strings:
                        values = bad_values(option)
                        if option != "--device" and values and not _option_is_int(action):
                            continue  # e.g. eval.navigate's --starts SPEC: not a count
                        for value in values:
                            marks = [pytest.mark.xfail(reason=OWNED_ELSEWHERE[name], strict=True)] \
                                if name in OWNED_ELSEWHERE else []
                            argv = [sub, option, value] if sub else [option, value]
                            out.append(pytest.param(name, argv, id=f"{name} {' '.join(argv)}", marks=marks))
    finally:
        mp.undo()
    return out


CASES = cases()


def _exit_code(main, argv: list[str]) -> int:
    try:
        return main(argv)
    except SystemExit as exc:
        return exc.code if isinstance(exc.code, int) else 1


def test_every_command_is_found_and_wrapped():
    assert {"eval.navigate", "eval.bench", "eval.paper.coverage", "training.maps.timing", "precompute.build"} \
        <= set(COMMANDS)
    for name in COMMANDS:
        main = entry_module(name).main
        assert hasattr(main, "__wrapped__"), f"python -m {name}: main is not decorated with cli_main"


def test_the_cases_cover_the_reported_flags():
    ids = {(c.values[0], c.values[1][-2]) for c in CASES}
    for name in ("eval.paper.cluttered", "eval.paper.coverage", "eval.paper.sudden_obstacle", "eval.paper.uniformity",
                 "eval.bench"):
        assert (name, "--device") in ids, name
    subs = {c.values[1][0] for c in CASES if c.values[0] == "eval.bench" and len(c.values[1]) == 3}
    assert {"controllers", "soak_bank", "family"} <= subs, subs  # python -m eval.bench SUB: each one's flags
    assert ("eval.navigate", "--horizon") in ids and ("training.maps.timing", "--threads") in ids
    argvs = {tuple(c.values[1][:-1]) for c in CASES if c.values[0] == "precompute.build"}
    assert {("maxflow", "--rollouts"), ("coverage", "--seed"), ("set", "--workers"), ("safe", "--horizon"),
            ("set", "--threads")} <= argvs, argvs  # the subcommands' flags are tried


@pytest.mark.parametrize("name, argv", CASES)
def test_a_bad_value_is_refused_as_it_parses(name, argv, monkeypatch, tmp_path, capsys):
    option, value = argv[-2:]
    if value.startswith("cuda") and torch.cuda.device_count() > int(value.split(":")[1]):
        pytest.skip("this machine has that CUDA device")
    real_parse_args = argparse.ArgumentParser.parse_args

    def parse_then_stop(self, args=None, namespace=None):
        real_parse_args(self, args, namespace)
        raise _Parsed

    monkeypatch.setattr(argparse.ArgumentParser, "parse_args", parse_then_stop)
    monkeypatch.chdir(tmp_path)  # nothing lands in the checkout
    try:
        code = _exit_code(entry_module(name).main, argv)
    except _Parsed:
        pytest.fail(f"python -m {name} {' '.join(argv)}: the value parsed")
    assert code == cli.EXIT_ERROR
    _one_error(capsys, option)


def test_device_arg_accepts_what_the_machine_has():
    assert cli.device_arg("cpu") == "cpu"
    if torch.cuda.is_available():
        assert cli.device_arg("cuda:0") == "cuda:0"
    for bad in ("banana", "meta", "", CUDA_BEYOND):
        with pytest.raises(argparse.ArgumentTypeError):
            cli.device_arg(bad)


def test_int_and_float_validators():
    assert cli.horizon_arg(str(cli.MAX_HORIZON)) == cli.MAX_HORIZON
    assert cli.threads_arg("0") == 0 and cli.non_negative_int("0") == 0 and cli.positive_int("1") == 1
    for parse, bad in ((cli.horizon_arg, "0"), (cli.horizon_arg, str(cli.MAX_HORIZON + 1)), (cli.threads_arg, "-1"),
                       (cli.positive_int, "0"), (cli.positive_int, "2.5"), (cli.positive_float, "0"),
                       (cli.positive_float, "nan"), (cli.positive_float, "inf")):
        with pytest.raises(argparse.ArgumentTypeError):
            parse(bad)


# ------------------------------------------------------------------------------------------ after the parse

def _main(name: str):
    return entry_module(name).main


class _Ran(BaseException):
    """The command went on past its checks (a stub of its first real work): the flag was not refused."""


def _ran(*args, **kwargs):
    raise _Ran


@pytest.mark.parametrize("name, argv, needles, work", [
    ("eval.navigate", ["--suite", "gaps", "--barn-file", "maps.npz"], ["--barn-file", "--suite gaps"], "eval.navigate.run:_robot"),
    ("eval.navigate", ["--suite", "forest", "--barn-worlds", "w"], ["--barn-worlds", "--suite forest"], "eval.navigate.run:_robot"),
    ("eval.navigate", ["--suite", "barn", "--sensing-range", "2"], ["--sensing-range", "--suite barn"], "eval.navigate.run:_robot"),
    ("eval.navigate", ["--tasks", "100000", "--repeats", "10"], ["episodes", "--no-limit"], "eval.navigate.run:_robot"),
    ("eval.bench", ["controllers", "--rollout-only", "--table", "GARBAGE"], ["--table", "--rollout-only"],
     "eval.bench.controllers:check_output_file"),
    ("eval.bench", ["controllers", "--horizons", "15", "--table", "GARBAGE"], ["--table", "--horizons"],
     "eval.bench.controllers:check_output_file"),
    ("eval.bench", ["soak_bank", "--table", "t.npz", "--horizon", "10"], ["--horizon", "--table"],
     "eval.bench.soak_bank:import_system_modules"),
    ("training.maps.timing", ["--checkpoint", "p.pt", "--layers", "3"], ["--layers", "--checkpoint"], "make_system"),
    ("eval.mountain_car", ["--methods", "mppi", "--set-grid", "3x3"], ["--set-grid", "--methods"],
     "check_output_folder"),
    ("eval.mountain_car", ["--seeds", "100000"], ["seeds", "--no-limit"], "check_output_folder"),
    ("eval.paper.sudden_obstacle", ["--positions", "100000"], ["positions", "--no-limit"], "cli.prepare"),
    ("eval.paper.cluttered", ["--starts", "100000", "--seeds-per-start", "10"], ["starts", "--no-limit"],
     "cli.prepare"),
])
def test_a_flag_that_does_not_apply_or_a_run_too_large_is_refused(name, argv, needles, work, monkeypatch, tmp_path,
                                                                   capsys):
    module = entry_module(name)
    where, _, work = work.rpartition(":")  # MODULE:NAME: the work is another module's (a subcommand's)
    owner, _, attr = work.rpartition(".")
    home = importlib.import_module(where) if where else module
    monkeypatch.setattr(getattr(home, owner) if owner else home, attr, _ran)
    monkeypatch.chdir(tmp_path)
    try:
        code = _exit_code(module.main, argv)
    except _Ran:
        pytest.fail(f"python -m {name} {' '.join(argv)}: accepted")
    assert code == cli.EXIT_ERROR
    _one_error(capsys, *needles)
    assert not any(tmp_path.iterdir())  # refused before any work


def test_navigate_paths_on_a_folder_of_episodes_without_paths(tmp_path, capsys, monkeypatch):
    from eval.navigate.records.store import EpisodeStore

    record = {"key": "barn/0/cu_table/256/0", "outcome": "goal"}  # kept by a run without --paths
    (tmp_path / "episodes.jsonl").write_text(json.dumps(record) + "\n")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(importlib.import_module("eval.navigate.run"), "_robot", _ran)  # the first work after the checks
    monkeypatch.setattr(EpisodeStore, "read", lambda self: {record["key"]: record})  # the store's own checks aside
    try:
        assert _exit_code(_main("eval.navigate"), ["--out", str(tmp_path), "--paths"]) == cli.EXIT_ERROR
    except _Ran:
        pytest.fail("--paths accepted on a folder of episodes without their paths")
    _one_error(capsys, "--paths", "episodes.jsonl", "--out")
    monkeypatch.setattr(EpisodeStore, "read", lambda self: {record["key"]: {**record, "path": [[0.0, 0.0]]}})
    with pytest.raises(_Ran):  # episodes with their paths: accepted
        _main("eval.navigate")(["--out", str(tmp_path), "--paths"])


@pytest.mark.parametrize("name", ["training.maps.evaluate", "training.maps.coverage"])
def test_map_entries_beyond_the_data_set_are_refused(name, capsys):
    from training.maps.evaluate import check_entries

    with pytest.raises(cli.CLIError, match=r"--entries 99: the data set m has 3 entries"):
        check_entries(99, [0, 1, 2], "m")
    assert check_entries(0, [0, 1, 2], "m") == 3 and check_entries(2, [0, 1, 2], "m") == 2
    assert "check_entries" in Path(entry_module(name).__file__).read_text()  # both commands use it


def test_refuse_flags_rule():
    p = cli.ArgumentParser(prog="t")
    p.add_argument("--a", type=int, default=1)
    p.add_argument("--b", default=None)
    args = p.parse_args(["--a", "1"])
    cli.refuse_flags(p, args, ["a", "b"], "here")  # defaults: nothing was set
    with pytest.raises(SystemExit):
        cli.refuse_flags(p, p.parse_args(["--b", "x"]), ["a", "b"], "here")


# ------------------------------------------------------------------------------------------ Ctrl-C

def _python_m(name: str, *argv: str, pause: str | None, cwd: Path) -> subprocess.Popen:
    env = {k: v for k, v in os.environ.items() if k != "CUNIFORM_IMPORT_PAUSE"}
    if pause is not None:
        env["CUNIFORM_IMPORT_PAUSE"] = pause
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")])
    return subprocess.Popen([sys.executable, "-m", name, *argv], cwd=cwd, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))


def _wait_for_line(proc: subprocess.Popen, prefix: str, timeout: float = 120) -> None:
    """Read stdout until a line starts with ``prefix`` (the process must still run)."""
    deadline = time.time() + timeout
    while time.time() < deadline:
        ready, _, _ = select.select([proc.stdout], [], [], max(0.0, deadline - time.time()))
        if not ready:
            break
        line = proc.stdout.readline()
        if line.startswith(prefix):
            return
        if not line:  # the process ended without it
            break
    proc.kill()
    out, err = proc.communicate()
    pytest.fail(f"no {prefix!r} line; stdout {out!r}, stderr {err!r}")


def _interrupt(proc: subprocess.Popen) -> tuple[int, str]:
    """One SIGINT, then the exit code and stderr; a second only when the first was lost (after 60 s; not sooner:
    a second Ctrl-C while the interpreter shuts down after the first one kills it by the signal, code -2)."""
    try:
        for _ in range(2):
            proc.send_signal(signal.SIGINT)
            try:
                _, err = proc.communicate(timeout=60)
                return proc.returncode, err
            except subprocess.TimeoutExpired:
                continue
        pytest.fail("the process ignored SIGINT")
    finally:
        proc.kill()
        proc.communicate()


CTRL_C_CASES = list(COMMANDS)


@pytest.mark.parametrize("name", CTRL_C_CASES)
def test_ctrl_c_while_importing_is_one_line_and_130(name, tmp_path):
    proc = _python_m(name, pause="60", cwd=tmp_path)
    _wait_for_line(proc, "importing")
    code, err = _interrupt(proc)
    assert code == cli.EXIT_INTERRUPTED and err == "interrupted\n", (code, err)


def test_ctrl_c_during_the_heavy_imports(tmp_path):
    """No pause: the signal lands while torch imports (or, on a very fast machine, in main): the same line and code."""
    proc = _python_m("eval.bench", "soak_bank", "--commands", "1000000", "--quiet", pause="0", cwd=tmp_path)
    _wait_for_line(proc, "importing")
    code, err = _interrupt(proc)
    assert code == cli.EXIT_INTERRUPTED and err == "interrupted\n", (code, err)


def test_ctrl_c_in_main_is_one_line_and_130(tmp_path):
    proc = _python_m("training.maps.timing", "--commands", "1000000", "--samples", "16", pause=None, cwd=tmp_path)
    _wait_for_line(proc, "map policy:")
    code, err = _interrupt(proc)
    assert code == cli.EXIT_INTERRUPTED and err == "interrupted\n", (code, err)


def test_the_import_handler_is_for_commands_only():
    """Imported by a library user or a test, the command packages leave SIGINT alone."""
    assert signal.getsignal(signal.SIGINT) is not getattr(importlib.import_module("precompute.startup"),
                                                          "exit_on_ctrl_c")


def test_cli_main_hands_ctrl_c_to_main_and_takes_it_back():
    """While main runs, Ctrl-C is Python's KeyboardInterrupt (main may clean up and say what survives); after it,
    the import-time handler again."""
    from precompute.startup import exit_on_ctrl_c

    seen = {}

    @cli.cli_main(interrupted="interrupted: rerun with --resume")
    def main(argv=None) -> int:
        seen["handler"] = signal.getsignal(signal.SIGINT)
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGINT, exit_on_ctrl_c)
    try:
        assert main([]) == cli.EXIT_INTERRUPTED
        assert seen["handler"] is signal.default_int_handler
        assert signal.getsignal(signal.SIGINT) is exit_on_ctrl_c
    finally:
        signal.signal(signal.SIGINT, previous)
