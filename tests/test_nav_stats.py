"""eval.navigate.records.stats / eval.navigate.results / eval.navigate.figures: Wilson values, cycle-time
histograms, summaries, paired comparisons (Newcombe interval, exact McNemar), markdown, the success figure and the
TensorBoard writer."""

from __future__ import annotations

import math
import random

import pytest

from eval.common.stats import wilson_interval
from eval.navigate.records.stats import (
    BINS_PER_DECADE,
    NUM_BINS,
    cycle_histogram,
    histogram_quantile,
    mcnemar_exact_p,
    merge_histograms,
    newcombe_paired_interval,
    paired_comparisons,
    summarize,
)
from eval.navigate.results import markdown

BIN = 10 ** (1 / BINS_PER_DECADE)


def rec(method: str, task: int, outcome: str, *, suite: str = "barn", budget: int = 256, seed: int = 0,
        time: float = 10.0, path_length: float = 5.0, hist: dict | None = None, wall_s: float = 1.0) -> dict:
    """One episode record as eval.navigate.run writes it."""
    return {"suite": suite, "task_id": task, "method": method, "budget": budget, "seed": seed,
            "outcome": outcome, "success": outcome == "goal", "time": time, "path_length": path_length,
            "steps": 100, "wall_s": wall_s, "cycle_hist": hist or {}, "cycles": 100}


def paired(method: str, outcomes: str, **kw) -> list[dict]:
    """Records of tasks 0.. with outcomes from a string: g = goal, c = collision, t = timeout."""
    names = {"g": "goal", "c": "collision", "t": "timeout"}
    return [rec(method, i, names[o], **kw) for i, o in enumerate(outcomes)]


# ------------------------------------------------------------------------------------------------ Wilson

@pytest.mark.parametrize("k, n, low, high", [(0, 10, 0.0, 0.2775), (5, 10, 0.2366, 0.7634), (10, 10, 0.7225, 1.0)])
def test_wilson_known_values(k, n, low, high):
    lo, hi = wilson_interval(k, n)
    assert lo == pytest.approx(low, abs=1e-4) and hi == pytest.approx(high, abs=1e-4)


# ------------------------------------------------------------------------------------------------ histograms

def test_histogram_bins_keys_and_clipping():
    # 1.01 ms: 40 * log10(101) = 80.17 -> bin 80; 1e-7 s clips to bin 0, 1000 s to the last bin
    h = cycle_histogram([1.01e-3, 1.01e-3, 1e-7, 1e3, 0.0])
    assert h == {"0": 2, "80": 2, str(NUM_BINS - 1): 1}
    assert NUM_BINS == 280
    assert merge_histograms([h, {"80": 3}, {}]) == {"0": 2, "80": 5, "279": 1}


def test_histogram_quantile_within_one_bin():
    rng = random.Random(0)
    times = sorted(10 ** rng.uniform(-4, -1) for _ in range(2001))
    h = cycle_histogram(times)
    true_median, true_p95 = times[1000], times[int(0.95 * 2001)]
    assert 1 / BIN <= histogram_quantile(h, 0.5) / true_median <= BIN
    assert 1 / BIN <= histogram_quantile(h, 0.95) / true_p95 <= BIN
    assert histogram_quantile({}, 0.5) is None


def test_histogram_quantile_first_bin_reaching_q():
    # 3 of 4 in bin 10, 1 in bin 20: the median and the 0.75 quantile are bin 10, the 0.76 quantile is bin 20
    h = {"10": 3, "20": 1}
    centre = lambda b: 1e-5 * 10 ** ((b + 0.5) / 40)  # noqa: E731
    assert histogram_quantile(h, 0.5) == pytest.approx(centre(10))
    assert histogram_quantile(h, 0.75) == pytest.approx(centre(10))
    assert histogram_quantile(h, 0.76) == pytest.approx(centre(20))


# ------------------------------------------------------------------------------------------------ summarize

