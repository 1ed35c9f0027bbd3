"""The old name of :mod:`eval.coverage_experiment`: ``python -m eval.coverage`` still runs the coverage experiment.

Kept only for the commands people have typed; new code imports :mod:`eval.coverage_experiment` (the metric is
:mod:`cuniform_torch.metrics`, the build method :mod:`precompute.coverage_method`).
"""

import sys

from .coverage_experiment import *  # noqa: F401,F403
from .coverage_experiment import main

if __name__ == "__main__":
    sys.exit(main())
