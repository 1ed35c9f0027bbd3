"""``python -m eval.mountain_car``: runs :func:`eval.mountain_car.run.main`."""

import sys

from eval.mountain_car.run import main

sys.exit(main())
