"""The library's training jobs as typed functions: ``from training import DistillConfig, distill_policy``.

* :func:`~training.distill.distill_policy`: tables (or one table-set folder) -> a distilled MLP policy, checkpointed;
* :func:`~training.maps.distill.train_map_policy`: map-table data sets -> a map-conditioned policy, checkpointed.

Each lives in the module of its command (``python -m training.distill``, ``python -m training.maps.distill``),
whose ``main`` parses the flags into the same config and calls it with ``progress=True``. From Python the
progress bars are off by default, nothing calls ``sys.exit``, and a bad setting is one ``ValueError`` naming
the field by its flag.
"""

from __future__ import annotations

from training.distill import distill_policy
from training.maps.distill import MapDistillConfig, train_map_policy
from training.tables.config import DistillConfig

__all__ = ["DistillConfig", "MapDistillConfig", "distill_policy", "train_map_policy"]