def test_summarize_counts_and_rates():
    ms = cycle_histogram([2e-3] * 9 + [5e-2])  # median 2 ms, p95 50 ms
    records = (paired("a", "ggcct", hist=ms) + paired("b", "gg", budget=512)
               + [rec("a", 9, "goal", time=30.0, path_length=8.0)])
    rows = summarize(records)
    assert [(r["method"], r["budget"]) for r in rows] == [("a", 256), ("b", 512)]
    a = rows[0]
    assert (a["n"], a["successes"], a["collisions"], a["timeouts"]) == (6, 3, 2, 1)
    assert a["success_rate"] == pytest.approx(0.5) and a["collision_rate"] == pytest.approx(1 / 3)
    assert a["timeout_rate"] == pytest.approx(1 / 6)
    assert (a["success_rate_low"], a["success_rate_high"]) == pytest.approx(wilson_interval(3, 6))
    assert (a["collision_rate_low"], a["collision_rate_high"]) == pytest.approx(wilson_interval(2, 6))
    assert (a["timeout_rate_low"], a["timeout_rate_high"]) == pytest.approx(wilson_interval(1, 6))
    # over the three successes only: times 10, 10, 30 and lengths 5, 5, 8
    assert a["time_mean"] == pytest.approx(50 / 3) and a["time_median"] == pytest.approx(10.0)
    assert a["path_length_mean"] == pytest.approx(6.0) and a["path_length_median"] == pytest.approx(5.0)
    assert a["cycle_ms_median"] == pytest.approx(2.0, rel=BIN - 1)
    assert a["cycle_ms_p95"] == pytest.approx(50.0, rel=BIN - 1)
    assert a["wall_s"] == pytest.approx(6.0)
    assert rows[1]["cycle_ms_median"] is None and rows[1]["success_rate"] == 1.0
    none = summarize(paired("c", "ct"))[0]
    assert none["time_mean"] is None and none["path_length_median"] is None


# ------------------------------------------------------------------------------------------------ paired

def test_paired_all_wins_is_better():
    rows = paired_comparisons(paired("cu", "g" * 10) + paired("mppi", "c" * 5 + "t" * 5), ["mppi"])
    (r,) = rows
    assert (r["method"], r["baseline"], r["n"], r["wins"], r["losses"]) == ("cu", "mppi", 10, 10, 0)
    assert (r["method_successes"], r["baseline_successes"]) == (10, 0)
    assert r["p_value"] == pytest.approx(0.001953125) and r["diff"] == 1.0 and r["verdict"] == "better"
    assert r["diff_low"] > 0 and r["diff_high"] == 1.0


def test_paired_worse_and_equal_outcomes():
    worse = paired_comparisons(paired("cu", "c" * 10) + paired("mppi", "g" * 10), ["mppi"])[0]
    assert worse["verdict"] == "worse" and worse["diff"] == -1.0
    same = paired_comparisons(paired("cu", "ggcgt") + paired("mppi", "ggcgt"), ["mppi"])[0]
    assert (same["wins"], same["losses"], same["p_value"], same["verdict"]) == (0, 0, 1.0, "tie")


def test_paired_only_common_episodes():
    # cu ran tasks 0..4, the baseline tasks 0..2 and, for task 0, a second seed cu never ran
    records = paired("cu", "ggggg") + paired("mppi", "cgg") + [rec("mppi", 0, "goal", seed=7)]
    r = paired_comparisons(records, ["mppi"])[0]
    assert (r["n"], r["wins"], r["losses"], r["method_successes"]) == (3, 1, 0, 3)


def test_best_baseline_highest_rate_then_order():
    records = paired("m1", "ggcc") + paired("m2", "ggcc") + paired("m3", "gggc") + paired("cu", "gggg")
    # m3 is the best by rate wherever it sits in the list
    assert {r["baseline"] for r in paired_comparisons(records, ["m1", "m3", "m2"])} == {"m3"}
    # m1 and m2 tie: the earlier in `baselines` wins; the other baseline is compared too, itself is skipped
    no_m3 = [r for r in records if r["method"] != "m3"]
    rows = paired_comparisons(no_m3, ["m2", "m1"])
    assert {r["baseline"] for r in rows} == {"m2"} and [r["method"] for r in rows] == ["m1", "cu"]


def test_paired_groups_by_suite_and_budget():
    records = (paired("cu", "gg", budget=64) + paired("b", "cc", budget=64) + paired("cu", "gg", budget=128)
               + paired("b", "gg", budget=128) + paired("cu", "g", suite="gap", budget=64))
    rows = paired_comparisons(records, ["b"])
    assert [(r["suite"], r["budget"], r["wins"]) for r in rows] == [("barn", 64, 2), ("barn", 128, 0)]


