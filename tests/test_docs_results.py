"""The docs site's results pages stay true to the code: every page names the command that printed its numbers,
every ``python -m`` module a docs page names exists with a ``main`` (a package: its ``__main__``), every command
shown parses with today's flags, and every image a page links is there.

A command is run up to its argument parsing only (``parse_args`` returns, then the run stops), as
``tests/test_docs.py`` does for the README, so a renamed module or flag fails here in a second.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import re
import runpy
import shlex
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

from test_docs import _my_robots, bare_subcommand, docs_text, registry_restored  # noqa: E402, F401  (registry_restored: a fixture)

DOCS = ROOT / "docs"
RESULTS = DOCS / "results"


def _pages(folder: Path) -> list[Path]:
    return sorted(folder.rglob("*.md")) if folder.is_dir() else []


def page_commands(text: str) -> list[str]:
    """Every ``python -m ...`` command of a page: fenced-block lines (a ``$ `` prompt optional, ``\\``
    continuations joined, comments cut) and inline code spans (joined across line breaks)."""
    commands = []
    for block in re.findall(r"```[a-z]*\n(.*?)```", text, flags=re.S):
        for line in block.replace("\\\n", " ").splitlines():
            line = line.strip().removeprefix("$ ").strip()
            if line.startswith("python -m "):
                commands.append(line)
    outside = re.sub(r"```.*?```", "", text, flags=re.S)
    commands += [span.replace("\n", " ") for span in re.findall(r"`(python -m [^`]+)`", outside)]
    words = [shlex.split(c, comments=True) for c in commands]
    # a placeholder (`python -m ...`, `python -m <module>`) names no module
    return sorted({shlex.join(w) for w in words if len(w) > 2 and re.fullmatch(r"[A-Za-z_][\w.]*", w[2])})


def image_links(text: str) -> list[str]:
    """The local images a markdown page shows: ``![alt](path)`` and ``<img src="path">``."""
    links = re.findall(r"!\[[^\]]*\]\(([^)\s]+)", text) + re.findall(r"<img[^>]*\bsrc=\"([^\"]+)\"", text)
    return [link for link in links if not re.match(r"[a-z]+://", link)]


RESULT_PAGES = _pages(RESULTS)
DOC_PAGES = _pages(DOCS) + ([ROOT / "README.md"] if (ROOT / "README.md").is_file() else [])
COMMANDS = sorted({(page.relative_to(ROOT).as_posix(), c) for page in _pages(DOCS) for c in page_commands(page.read_text())})


def test_there_are_results_pages():
    assert len(RESULT_PAGES) >= 10, [p.name for p in RESULT_PAGES]
    assert (RESULTS / "index.md") in RESULT_PAGES


@pytest.mark.parametrize("page", RESULT_PAGES, ids=lambda p: p.name)
def test_results_page_names_a_command(page):
    if page.name == "index.md":
        return
    assert page_commands(page.read_text()), f"{page.relative_to(ROOT)} names no `python -m` command"


def test_results_index_lists_every_page():
    index = (RESULTS / "index.md").read_text()
    linked = set(re.findall(r"\]\(([\w.-]+\.md)(?:#[\w-]*)?\)", index))
    missing = sorted(p.name for p in RESULT_PAGES if p.name != "index.md" and p.name not in linked)
    assert not missing, f"docs/results/index.md does not list {missing}"
    dangling = sorted(name for name in linked if not (RESULTS / name).is_file())
    assert not dangling, f"docs/results/index.md links pages that do not exist: {dangling}"


def _entry_point(module: str) -> str:
    """How ``python -m module`` runs: ``"package"`` (its ``__main__`` exists) or ``"module"`` (it has a callable
    ``main``); AssertionError naming what is missing."""
    try:
        spec = importlib.util.find_spec(module)
    except ModuleNotFoundError:
        spec = None
    assert spec is not None, f"python -m {module}: no such module"
    if spec.submodule_search_locations is not None:
        assert importlib.util.find_spec(f"{module}.__main__") is not None, \
            f"python -m {module}: a package without __main__"
        return "package"
    assert callable(getattr(importlib.import_module(module), "main", None)), f"python -m {module}: no main()"
    return "module"


@pytest.mark.parametrize("module", sorted({shlex.split(c)[2] for _, c in COMMANDS}))
def test_docs_module_exists_with_main(module):
    _entry_point(module)


class _Parsed(BaseException):
    """Raised right after the command's arguments parse (a BaseException: no CLI wrapper turns it into exit 2)."""


@pytest.mark.parametrize("where,command", COMMANDS, ids=[f"{w}: {c[:80]}" for w, c in COMMANDS])
@pytest.mark.usefixtures("registry_restored")
def test_docs_command_parses(where, command, monkeypatch, tmp_path, capsys):
    words = shlex.split(command)
    module, argv = words[2], words[3:]
    if module == "pytest":
        return  # not ours
    if module == "cProfile":  # python -m cProfile -o FILE -m MODULE ARGS: the profiled command must parse
        inner = words.index("-m", 3)
        module, argv = words[inner + 1], words[inner + 2:]
    kind = _entry_point(module)
    if not argv or bare_subcommand(module, argv):
        return  # a bare mention of the command (a heading, a table cell): the module and its main exist
    if "my_robots" in command:  # the user's own module of the your-own-robot example: tests/test_docs.py builds it
        (tmp_path / "my_robots.py").write_text(_my_robots(docs_text()))
        monkeypatch.syspath_prepend(str(tmp_path))
        monkeypatch.delitem(sys.modules, "my_robots", raising=False)
    real_parse_args = argparse.ArgumentParser.parse_args

    def parse_then_stop(self, args=None, namespace=None):
        real_parse_args(self, args, namespace)
        raise _Parsed

    monkeypatch.setattr(argparse.ArgumentParser, "parse_args", parse_then_stop)
    monkeypatch.chdir(tmp_path)  # nothing the parse might create lands in the checkout
    monkeypatch.setattr(sys, "argv", [module, *argv])
    try:
        if kind == "package":  # what python -m runs: the package's __main__, which reads sys.argv
            runpy.run_module(module, run_name="__main__", alter_sys=False)
            code = 0
        else:
            code = importlib.import_module(module).main(argv)
    except _Parsed:
        return
    except SystemExit as exc:  # --help exits 0; a bad flag exits 2 with its error line
        code = exc.code
    assert code == 0, f"{where}: command does not parse: {command}\n{capsys.readouterr().err}"


@pytest.mark.parametrize("page", DOC_PAGES, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_page_images_exist(page):
    missing = [link for link in image_links(page.read_text()) if not (page.parent / link.split("#")[0]).is_file()]
    assert not missing, f"{page.relative_to(ROOT)} links images that do not exist: {missing}"
