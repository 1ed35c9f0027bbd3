"""The README's and the guides' commands stay true: every ``python -m`` command they show parses with today's
flags, and every command-line module of the project is shown somewhere.

Each command is run in-process up to its argument parsing (``parse_args`` returns, then the run stops), so a
renamed module or flag fails here in a second, without doing the command's work.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import re
import shlex
import sys
from pathlib import Path

import pytest

from cuniform_torch.systems import _REGISTRY

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
GUIDES = sorted((ROOT / "docs" / "guides").glob("*.md"))
LAYERS = ("precompute", "training", "eval")  # the packages whose modules are command-line entry points
SKIP = {"pytest", "cProfile"}  # not ours


def readme_commands(text: str) -> list[str]:
    """Every ``python -m ...`` command of the README: in fenced blocks (a ``$ `` prompt optional, ``\\``
    continuations joined, comments cut) and in inline code spans (joined across line breaks)."""
    commands = []
    for block in re.findall(r"```[a-z]*\n(.*?)```", text, flags=re.S):
        for line in block.replace("\\\n", " ").splitlines():
            line = line.strip().removeprefix("$ ").strip()
            if line.startswith("python -m "):
                commands.append(line)
    outside = re.sub(r"```.*?```", "", text, flags=re.S)
    commands += [span.replace("\n", " ") for span in re.findall(r"`(python -m [^`]+)`", outside)]
    cleaned = []
    for command in commands:
        words = shlex.split(command, comments=True)
        cleaned.append(shlex.join(words))
    return sorted(set(cleaned))


class _Parsed(BaseException):
    """Raised right after the command's arguments parse (a BaseException: no CLI wrapper turns it into exit 2)."""


def docs_text() -> str:
    """The README and every guide page, one text."""
    return "\n".join(path.read_text() for path in [README, *GUIDES])


COMMANDS = readme_commands(docs_text())


def command_module(name: str) -> str:
    """The module whose ``main`` ``python -m name`` runs: ``name`` itself, or for a package the module its
    ``__main__.py`` takes ``main`` from (``eval.navigate`` -> ``eval.navigate.commands``, which dispatches its
    subcommands)."""
    spec = importlib.util.find_spec(name)
    if spec is None or not spec.submodule_search_locations:
        return name
    runner = Path(next(iter(spec.submodule_search_locations))) / "__main__.py"
    found = re.search(r"^from ([\w.]+) import main$", runner.read_text(), flags=re.M) if runner.exists() else None
    assert found, f"python -m {name}: the package has no __main__.py that imports a main"
    return found.group(1)


def bare_subcommand(name: str, argv: list[str]) -> bool:
    """A subcommand named alone (``python -m eval.navigate budget`` in a sentence or a table cell): a mention, like
    a bare module; True only when the command's parser (its module's ``make_parser``) has that subcommand."""
    make = getattr(importlib.import_module(command_module(name)), "make_parser", None)
    if len(argv) != 1 or make is None:
        return False
    return any(isinstance(a, argparse._SubParsersAction) and argv[0] in a.choices for a in make()._actions)


def cli_modules() -> set[str]:
    """Every ``python -m`` name of the project: a module with a ``__main__`` guard, or a package with a
    ``__main__.py`` (whose runner module, e.g. ``eval.navigate.commands``, is then covered by the package's name)."""
    names, runners = set(), set()
    for layer in LAYERS:
        for path in (ROOT / layer).rglob("*.py"):
            module = ".".join(path.relative_to(ROOT).with_suffix("").parts)
            if path.name == "__main__.py":
                package = module.removesuffix(".__main__")
                names.add(package)
                runners.add(command_module(package))
            elif re.search(r'^if __name__ == "__main__":', path.read_text(), flags=re.M):
                names.add(module)
    return names - runners


def test_the_readme_shows_commands():
    modules = {shlex.split(c)[2] for c in readme_commands(README.read_text())}
    assert {"precompute.build", "training.distill", "eval.report", "eval.bench", "eval.navigate"} <= modules, modules


def test_the_docs_show_every_command_line_module():
    shown = {shlex.split(c)[2] for c in COMMANDS}
    mentioned = set(re.findall(r"python -m ([\w.]+)", docs_text())) | shown
    missing = sorted(cli_modules() - mentioned)
    assert not missing, f"command-line modules the README and docs/guides never show: {missing}"
    assert {"eval.navigate", "eval.bench", "eval.mountain_car"} <= cli_modules()  # packages with __main__.py


def test_command_module_follows_a_package_main():
    assert command_module("eval.navigate") == "eval.navigate.commands"
    assert command_module("precompute.build") == "precompute.build"


def _my_robots(text: str) -> str:
    """The README's own ``Unicycle`` example as the module ``my_robots`` its commands import: the example's
    imports, class and ``register_system`` line."""
    block = next(b for b in re.findall(r"```python\n(.*?)```", text, flags=re.S) if "class Unicycle" in b)
    lines = block.splitlines()
    end = next(i for i, line in enumerate(lines) if line.startswith("register_system("))
    keep = [line for line in lines[: end + 1] if not line.startswith(("from precompute", "from training"))]
    return "\n".join(keep) + "\n"


@pytest.fixture()
def registry_restored():
    """The system registry as it was: a command may register the README's unicycle from ``my_robots``."""
    saved = dict(_REGISTRY)
    _REGISTRY.pop("unicycle", None)  # as a fresh process: the README's Python example may have registered its own
    yield
    _REGISTRY.clear()
    _REGISTRY.update(saved)


@pytest.mark.parametrize("command", [c for c in COMMANDS if shlex.split(c)[2] not in SKIP])
def test_readme_command_parses(command, monkeypatch, tmp_path, capsys, registry_restored):
    words = shlex.split(command)
    module, argv = words[2], words[3:]
    main = getattr(importlib.import_module(command_module(module)), "main", None)
    assert callable(main), f"{module} has no main(argv)"
    if not argv or bare_subcommand(module, argv):
        return  # a bare mention of the command (a heading, a sentence): the module and its main exist
    if "my_robots" in command:
        (tmp_path / "my_robots.py").write_text(_my_robots(docs_text()))
        monkeypatch.syspath_prepend(str(tmp_path))
        monkeypatch.delitem(sys.modules, "my_robots", raising=False)
    real_parse_args = argparse.ArgumentParser.parse_args

    def parse_then_stop(self, args=None, namespace=None):
        real_parse_args(self, args, namespace)
        raise _Parsed

    monkeypatch.setattr(argparse.ArgumentParser, "parse_args", parse_then_stop)
    monkeypatch.chdir(tmp_path)  # nothing the parse might create lands in the checkout
    try:
        code = main(argv)
    except _Parsed:
        return
    except SystemExit as exc:  # --help exits 0; a bad flag exits 2 with its error line
        code = exc.code
    assert code == 0, f"README command does not parse: {command}\n{capsys.readouterr().err}"


def test_readme_gymnasium_example_runs():
    """The gymnasium example of the docs, executed as shown."""
    pytest.importorskip("gymnasium")
    block = next(b for b in re.findall(r"```python\n(.*?)```", docs_text(), flags=re.S)
                 if "from eval.navigate.gym_env import make_env" in b)
    scope: dict = {}
    exec(compile(block, "README.md", "exec"), scope)
    assert scope["env"].observation_space.contains(scope["obs"])
    assert scope["info"]["outcome"] in (None, "goal", "collision", "timeout")
