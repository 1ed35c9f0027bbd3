"""``python -m eval.navigate``: runs :func:`eval.navigate.run.main`."""

import sys

from eval.navigate.run import main

sys.exit(main())
