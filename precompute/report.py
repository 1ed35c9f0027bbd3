"""How C-Uniform a table really is, level by level.

For every level t: its cells n_t; the flow ratio of the step into it (max flow / n_{t-1} n_t; 1 means the
flow network admits exact C-Uniformity); the total-variation (TV) distance from uniform of the exact cell
distribution ``cell_probs``; and the TV of *real* rollouts: N trajectories sampled by the table policy on true
continuous states from the origin, with the runtime's default fallback (a state outside L_t counts as mass
outside the level set; it takes the action row of the nearest cell of L_t when within one cell, else uniform). That TV is set against the noise floor: the TV of N perfectly uniform draws over
the n_t cells (mean and std over repeated draws), which no sampler can beat with N samples.

``TV = 1/2 (sum over cells of L_t |count/N - 1/n_t| + outside/N)``; the TV and the noise floor are
:mod:`cuniform_torch.metrics`' (``tv_from_uniform`` stays importable from here).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch

from cuniform_torch.metrics import noise_floor, tv_from_uniform, tv_of_distribution
from cuniform_torch.policies.table import TablePolicy
from cuniform_torch.sampling.rollout import rollout
from cuniform_torch.tables.file import Table

__all__ = ["LevelReport", "UniformityReport", "uniformity_report", "format_report", "tv_from_uniform"]


@dataclass
class LevelReport:
    level: int
    cells: int
    flow_ratio: float | None
    """max flow / n_{t-1} n_t of the step into this level (None at level 0)"""
    tv_exact: float
    """TV of the exact propagated ``cell_probs`` from uniform"""
    tv_rollout: float
    """TV of the real rollouts' cell histogram from uniform (outside mass counted)"""
    tv_floor: float
    """mean TV of N perfectly uniform draws (the noise floor)"""
    tv_floor_std: float
    outside_fraction: float
    """share of rollouts whose state at this step is not in the level set"""


@dataclass
class UniformityReport:
    num_rollouts: int
    seed: int
    levels: list[LevelReport]
    miss_rate: float
    """share of all policy lookups during the rollouts that fell back to uniform probabilities"""
    nearest_rate: float
    """share of all policy lookups answered by the nearest cell of the level set"""

    def to_dict(self) -> dict:
        return {"num_rollouts": self.num_rollouts, "seed": self.seed, "miss_rate": self.miss_rate,
                "nearest_rate": self.nearest_rate, "levels": [asdict(lv) for lv in self.levels]}


def uniformity_report(
    table: Table,
    num_rollouts: int | None = None,
    seed: int = 0,
    device: torch.device | str = "cpu",
    floor_repeats: int = 10,
) -> UniformityReport:
    """Measure the table's uniformity; ``num_rollouts`` defaults to 10 x the largest level."""
    sizes = table.level_sizes
    N = int(num_rollouts) if num_rollouts is not None else 10 * max(sizes)
    if N < 1:
        raise ValueError(f"num_rollouts must be positive, got {N}")
    policy = TablePolicy(table, device=device)
    gen = torch.Generator(device=policy.device).manual_seed(seed)
    x0 = policy.build_start.to(device=policy.device, dtype=torch.float32)  # [d] the table's start
    states, _ = rollout(policy.system, policy, x0, N, table.horizon, generator=gen)  # [N, T+1, d]
    floor_gen = torch.Generator().manual_seed(seed + 1)
    levels = []
    for t, n in enumerate(sizes):
        rows = policy.rows(states[:, t], t)  # [N]
        inside = rows >= 0
        local = rows[inside] - int(table.level_offsets[t])
        counts = torch.bincount(local, minlength=n).cpu()
        outside = int((~inside).sum())
        exact = table.cell_probs[table.level(t)]
        floor_mean, floor_std = noise_floor(n, N, floor_repeats, floor_gen)
        levels.append(
            LevelReport(
                level=t,
                cells=n,
                flow_ratio=None if (t == 0 or table.method not in (None, "maxflow"))
                else float(table.flow_value[t - 1] / table.flow_target[t - 1]),
                tv_exact=tv_of_distribution(exact),
                tv_rollout=tv_from_uniform(counts, N, outside),
                tv_floor=floor_mean,
                tv_floor_std=floor_std,
                outside_fraction=outside / N,
            )
        )
    return UniformityReport(num_rollouts=N, seed=seed, levels=levels, miss_rate=policy.miss_rate,
                            nearest_rate=policy.nearest_rate)


def format_report(report: UniformityReport) -> str:
    """A fixed-width text table of the report."""
    lines = [
        f"uniformity per level ({report.num_rollouts} rollouts, seed {report.seed}; TV = total-variation distance from uniform)",
        f"{'level':>5} {'cells':>7} {'flow/nm':>8} {'TV exact':>9} {'TV rollout':>11} {'TV floor':>14} {'outside':>8}",
    ]
    for lv in report.levels:
        flow = "-" if lv.flow_ratio is None else f"{lv.flow_ratio:.4f}"
        lines.append(
            f"{lv.level:>5} {lv.cells:>7} {flow:>8} {lv.tv_exact:>9.4f} {lv.tv_rollout:>11.4f} "
            f"{lv.tv_floor:>7.4f}+-{lv.tv_floor_std:.4f} {lv.outside_fraction:>8.2%}"
        )
    lines.append(f"table lookups outside the level set: {report.nearest_rate:.2%} answered by the nearest cell, "
                 f"{report.miss_rate:.2%} uniform fallback")
    return "\n".join(lines)
