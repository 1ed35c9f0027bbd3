"""``python -m eval.navigate SUBCOMMAND``: the tools dispatch with their flags, a run needs no subcommand, a word
that is no subcommand is one error line, and the old spellings (``python -m eval.navigate.compare``) are refused
with one line naming the new one, before the old module is imported."""

from __future__ import annotations

import importlib
import os
import subprocess
import sys
from pathlib import Path

import pytest

from eval.navigate import commands
from eval.navigate.subcommands import SUBCOMMANDS, old_spelling, refuse_old_spelling

ROOT = Path(__file__).resolve().parents[1]


def _python_m(module: str, *argv: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    return subprocess.run([sys.executable, "-m", module, *argv], cwd=ROOT, env=env, capture_output=True, text=True,
                          timeout=120)


@pytest.mark.parametrize("name", sorted(SUBCOMMANDS))
def test_the_old_spelling_is_refused_with_one_line_naming_the_new_one(name):
    module = SUBCOMMANDS[name][0]
    proc = _python_m(module, "--out", "somewhere")
    assert proc.returncode == 2
    assert proc.stdout == ""
    assert proc.stderr.splitlines() == [f"error: python -m {module} is now python -m eval.navigate {name} (the same "
                                        "flags); python -m eval.navigate --help lists the subcommands"]


def test_old_spelling_names_only_the_tools(monkeypatch):
    assert "is now python -m eval.navigate robot-files" in (old_spelling("eval.navigate.robot_files") or "")
    assert old_spelling("eval.navigate.episode") is None and old_spelling("eval.navigate") is None
    monkeypatch.setattr(sys, "argv", ["pytest"])  # imported by other code: nothing refused
    monkeypatch.setattr(sys, "orig_argv", [sys.executable, "-m", "eval.navigate.compare"])
    refuse_old_spelling()


@pytest.fixture
def called(monkeypatch):
    """The argv each tool's ``main`` gets, by module (the tools themselves stubbed)."""
    seen: dict[str, list[str]] = {}

    def stub(module: str):
        def main(argv) -> int:
            seen[module] = list(argv)
            return 0
        return main

    for module, _ in SUBCOMMANDS.values():
        monkeypatch.setattr(importlib.import_module(module), "main", stub(module))
    return seen


@pytest.mark.parametrize("argv, module, rest", [
    (["compare", "--out", "d", "--method", "a@1", "--against", "b@2"], "eval.navigate.compare",
     ["--out", "d", "--method", "a@1", "--against", "b@2"]),
    (["robot-files", "--check"], "eval.navigate.robot_files", ["--check"]),
    (["budget", "d"], "eval.navigate.budget", ["d"]),
    (["--suite", "barn", "--tasks", "2"], "eval.navigate.run", ["--suite", "barn", "--tasks", "2"]),  # no subcommand
    (["run", "--suite", "barn", "--tasks", "2"], "eval.navigate.run", ["--suite", "barn", "--tasks", "2"]),
])
def test_a_subcommand_runs_its_tool_with_the_rest_and_a_run_needs_none(called, argv, module, rest):
    assert commands.main(argv) == 0
    assert called == {module: rest}


def test_a_word_that_is_no_subcommand_is_one_error(called, capsys):
    assert commands.main(["comapre", "--out", "d"]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and "'comapre' is not a subcommand" in err[0] and "did you mean compare?" in err[0], err
    assert called == {}


def test_help_lists_every_subcommand_then_the_runs_flags(capsys):
    with pytest.raises(SystemExit) as exc:
        commands.main(["--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    for name in SUBCOMMANDS:
        assert f"\n  {name} " in out, name
    assert "--suite" in out and out.index("robot-files") < out.index("--suite")


@pytest.mark.parametrize("name", sorted(set(SUBCOMMANDS) - {"run", "budget"}))
def test_each_tool_says_its_new_spelling_in_its_usage(name):
    parser = importlib.import_module(SUBCOMMANDS[name][0]).make_parser()
    assert parser.prog == f"python -m eval.navigate {name}"


def test_make_parser_holds_every_tools_own_parser():
    sub = next(a for a in commands.make_parser()._actions if a.choices and "compare" in a.choices)
    assert set(sub.choices) == set(SUBCOMMANDS)
    assert "--against" in sub.choices["compare"].format_help() and "--suite" in sub.choices["run"].format_help()
