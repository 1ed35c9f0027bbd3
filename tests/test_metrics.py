"""cuniform_torch.metrics, the one home of coverage, TV from uniform, the noise floor and the entropy ratio: each
against a slow reference or a closed form, and the build report measuring what it says with them."""

from __future__ import annotations

import math
from collections import Counter

import numpy as np
import pytest
import torch

from cuniform_torch import metrics
from cuniform_torch.metrics import (
    entropy_ratio,
    histogram_over,
    level_uniformity,
    noise_floor,
    tv_from_uniform,
    tv_of_distribution,
)
from cuniform_torch.policies.table import TablePolicy
from cuniform_torch.sampling.rollout import rollout


def _reference(cells: torch.Tensor, reference: torch.Tensor) -> tuple[list[int], int, float]:
    """Counts per reference cell, samples outside, TV: with a dictionary, one cell at a time."""
    seen = Counter(tuple(c) for c in cells.tolist())
    ref = [tuple(c) for c in reference.tolist()]
    counts = [seen.get(c, 0) for c in ref]
    outside = len(cells) - sum(counts)
    tv = 0.5 * (sum(abs(k / len(cells) - 1 / len(ref)) for k in counts) + outside / len(cells))
    return counts, outside, tv


@pytest.mark.parametrize("seed", [0, 1])
def test_histogram_and_tv_match_a_dictionary(seed):
    gen = torch.Generator().manual_seed(seed)
    cells = torch.randint(-3, 4, (3000, 2), generator=gen)  # 49 cells, negative indices included
    reference = torch.unique(torch.randint(-3, 4, (30, 2), generator=gen), dim=0)  # some of them, sorted
    counts, outside, tv = _reference(cells, reference)
    hist, out = histogram_over(cells, reference)
    assert hist.tolist() == counts and int(out.sum()) == outside and outside > 0
    assert tv_from_uniform(hist, len(cells), outside) == pytest.approx(tv, abs=1e-12)
    stats = level_uniformity(cells, reference)
    assert stats["tv"] == pytest.approx(tv, abs=1e-12) and stats["outside"] == outside / len(cells)
    shares = np.array(list(Counter(tuple(c) for c in cells.tolist()).values())) / len(cells)
    assert stats["entropy"] == pytest.approx(float(-(shares * np.log(shares)).sum()) / math.log(len(reference)))


def test_exact_distributions():
    assert tv_of_distribution(np.full(8, 1 / 8)) == pytest.approx(0.0)
    assert tv_of_distribution(np.eye(8)[0]) == pytest.approx(1 - 1 / 8)
    assert tv_of_distribution(torch.tensor([0.5, 0.5, 0.0, 0.0])) == pytest.approx(0.5)
    assert entropy_ratio(torch.full((8,), 1 / 8), 8) == pytest.approx(1.0)
    assert entropy_ratio(torch.tensor([1.0, 0.0]), 8) == 0.0
    assert tv_from_uniform(torch.zeros(4), 10, outside=10) == pytest.approx(1.0)  # nothing in the set


def test_noise_floor_matches_the_multinomial_closed_form():
    """E TV of N uniform draws over n cells ~ 1/2 sqrt(2 (n - 1) / (pi N)) (the normal approximation of each
    cell's |count - N/n|); 40 repeats at n = 50, N = 5000 put the mean within 5% of it."""
    n, N = 50, 5000
    mean, std = noise_floor(n, N, repeats=40, generator=torch.Generator().manual_seed(0))
    expected = 0.5 * math.sqrt(2 * (n - 1) / (math.pi * N))
    assert mean == pytest.approx(expected, rel=0.05)
    assert 0 < std < 0.2 * mean
    assert noise_floor(n, N, repeats=1, generator=torch.Generator())[1] == 0.0


def test_the_build_report_and_eval_share_one_tv():
    from eval.paper import uniformity
    from precompute import report

    assert report.tv_from_uniform is metrics.tv_from_uniform
    assert uniformity.level_uniformity is metrics.level_uniformity


def test_report_outside_fraction_is_the_share_of_rollouts_outside_each_level_set(dubins_table):
    """The build report's ``outside_fraction`` against an independent count: the same rollouts (same seed), each
    state's grid cell looked up in a set of L_t's cells. The paper's network leaks on real rollouts: none leave
    L_1 or L_2, then 10% to 40% of the states are outside at some level."""
    from precompute.report import uniformity_report

    rep = uniformity_report(dubins_table, num_rollouts=4000, seed=0)
    policy = TablePolicy(dubins_table)
    states, _ = rollout(policy.system, policy, torch.zeros(3), 4000, dubins_table.horizon,
                        generator=torch.Generator().manual_seed(0))
    cells = policy.grid.cells(states)  # [N, T+1, d]
    outside = []
    for t in range(dubins_table.horizon + 1):
        level = {tuple(c) for c in dubins_table.cells[dubins_table.level(t)].tolist()}
        outside.append(sum(tuple(c) not in level for c in cells[:, t].tolist()) / 4000)
    assert [lv.outside_fraction for lv in rep.levels] == pytest.approx(outside, abs=1e-12)
    assert outside[:3] == [0.0, 0.0, 0.0] and 0.1 < max(outside) < 0.4
