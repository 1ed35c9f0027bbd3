"""Statistics of experiment records: success rates with Wilson intervals, per-group summaries, level means.

:func:`aggregate` turns closed-loop records (:func:`eval.paper.episodes.run_episodes`) into success rates with 95%
Wilson intervals, mean time to goal and mean path length (both over successful runs). The metrics of sampled
trajectories themselves (coverage, TV from uniform, noise floor) are :mod:`cuniform_torch.metrics`'.
"""

from __future__ import annotations

import math
import statistics
from collections import defaultdict
from collections.abc import Iterable, Sequence

__all__ = ["wilson_interval", "aggregate", "mean_or_none", "mean_over_levels"]


def wilson_interval(successes: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """Wilson score interval ``(low, high)`` for a binomial proportion; ``(0, 1)`` for ``n = 0``."""
    if n < 0 or successes < 0 or successes > n:
        raise ValueError(f"need 0 <= successes <= n, got successes={successes}, n={n}")
    if n == 0:
        return 0.0, 1.0
    p = successes / n
    denom = 1.0 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    # at p = 0 or 1 the bound equals p in exact arithmetic; rounding must not put p outside its own interval
    return min(p, max(0.0, centre - half)), max(p, min(1.0, centre + half))


def mean_or_none(values: Sequence[float]) -> float | None:
    """The mean, or None for no values."""
    return sum(values) / len(values) if values else None


def mean_over_levels(values: Sequence[float]) -> float:
    """Mean of a per-level series over levels 1..T (level 0 is the start, the same for every sampler)."""
    return statistics.mean(values[1:]) if len(values) > 1 else values[0]


def aggregate(records: Iterable[dict], keys: Sequence[str]) -> list[dict]:
    """Group records by ``keys`` (e.g. ``("appear", "num_samples", "method")``) and summarize each group.

    Per group: ``n``, ``successes``, ``success_rate``, ``ci_low`` / ``ci_high`` (95% Wilson), ``collisions``,
    ``timeouts``, ``mean_time`` and ``mean_path_length`` over the successful runs (None without one),
    ``wall_s`` (total compute seconds). Groups keep the order in which they first appear.
    """
    groups: dict[tuple, list[dict]] = defaultdict(list)
    for r in records:
        groups[tuple(r[k] for k in keys)].append(r)
    rows = []
    for key, recs in groups.items():
        n = len(recs)
        good = [r for r in recs if r["success"]]
        lo, hi = wilson_interval(len(good), n)
        row = dict(zip(keys, key))
        row.update(n=n, successes=len(good), success_rate=len(good) / n, ci_low=lo, ci_high=hi,
                   collisions=sum(r["outcome"] == "collision" for r in recs),
                   timeouts=sum(r["outcome"] == "timeout" for r in recs),
                   mean_time=mean_or_none([r["time"] for r in good]),
                   mean_path_length=mean_or_none([r["path_length"] for r in good]),
                   wall_s=sum(r.get("wall_s", 0.0) for r in recs))
        rows.append(row)
    return rows
