"""Ctrl-C while a ``python -m`` command is still importing: one line ``interrupted`` and exit 130.

A command's ``main`` is wrapped by :func:`precompute.cli.cli_main`, but its imports (torch alone takes
seconds) run before ``main``; a Ctrl-C there would print Python's ``KeyboardInterrupt`` traceback. The command
packages (``training``, ``eval``) call :func:`exit_on_ctrl_c` from their ``__init__`` when the process is run as
``python -m`` (``sys.argv[0] == "-m"`` while Python locates the module, before the module's own imports), so the
handler is in place before any heavy import. Nothing is half done during imports, so the handler exits at once;
``cli_main`` swaps it for Python's ``KeyboardInterrupt`` while ``main`` runs. This module imports only the
standard library (``cuniform_torch`` imports torch).

``CUNIFORM_IMPORT_PAUSE=SECONDS`` (for the tests): right after installing the handler, print ``importing`` on
stdout and wait that long, a known point inside the imports to interrupt.
"""

from __future__ import annotations

import os
import signal
import sys
import time
from types import FrameType

__all__ = ["EXIT_INTERRUPTED", "exit_on_ctrl_c", "install_when_run_as_command"]

EXIT_INTERRUPTED = 130
"""the exit code of Ctrl-C (128 + SIGINT), :data:`precompute.cli.EXIT_INTERRUPTED`"""


def exit_on_ctrl_c(signum: int, frame: FrameType | None) -> None:
    """SIGINT handler: ``interrupted`` on stderr and exit 130 at once (no traceback, no cleanup to do)."""
    os.write(2, b"interrupted\n")  # unbuffered: the process ends before any buffer would flush
    os._exit(EXIT_INTERRUPTED)


exit_on_ctrl_c.exit_on_ctrl_c = True  # how precompute.cli.cli_main recognises it


def install_when_run_as_command() -> None:
    """Install :func:`exit_on_ctrl_c` when the process is a ``python -m`` command being located and imported (not
    when a library user or a test imports the package)."""
    if sys.argv[:1] != ["-m"] or signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        return  # imported by other code, or SIGINT is someone else's (ignored by a parent, a custom handler)
    signal.signal(signal.SIGINT, exit_on_ctrl_c)
    pause = os.environ.get("CUNIFORM_IMPORT_PAUSE")
    if pause:
        print("importing", flush=True)
        time.sleep(float(pause))
