"""The paper's closed form for the 1-D random walk (Section IV-A).

Between L (n cells) and L' (m = n + 2k cells) with 2k+1 evenly spaced actions that move 0, +-1, ..., +-k cells,
cell i (1-based, left to right) takes the actions with probabilities ``[n-i+1, 1, ..., 1, i] / m``:
the leftmost action with weight n-i+1, the rightmost with weight i, every other action with weight 1.
"""

from __future__ import annotations

import numpy as np

__all__ = ["closed_form_1d_counts", "closed_form_1d"]


def closed_form_1d_counts(n: int, k: int) -> np.ndarray:
    """Integer weights ``[n, 2k+1]``: row i-1 is ``[n-i+1, 1, ..., 1, i]``; divide by m = n + 2k for probabilities."""
    if n < 1 or k < 1:
        raise ValueError(f"closed_form_1d needs n >= 1 and k >= 1 (2k+1 >= 3 actions), got n={n}, k={k}")
    counts = np.ones((n, 2 * k + 1), dtype=np.int64)
    i = np.arange(1, n + 1)
    counts[:, 0] = n - i + 1
    counts[:, -1] = i
    return counts


def closed_form_1d(n: int, k: int) -> np.ndarray:
    """C-Uniform probabilities ``[n, 2k+1]`` (float64, rows sum to 1) for the 1-D random walk."""
    return closed_form_1d_counts(n, k) / float(n + 2 * k)
