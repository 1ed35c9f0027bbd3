"""Per-cycle wall times as fixed log-spaced histograms, so that episodes, seeds and runs merge by adding counts.

A histogram is ``{str(bin): count}`` with only non-zero bins. One bin spans a factor ``10**(1/40)`` (about
5.9%), from ``T_MIN = 1e-5`` s up to 100 s, so a quantile read from a histogram is within about 3% (half a
bin, geometric) of a time inside the bin that holds it. :mod:`eval.navigate.records.stats` reads them into its summaries.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence

__all__ = ["T_MIN", "BINS_PER_DECADE", "NUM_BINS", "cycle_histogram", "merge_histograms", "histogram_quantile",
           "bin_centre"]

T_MIN = 1e-5
"""seconds: the lower edge of bin 0 (shorter times are counted in bin 0)"""
BINS_PER_DECADE = 40
"""bins per factor 10; one bin spans a factor 10**(1/40), about 5.9%"""
NUM_BINS = 7 * BINS_PER_DECADE
"""bins from T_MIN = 1e-5 s up to 100 s (longer times are counted in the last bin)"""


def _bin_of(t: float) -> int:
    """Bin index of one cycle time ``t`` (s), clipped to ``[0, NUM_BINS - 1]``."""
    if not isinstance(t, (int, float)) or isinstance(t, bool) or not math.isfinite(t) or t < 0:
        raise ValueError(f"cycle times must be finite non-negative seconds, got {t!r}")
    if t <= T_MIN:  # includes 0: a clock that ticked less than T_MIN
        return 0
    return min(NUM_BINS - 1, max(0, math.floor(BINS_PER_DECADE * math.log10(t / T_MIN))))


def cycle_histogram(times_s: Sequence[float]) -> dict[str, int]:
    """Histogram of per-cycle wall times ``times_s`` (seconds): ``{str(bin): count}`` with only non-zero bins.

    Bin ``b = floor(40 * log10(t / 1e-5))`` clipped to ``[0, 279]`` (1e-5 s .. 100 s, 5.9% per bin).
    """
    hist: dict[int, int] = {}
    for t in times_s:
        b = _bin_of(t)
        hist[b] = hist.get(b, 0) + 1
    return {str(b): hist[b] for b in sorted(hist)}


def _checked_bins(hist: Mapping[str, int]) -> dict[int, int]:
    """``hist`` as ``{int bin: count}``; ValueError naming the first bad key or count."""
    if not isinstance(hist, Mapping):
        raise ValueError(f"a cycle histogram must be a mapping of str(bin) -> count, got {type(hist).__name__}")
    out: dict[int, int] = {}
    for key, count in hist.items():
        try:
            b = int(key)
        except (TypeError, ValueError):
            raise ValueError(f"cycle histogram key {key!r} is not a bin index") from None
        if not 0 <= b < NUM_BINS:
            raise ValueError(f"cycle histogram bin {b} outside [0, {NUM_BINS - 1}]")
        if isinstance(count, bool) or not isinstance(count, int) or count < 0:
            raise ValueError(f"cycle histogram count {count!r} of bin {key!r} is not a non-negative integer")
        out[b] = out.get(b, 0) + count
    return out


def merge_histograms(hists: Iterable[Mapping[str, int]]) -> dict[str, int]:
    """Sum of cycle histograms (bin-wise counts), keys ``str(bin)`` in bin order, only non-zero bins."""
    total: dict[int, int] = {}
    for h in hists:
        for b, c in _checked_bins(h).items():
            total[b] = total.get(b, 0) + c
    return {str(b): total[b] for b in sorted(total) if total[b] > 0}


def bin_centre(b: int) -> float:
    """Geometric centre of bin ``b`` in seconds: ``T_MIN * 10**((b + 0.5) / 40)``."""
    return T_MIN * 10.0 ** ((b + 0.5) / BINS_PER_DECADE)


def histogram_quantile(hist: Mapping[str, int], q: float) -> float | None:
    """The ``q``-quantile (seconds) of a cycle histogram: the geometric centre of the first bin where the
    cumulative count reaches ``q * total``; None for an empty histogram. Exact to one bin (5.9%)."""
    if not isinstance(q, (int, float)) or not 0.0 <= q <= 1.0:
        raise ValueError(f"quantile q must be in [0, 1], got {q!r}")
    bins = sorted((b, c) for b, c in _checked_bins(hist).items() if c > 0)
    total = sum(c for _, c in bins)
    if total == 0:
        return None
    cum = 0
    for b, c in bins:
        cum += c
        if cum >= q * total:
            return bin_centre(b)
    return bin_centre(bins[-1][0])  # only reached through rounding of q * total