def _wilson_by_bisection(k: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """Wilson bounds straight from their definition: the p with |k/n - p| = z sqrt(p (1 - p) / n)."""
    phat = k / n
    f = lambda p: (phat - p) ** 2 - z * z * p * (1 - p) / n  # noqa: E731

    def root(lo: float, hi: float) -> float:
        for _ in range(200):
            mid = (lo + hi) / 2
            lo, hi = (mid, hi) if (f(mid) > 0) == (f(lo) > 0) else (lo, mid)
        return (lo + hi) / 2

    return (0.0 if k == 0 else root(0.0, phat)), (1.0 if k == n else root(phat, 1.0))


@pytest.mark.parametrize("a, b, c, d", [(59, 6, 16, 80), (1, 1, 7, 12), (12, 9, 2, 3), (0, 10, 0, 0), (5, 3, 3, 5)])
def test_newcombe_interval_matches_definition(a, b, c, d):
    n = a + b + c + d
    p1, p2 = (a + b) / n, (a + c) / n
    l1, u1 = _wilson_by_bisection(a + b, n)
    l2, u2 = _wilson_by_bisection(a + c, n)
    cross, margins = a * d - b * c, (a + b) * (c + d) * (a + c) * (b + d)
    # Newcombe's phi*: ad - bc shrunk by n/2 towards 0 when positive, 0 inside [0, n/2], 0 for an empty margin
    phi = 0.0 if margins == 0 else (cross - n / 2 if cross > n / 2 else min(cross, 0)) / math.sqrt(margins)
    low = p1 - p2 - math.sqrt((p1 - l1) ** 2 - 2 * phi * (p1 - l1) * (u2 - p2) + (u2 - p2) ** 2)
    high = p1 - p2 + math.sqrt((p2 - l2) ** 2 - 2 * phi * (p2 - l2) * (u1 - p1) + (u1 - p1) ** 2)
    assert newcombe_paired_interval(a, b, c, d) == pytest.approx((max(-1, low), min(1, high)), abs=1e-9)


def test_newcombe_interval_published_example():
    # Cavo et al. (2012) as analysed in Fagerland, Lydersen & Laake (2014): -0.0621 (-0.1186 to -0.0046)
    low, high = newcombe_paired_interval(59, 6, 16, 80)
    assert (low, high) == pytest.approx((-0.1186, -0.0046), abs=1e-4)
    assert mcnemar_exact_p(3, 3) == 1.0 and mcnemar_exact_p(0, 0) == 1.0


# ------------------------------------------------------------------------------------------------ markdown

def test_markdown_tables():
    records = paired("cu", "g" * 10) + paired("mppi", "c" * 10)
    text = markdown(summarize(records), paired_comparisons(records, ["mppi"]))
    lo, hi = wilson_interval(10, 10)
    assert "## barn" in text and f"1.00 [{lo:.2f}, {hi:.2f}]" in text
    assert "| 256 | cu | mppi | 10 | 10 | 0 | +1.00 [" in text and "better" in text


# ------------------------------------------------------------------------------------------------ figures

def test_success_figure_is_png(tmp_path):
    from eval.navigate.figures import success_figure

    records = (paired("cu", "ggc", budget=64) + paired("cu", "ggg", budget=256)
               + paired("mppi", "gcc", budget=64) + paired("mppi", "ggc", budget=256, suite="gap"))
    out = success_figure(summarize(records), tmp_path / "fig" / "success.png", labels={"cu": "C-Uniform"})
    assert out == tmp_path / "fig" / "success.png"
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert [p.name for p in out.parent.iterdir()] == ["success.png"]  # no temporary left behind


def test_tensorboard_event_file(tmp_path):
    from eval.navigate.figures import write_tensorboard

    write_tensorboard(summarize(paired("cu", "gc", budget=64) + paired("cu", "gg", budget=128)), tmp_path)
    events = list(tmp_path.glob("events.out.tfevents.*"))
    assert events and events[0].stat().st_size > 0
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(tmp_path))
    acc.Reload()
    steps = [(e.step, e.value) for e in acc.Scalars("navigate/barn/cu/success_rate")]
    assert steps == [(64, 0.5), (128, 1.0)]


# ------------------------------------------------------------------------------------------------ bad input

def test_bad_input_raises_clear_errors():
    records = paired("cu", "gg") + paired("mppi", "gc")
    broken = [dict(r) for r in records]
    del broken[1]["outcome"]
    with pytest.raises(ValueError, match="record 1 lacks the field.*outcome"):
        summarize(broken)
    no_seed = [{k: v for k, v in r.items() if k != "seed"} for r in records]
    with pytest.raises(ValueError, match="lacks the field.*seed"):
        paired_comparisons(no_seed, ["mppi"])
    with pytest.raises(ValueError, match="baseline.*'dwa'.*no records"):
        paired_comparisons(records, ["mppi", "dwa"])
    with pytest.raises(ValueError, match="cycle times"):
        cycle_histogram([0.01, -1.0])
    with pytest.raises(ValueError, match="contradicts"):
        summarize([dict(records[0], success=False)])
    with pytest.raises(ValueError, match="appears twice"):
        paired_comparisons(records + [records[0]], ["mppi"])


def test_wilson_interval_always_holds_the_observed_rate():
    """At 0 / n and n / n the bound equals the rate exactly; rounding once put 6/6 above its own upper bound
    (a negative error bar, which matplotlib refuses)."""
    from eval.common.stats import wilson_interval

    for n in range(1, 200):
        for s in range(n + 1):
            low, high = wilson_interval(s, n)
            assert 0.0 <= low <= s / n <= high <= 1.0, (s, n, low, high)
    assert wilson_interval(6, 6)[1] == 1.0 and wilson_interval(0, 11)[0] == 0.0
