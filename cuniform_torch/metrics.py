"""Metrics of sampled trajectories, one home for precompute, training and eval: coverage and uniformity.

Shapes: N trajectories (or samples of one level), T horizon, d state dimensions, n cells of a reference set.

* **Coverage** (:func:`coverage`): the number of distinct cells visited by any trajectory at any step, start
  included (the paper's reference release's definition); per level, the distinct cells at step t; against a
  table, the distinct cells *of L_t* visited at step t. N perfectly uniform draws over m cells cover
  ``m (1 - (1 - 1/m)^N)`` cells on average: the ceiling for any sampler (:func:`uniform_ceiling`).
* **Total variation from uniform** over a reference set S of n cells (:func:`tv_from_uniform`), with
  ``outside`` of the N samples in no cell of S: ``TV = 1/2 (sum_{c in S} |count_c / N - 1/n| + outside / N)``;
  0 exactly when the samples are spread evenly over S, 1 when none lands in S. :func:`tv_of_distribution`
  is the same distance for exact probabilities.
* **Noise floor** (:func:`noise_floor`): the TV of N perfectly uniform draws over the n cells, mean and std over
  repeated draws: what no sampler can beat, on average, with N samples.
* **Entropy ratio** (:func:`entropy_ratio`): ``H(p) / log n`` (1 = uniform over the n cells).

:func:`level_uniformity` puts the last three together for one level's visited cells against a reference set.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from cuniform_torch.grid.cells import CellKeys, Grid

__all__ = ["Coverage", "coverage", "uniform_ceiling", "tv_from_uniform", "tv_of_distribution", "noise_floor",
           "entropy_ratio", "histogram_over", "level_uniformity"]


@dataclass
class Coverage:
    total: int
    """distinct cells over all steps (start included)"""
    per_level: list[int]
    """distinct cells at each step t = 0..T"""
    in_level_set: list[int] | None = None
    """distinct cells of L_t visited at step t (when a table policy was given)"""


def uniform_ceiling(num_cells: int, num_samples: int) -> float:
    """Expected distinct cells hit by ``num_samples`` uniform draws over ``num_cells`` cells."""
    return num_cells * (1.0 - (1.0 - 1.0 / num_cells) ** num_samples)


def coverage(states: Tensor, grid: Grid, table_policy=None) -> Coverage:
    """Coverage of ``states [N, T+1, d]`` on ``grid``; with a TablePolicy, also the cells of each L_t reached."""
    if states.ndim != 3 or states.shape[2] != grid.dim:
        raise ValueError(f"states must have shape [N, T+1, {grid.dim}], got {list(states.shape)}")
    N, T1, d = states.shape
    cells = grid.cells(states).reshape(-1, d)  # [N*(T+1), d]
    level = torch.arange(T1, device=states.device).repeat(N).unsqueeze(1)  # step index of each row
    keyed = torch.cat((level, cells), dim=1)
    keys = CellKeys.covering(keyed)
    per_level_keys = torch.unique(keys.pack(keyed))
    per_level_t = keys.unpack(per_level_keys)[:, 0]
    per_level = torch.bincount(per_level_t, minlength=T1).tolist()
    cell_keys = CellKeys.covering(cells)
    total = int(torch.unique(cell_keys.pack(cells)).numel())
    in_level = None
    if table_policy is not None:
        in_level = []
        for t in range(min(T1, table_policy.horizon + 1)):
            rows = table_policy.rows(states[:, t].to(table_policy.dtype), t)
            in_level.append(int(torch.unique(rows[rows >= 0]).numel()))
    return Coverage(total=total, per_level=per_level, in_level_set=in_level)


def tv_from_uniform(counts: Tensor, total: int, outside: int | float | Tensor = 0) -> float:
    """TV distance from uniform of a histogram ``counts [n]`` over the n cells of a reference set, out of
    ``total`` samples of which ``outside`` fell in no cell of the set."""
    n = counts.numel()
    dev = (counts.double() / total - 1.0 / n).abs().sum() + float(outside) / total
    return 0.5 * float(dev)


def tv_of_distribution(probs: np.ndarray | Tensor) -> float:
    """TV distance from uniform of exact probabilities ``probs [n]`` over n cells (summing to 1)."""
    p = torch.as_tensor(np.asarray(probs) if not isinstance(probs, Tensor) else probs, dtype=torch.float64)
    return 0.5 * float((p - 1.0 / p.numel()).abs().sum())


def noise_floor(num_cells: int, num_samples: int, repeats: int = 1,
                generator: torch.Generator | None = None) -> tuple[float, float]:
    """``(mean, std)`` over ``repeats`` of the TV from uniform of ``num_samples`` uniform draws over
    ``num_cells`` cells (std 0 for one repeat)."""
    tvs = []
    for _ in range(repeats):
        draws = torch.randint(0, num_cells, (num_samples,), generator=generator)
        tvs.append(tv_from_uniform(torch.bincount(draws, minlength=num_cells), num_samples))
    arr = np.array(tvs)
    return float(arr.mean()), float(arr.std(ddof=1)) if repeats > 1 else 0.0


def entropy_ratio(probs: Tensor, num_cells: int) -> float:
    """``H(probs) / log num_cells`` (``probs``: the visited cells' probabilities, zeros allowed; 1 when the
    reference set has one cell)."""
    p = probs.double()
    p = p[p > 0]
    return float(-(p * p.log()).sum()) / math.log(num_cells) if num_cells > 1 else 1.0


def histogram_over(cells: Tensor, reference: Tensor) -> tuple[Tensor, Tensor]:
    """``(counts [n], outside [k])``: how many of ``cells [N, d]`` are each cell of ``reference [n, d]``, and the
    counts of the k visited cells that are not in it."""
    n = reference.shape[0]
    keys = CellKeys.covering(torch.cat((cells, reference)))
    ref = torch.sort(keys.pack(reference)).values  # [n]
    uniq, counts = torch.unique(keys.pack(cells), return_counts=True)
    pos = torch.searchsorted(ref, uniq).clamp(max=n - 1)
    inside = ref[pos] == uniq
    hist = torch.zeros(n, dtype=torch.int64)
    hist[pos[inside]] = counts[inside]
    return hist, counts[~inside]


def level_uniformity(cells: Tensor, reference: Tensor, floor_generator: torch.Generator | None = None) -> dict[str, float]:
    """Uniformity of one level's visited ``cells [N, d]`` against the set ``reference [n, d]``: ``tv`` (from
    uniform over the set, outside mass counted), ``floor`` (one draw of the noise floor), ``entropy`` (ratio,
    of every visited cell's share, over ``log n``) and ``outside`` (share of the N not in the set)."""
    N, n = cells.shape[0], reference.shape[0]
    hist, outside_counts = histogram_over(cells, reference)
    outside = int(outside_counts.sum())
    shares = torch.cat((hist[hist > 0], outside_counts)).double() / N
    return {"tv": tv_from_uniform(hist, N, outside), "floor": noise_floor(n, N, 1, floor_generator)[0],
            "entropy": entropy_ratio(shares, n), "outside": outside / N}
