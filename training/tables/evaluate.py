"""Compare a policy with the C-Uniform table it was distilled from: KL, coverage, fallbacks, sizes.

Shapes: C table cells, N states (or rollouts), d state dimensions, A actions, T horizon, J points per cell.

Everything the distillation script needs besides its loop lives here, so that the same numbers can be computed
for any saved checkpoint::

    from cuniform_torch import load_policy, read_table
    from training.tables.evaluate import compare
    report = compare(load_policy("out/dubins.policy.pt"), read_table("out/dubins.npz"), eval_samples=[1000, 10000])

Definitions (the keys of :func:`compare`'s dict):

* ``kl_centres`` / ``kl_jitter``: mean KL(table || policy) = sum_u p log(p / q) (0 log 0 = 0) of the cells of each
  level t = 0..T, at the cell centres and at ``jitter_per_cell`` points drawn uniformly inside every cell (+-0.5
  cell on every dimension, angles wrapped; seed ``seed + JITTER_SEED_OFFSET``); the target at a jittered point is
  its cell's row, as a :class:`~cuniform_torch.TablePolicy` answers there. ``mean`` averages the levels,
  ``mean_rollout_levels`` the levels 0..T-1 whose rows drive a T-step rollout (level T is uniform by construction).
* ``coverage``: for each N, N real rollouts of the policy and of the table from the origin (seeded), with the
  distinct cells visited (``total``), per step (``per_level``), and cells of L_t visited at step t
  (``in_level_set``, see :func:`cuniform_torch.metrics.coverage`), the uniform-draw ceiling of each level, and
  the ratios policy / table. The table's rollouts also give its fallback rates (``nearest_rate``: lookups outside
  L_t answered by the nearest cell; ``miss_rate``: uniform fallback); an MLP answers every state, so its are 0.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from cuniform_torch.grid.cells import Grid
from cuniform_torch.metrics import coverage, uniform_ceiling
from cuniform_torch.policies.mlp import MLPPolicy
from cuniform_torch.policies.table import TablePolicy
from cuniform_torch.sampling.rollout import Policy, rollout
from cuniform_torch.tables.file import Table

__all__ = ["JITTER_SEED_OFFSET", "cell_centres", "cell_levels", "jitter_cells", "kl_rows", "policy_log_probs",
           "kl_per_level", "coverage_comparison", "sizes", "compare"]

_CHUNK = 65536  # states per forward pass when evaluating (bounds memory on large tables)
JITTER_SEED_OFFSET = 7919
""":func:`compare` draws its jittered points with seed ``seed + 7919``: apart from the distillation's training
jitter (``seed``) and validation points (``seed + 1``)"""


def cell_centres(table: Table) -> Tensor:
    """Centre of every cell of the table: ``[C, d]`` float64 (angles in [-pi, pi))."""
    return Grid.of(table.make_system()).centers(torch.from_numpy(table.cells), dtype=torch.float64)


def cell_levels(table: Table) -> Tensor:
    """Level t of every cell of the table: ``[C]`` int64."""
    return torch.repeat_interleave(torch.arange(table.horizon + 1), torch.tensor(table.level_sizes))


def jitter_cells(centres: Tensor, grid: Grid, rows: Tensor, generator: torch.Generator) -> Tensor:
    """Points drawn uniformly inside the cells ``rows [N]`` of ``centres [C, d]``: ``[N, d]`` float64.

    Each coordinate is the centre +- up to half a cell (uniform); angles are wrapped to [-pi, pi).
    """
    u = torch.rand((rows.shape[0], grid.dim), generator=generator, dtype=torch.float64) - 0.5  # [N, d] in [-0.5, 0.5)
    delta = torch.tensor(grid.cell_size, dtype=torch.float64)
    return grid.wrap(centres[rows] + u * delta)


def kl_rows(p: Tensor, log_q: Tensor) -> Tensor:
    """KL(p || q) of each row, ``sum_u p (log p - log q)`` with 0 log 0 = 0: ``[N, A], [N, A] -> [N]``."""
    return (torch.xlogy(p, p) - torch.where(p > 0, p * log_q, torch.zeros_like(p))).sum(dim=1)


def policy_log_probs(policy: Policy, x: Tensor, t: int) -> Tensor:
    """log pi(u | x, t) ``[N, A]``: exact log-softmax for an :class:`MLPPolicy`, else log of its probabilities."""
    with torch.no_grad():
        if isinstance(policy, MLPPolicy):
            return torch.log_softmax(policy(x, t), dim=1)
        return torch.log(policy.action_probs(x, t).clamp_min(1e-30))


def kl_per_level(policy: Policy, table: Table, points_per_cell: int = 0, seed: int = 0,
                 device: torch.device | str = "cpu") -> list[float]:
    """Mean KL(table || policy) over the cells of each level ``[T+1]``.

    ``points_per_cell = 0``: at the cell centres; ``J > 0``: at J jittered points per cell (generator seeded
    with ``seed``), each compared with its cell's row.
    """
    grid = Grid.of(table.make_system())
    centres = cell_centres(table)
    probs = torch.from_numpy(table.action_probs)  # [C, A]
    gen = torch.Generator().manual_seed(seed)
    dtype = getattr(policy, "dtype", torch.float32)
    out = []
    for t in range(table.horizon + 1):
        rows = torch.arange(int(table.level_offsets[t]), int(table.level_offsets[t + 1]))
        if points_per_cell > 0:
            rows = rows.repeat(points_per_cell)
            x = jitter_cells(centres, grid, rows, gen)
        else:
            x = centres[rows]
        total = 0.0
        for lo in range(0, rows.shape[0], _CHUNK):
            xb = x[lo:lo + _CHUNK].to(device=device, dtype=dtype)
            log_q = policy_log_probs(policy, xb, t).double().cpu()
            total += float(kl_rows(probs[rows[lo:lo + _CHUNK]].double(), log_q).sum())
        out.append(total / rows.shape[0])
    return out


def _level_stats(values: list[float], horizon: int) -> dict[str, Any]:
    return {"per_level": values, "mean": sum(values) / len(values),
            "mean_rollout_levels": sum(values[:horizon]) / max(horizon, 1), "max": max(values)}


def coverage_comparison(policy: Policy, table: Table, num_samples: int, seed: int = 0,
                        device: torch.device | str = "cpu", table_policy: TablePolicy | None = None) -> dict[str, Any]:
    """Coverage of ``num_samples`` rollouts of ``policy`` vs the table's own, from the origin (both seeded)."""
    system = table.make_system()
    grid = Grid.of(system)
    T = table.horizon
    tp = table_policy if table_policy is not None else TablePolicy(table, device=device)
    x0 = tp.build_start.to(dtype=tp.dtype, device=tp.device)  # [d] the table's start
    result: dict[str, Any] = {"num_samples": num_samples}
    for name, pol in (("table", tp), ("policy", policy)):
        gen = torch.Generator(device=tp.device).manual_seed(seed)
        tp.reset_counters()
        states, _ = rollout(system, pol, x0, num_samples, T, gen)  # [N, T+1, d]
        rates = (tp.nearest_rate, tp.miss_rate) if pol is tp else (0.0, 0.0)
        tp.reset_counters()
        cov = coverage(states, grid, tp)
        result[name] = {"total": cov.total, "per_level": cov.per_level, "in_level_set": cov.in_level_set,
                        "in_level_set_sum": sum(cov.in_level_set), "nearest_rate": rates[0], "miss_rate": rates[1]}
    a, b = result["policy"], result["table"]
    ratio = [x / y if y else math.nan for x, y in zip(a["in_level_set"], b["in_level_set"])]
    result["level_sizes"] = table.level_sizes
    result["uniform_ceiling"] = [uniform_ceiling(n, num_samples) for n in table.level_sizes]
    result["ratio"] = {"total": a["total"] / b["total"], "in_level_set": ratio,
                       "in_level_set_sum": a["in_level_set_sum"] / b["in_level_set_sum"], "min_level": min(ratio)}
    return result


