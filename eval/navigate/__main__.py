"""``python -m eval.navigate``: runs :func:`eval.navigate.commands.main` (the run, or a subcommand)."""

import sys

from eval.navigate.commands import main

sys.exit(main())
