"""The README's setup and test commands, exactly as a newcomer runs them: ``python .ci/readme_commands.py setup|test``.

Each is the one fenced ```bash block right after a ``<!-- ci:setup -->`` / ``<!-- ci:test -->`` line of README.md.
CI runs what this prints, so the README and CI cannot drift apart; a missing or repeated marker is an error.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

README = Path(__file__).resolve().parents[1] / "README.md"
MARKERS = ("setup", "test")


def readme_command(text: str, which: str) -> str:
    """The commands of the fenced bash block after ``<!-- ci:<which> -->`` in ``text``; ValueError otherwise."""
    if which not in MARKERS:
        raise ValueError(f"unknown block {which!r}; one of {MARKERS}")
    found = re.findall(rf"^<!-- ci:{which} -->\n```bash\n(.*?)```", text, flags=re.S | re.M)
    if len(found) != 1:
        raise ValueError(f"README.md needs exactly one '<!-- ci:{which} -->' line right before a ```bash block, "
                         f"found {len(found)}")
    return found[0].strip()


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit(f"usage: python {sys.argv[0]} {'|'.join(MARKERS)}")
    try:
        print(readme_command(README.read_text(), sys.argv[1]))
    except ValueError as exc:
        sys.exit(f"error: {exc}")
