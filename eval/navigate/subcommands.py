"""The subcommands of ``python -m eval.navigate`` and the refusal of their old spellings; standard library only.

The package's ``__init__`` imports this module (:func:`refuse_old_spelling`), so it must stay light: importing
:mod:`eval.navigate.records` never loads torch. The dispatcher itself is :mod:`eval.navigate.commands`.
"""

from __future__ import annotations

import sys

__all__ = ["SUBCOMMANDS", "EXIT_ERROR", "old_spelling", "refuse_old_spelling"]

SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "run": ("eval.navigate.run", "run the benchmark into a folder (the default: the words are its flags)"),
    "budget": ("eval.navigate.budget", "judge the methods per cycle-time budget (ms), not per sample count"),
    "atlas": ("eval.navigate.atlas", "run every suite's test split and judge it per cycle budget on one page"),
    "compare": ("eval.navigate.compare", "paired comparison of any two METHOD@BUDGET cells of a folder"),
    "failures": ("eval.navigate.failures", "why the failed episodes failed: trapped, a sampling miss, or lost"),
    "replay": ("eval.navigate.replay", "replay one stored episode with a per-command trace, and draw it"),
    "figures": ("eval.navigate.figures", "the success figure and TensorBoard scalars of results.json files"),
    "robot-files": ("eval.navigate.robot_files", "rebuild, check or time the navigation robot's shipped tables"),
}
"""subcommand -> (the module whose ``main(argv)`` runs it, one line of help)"""

EXIT_ERROR = 2
"""the exit code of a bad command line (``precompute.cli.EXIT_ERROR``; not imported: it imports torch)"""


def old_spelling(module: str) -> str | None:
    """The one-line refusal of ``python -m module`` when ``module`` is a tool's old spelling
    (``eval.navigate.compare``), else None."""
    new = {target: name for name, (target, _) in SUBCOMMANDS.items()}.get(module)
    if new is None:
        return None
    return (f"error: python -m {module} is now python -m eval.navigate {new} (the same flags); "
            "python -m eval.navigate --help lists the subcommands")


def refuse_old_spelling() -> None:
    """Exit 2 with :func:`old_spelling`'s line when this process is ``python -m`` of an old spelling, before that
    module is imported: while Python locates it ``sys.argv[0]`` is ``-m`` and ``sys.orig_argv`` names it. Nothing
    when other code imports the package."""
    if sys.argv[:1] != ["-m"]:
        return
    words = list(sys.orig_argv)
    module = words[words.index("-m") + 1] if "-m" in words[:-1] else ""
    line = old_spelling(module)
    if line is not None:
        print(line, file=sys.stderr)
        raise SystemExit(EXIT_ERROR)
