"""``python -m eval.bench SUB [flags]``: the speed benchmarks as subcommands of one command.

``python -m eval.bench SUB --help`` lists the flags of a subcommand (:data:`COMMANDS`). Without a subcommand (no
flags, or flags first) it runs ``controllers``, and on the command line first prints one note naming the new
spelling, as ``python -m precompute.build`` does for its old one. The old per-module spelling,
``python -m eval.bench.NAME``, is refused in one line naming ``python -m eval.bench NAME``
(:func:`refuse_old_spelling`, called at the bottom of each such module).
"""

from __future__ import annotations

import importlib
import shlex
import sys
from collections.abc import Sequence

from precompute.cli import EXIT_ERROR, ArgumentParser, cli_main, flags_listing, parser_flags

__all__ = ["COMMANDS", "PROG", "main", "make_parser", "refuse_old_spelling"]

PROG = "python -m eval.bench"

COMMANDS = {
    "controllers": "per-command time of the MPPI family against pytorch_mppi, and bare rollout times",
    "family": "per-command time of the whole MPPI family on the navigation robot, one robot or a batch",
    "first_stage": "CU-MPPI's first stage, whole plan against lean: per-command CPU time side by side",
    "maxflow": "the max-flow solvers on the flow networks of a real table, side by side",
    "pendulum": "many robots in one call: 32 pendulums by one batched MPPI, a loop of 32, pytorch_mppi's MPPI_Batched",
    "profile_split": "where a control cycle goes, from a cProfile of a benchmark run",
    "soak_bank": "soak of the background proposal bank: many C-Uniform commands while a worker refreshes it",
    "switch_pendulum": "a pytorch_mppi user's pendulum script run with pytorch_mppi and with cuniform_torch",
}
"""the subcommands (each a module of :mod:`eval.bench` with a ``main(argv)``) and one line on each"""


def _usage() -> str:
    width = max(map(len, COMMANDS))
    lines = [f"usage: {PROG} SUB [flags]   ({PROG} SUB --help: the flags of SUB)", "", "subcommands:"]
    lines += [f"  {name:<{width}}  {text}" for name, text in COMMANDS.items()]
    return "\n".join(lines)


def make_parser() -> ArgumentParser:
    """The whole command as one parser, a subparser per :data:`COMMANDS` with that module's flags (its own
    ``make_parser()``): for ``--help`` of everything and for the tests that read every command's flags. It imports
    every subcommand; :func:`main` imports only the one it runs."""
    parser = ArgumentParser(prog=PROG, description="The speed benchmarks. " + _usage().split("\n")[0][len("usage: "):])
    subs = parser.add_subparsers(dest="command", metavar="{" + ",".join(COMMANDS) + "}", parser_class=ArgumentParser)
    for name, text in COMMANDS.items():
        own = importlib.import_module(f"eval.bench.{name}").make_parser()
        subs.add_parser(name, parents=[own], add_help=False, help=text, description=own.description,
                        conflict_handler="resolve")
    return parser


@cli_main()
def main(argv: Sequence[str] | None = None) -> int:
    """Run the subcommand ``argv[0]`` with the rest of ``argv`` (default: the command line): its exit code, or 2
    after one ``error: ...`` line for an unknown subcommand. No subcommand runs ``controllers`` (a note on stderr
    from the command line)."""
    command_line = argv is None
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] in ("-h", "--help"):  # the subcommands, then every subcommand's flags (imports all eight)
        parsers = {name: importlib.import_module(f"eval.bench.{name}").make_parser() for name in COMMANDS}
        print(_usage() + "\n\n" + flags_listing({name: parser_flags(p) for name, p in parsers.items()}))
        return 0
    if not argv or argv[0].startswith("-"):
        if command_line:
            print(f"note: {PROG} without a subcommand runs controllers; the same run is: "
                  f"{PROG} {shlex.join(['controllers', *argv])}", file=sys.stderr)
        argv = ["controllers", *argv]
    name, rest = argv[0].replace("-", "_"), argv[1:]
    if name not in COMMANDS:
        print(f"error: {argv[0]!r} is not a subcommand of {PROG}; choose from {', '.join(COMMANDS)}",
              file=sys.stderr)
        return EXIT_ERROR
    module = importlib.import_module(f"eval.bench.{name}")  # imported on use: each pulls in its own peers
    return int(module.main(rest))


def refuse_old_spelling(module_name: str, command: str) -> None:
    """At the bottom of ``eval/bench/<command>.py``: run as ``python -m eval.bench.<command>``, print one line
    naming the new spelling and exit 2; imported, nothing."""
    if module_name != "__main__":
        return
    words = shlex.join(sys.argv[1:])
    print(f"error: python -m eval.bench.{command} is now a subcommand: python -m eval.bench {command}"
          + (f" {words}" if words else ""), file=sys.stderr)
    sys.exit(EXIT_ERROR)
