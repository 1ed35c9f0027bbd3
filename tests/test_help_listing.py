"""One ``--help`` of a command with subcommands shows every flag there is: ``python -m eval.bench --help`` and
``python -m eval.navigate --help`` list each subcommand's flags under its name (``precompute.build``'s listing is
tested in test_build_commands)."""

from __future__ import annotations

import importlib
import re

import pytest

import eval.bench.cli as bench
import eval.navigate.commands as navigate
from eval.navigate.subcommands import SUBCOMMANDS
from precompute.cli import parser_flags


def _listing(capsys, main) -> str:
    try:
        code = main(["--help"])
    except SystemExit as done:  # eval.navigate's help ends with the run's own argparse help
        code = done.code
    assert code == 0
    text = capsys.readouterr().out
    return text.split("flags of each subcommand")[1].split("the run's flags")[0]


def _block(listing: str, name: str) -> set[str]:
    block = listing.split(f"\n  {name}:")[1]
    block = re.split(r"\n  \S+:", block)[0]  # up to the next subcommand's name
    return set(re.findall(r"--[a-z][\w-]*", block))


@pytest.mark.parametrize("main, modules", [
    (bench.main, {name: f"eval.bench.{name}" for name in bench.COMMANDS}),
    (navigate.main, {name: module for name, (module, _) in SUBCOMMANDS.items() if name != "run"}),
])
def test_the_help_lists_every_subcommands_flags(capsys, main, modules):
    listing = _listing(capsys, main)
    for name, module in modules.items():
        flags = {f for f in parser_flags(importlib.import_module(module).make_parser())
                 if f.startswith("--") and f != "--help"}
        assert _block(listing, name) == flags, name
