"""``python -m eval.bench SUB [flags]``: runs :func:`eval.bench.cli.main` (the subcommands)."""

import sys

from eval.bench.cli import main

sys.exit(main())