def sizes(table: Table, table_path: str | os.PathLike, checkpoint_path: str | os.PathLike) -> dict[str, Any]:
    """Bytes of the table (``cells`` + ``action_probs`` arrays; its file) vs the checkpoint file, and their ratios."""
    arrays = int(table.cells.nbytes + table.action_probs.nbytes)
    table_file, ckpt = Path(table_path).stat().st_size, Path(checkpoint_path).stat().st_size
    return {"table_arrays_bytes": arrays, "table_file_bytes": table_file, "checkpoint_bytes": ckpt,
            "compression_ratio": arrays / ckpt, "file_ratio": table_file / ckpt}


def compare(policy: Policy, table: Table, eval_samples: Sequence[int] = (1000, 10000), seed: int = 0,
            jitter_per_cell: int = 4, device: torch.device | str = "cpu") -> dict[str, Any]:
    """KL per level (centres and jittered points) and coverage vs the table for every N in ``eval_samples``."""
    tp = TablePolicy(table, device=device)
    T, jitter_seed = table.horizon, seed + JITTER_SEED_OFFSET
    return {
        "kl_centres": _level_stats(kl_per_level(policy, table, 0, seed, device), T),
        "kl_jitter": {**_level_stats(kl_per_level(policy, table, jitter_per_cell, jitter_seed, device), T),
                      "points_per_cell": jitter_per_cell, "seed": jitter_seed},
        "coverage": {str(n): coverage_comparison(policy, table, n, seed, device, tp) for n in eval_samples},
    }
