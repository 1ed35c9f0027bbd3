"""``python -m eval.navigate``: the benchmark run, and the tools on its folders as subcommands.

    python -m eval.navigate [run] --suite barn --out out/navigate/barn ...   (the run; ``run`` may be left out)
    python -m eval.navigate budget|compare|failures|replay|figures|robot-files ...

Without a subcommand the words are the run's flags, so every run command written before the subcommands still
works; a first word that is neither a subcommand nor a flag is refused with one line naming the subcommands. The
old spellings (``python -m eval.navigate.compare``: one module per tool) are refused with one line naming the new
one (:mod:`eval.navigate.subcommands`). A subcommand's module is imported only when it runs.
"""

from __future__ import annotations

import difflib
import importlib
import sys
from collections.abc import Sequence

from eval.navigate.subcommands import SUBCOMMANDS
from precompute.cli import ArgumentParser, CLIError, cli_main, flags_listing, parser_flags

__all__ = ["SUBCOMMANDS", "make_parser", "main"]


def _listing() -> str:
    width = max(map(len, SUBCOMMANDS))
    lines = [f"  {name:<{width}}  {text}" for name, (_, text) in SUBCOMMANDS.items()]
    return ("usage: python -m eval.navigate [run] [FLAGS] | python -m eval.navigate SUBCOMMAND [FLAGS]\n\n"
            "subcommands (python -m eval.navigate SUBCOMMAND --help for each one's flags):\n" + "\n".join(lines))


def make_parser() -> ArgumentParser:
    """A parser whose subcommands are the tools' own parsers (each module's ``make_parser``), for the tests and
    tools that read every command's flags; :func:`main` dispatches on the first word without it (a run needs no
    ``run``)."""
    p = ArgumentParser(prog="python -m eval.navigate", description=(__doc__ or "").split("\n\n")[0])
    sub = p.add_subparsers(dest="subcommand", metavar="SUBCOMMAND")
    for name, (module, text) in SUBCOMMANDS.items():
        sub.add_parser(name, help=text)
        sub.choices[name] = importlib.import_module(module).make_parser()  # the tool's own flags and prog
    return p


@cli_main()
def main(argv: Sequence[str] | None = None) -> int:
    """Run the subcommand ``argv[0]`` with the rest of ``argv`` (default: the command line); without one, the
    benchmark run with all of ``argv``. 2 after one ``error: ...`` line for a first word that is no subcommand."""
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] in (["-h"], ["--help"]):  # the subcommands first, then the run's own flags
        tools = {name: parser_flags(importlib.import_module(module).make_parser())
                 for name, (module, _) in SUBCOMMANDS.items() if name != "run"}
        print(_listing() + "\n\n" + flags_listing(tools) + "\n\nthe run's flags (python -m eval.navigate [run] ...):",
              flush=True)
        name, rest = "run", argv
    elif argv and argv[0] in SUBCOMMANDS:
        name, rest = argv[0], argv[1:]
    elif argv and not argv[0].startswith("-"):
        near = difflib.get_close_matches(argv[0], SUBCOMMANDS, n=1)
        hint = f"did you mean {near[0]}? " if near else ""
        raise CLIError(f"{argv[0]!r} is not a subcommand of python -m eval.navigate; {hint}choose from "
                       f"{', '.join(SUBCOMMANDS)} (or give the run's flags: python -m eval.navigate --help)")
    else:
        name, rest = "run", argv
    return importlib.import_module(SUBCOMMANDS[name][0]).main(rest)

