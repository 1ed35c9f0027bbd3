"""``python -m eval.bench``: runs :func:`eval.bench.controllers.main`."""

import sys

from eval.bench.controllers import main

sys.exit(main())
