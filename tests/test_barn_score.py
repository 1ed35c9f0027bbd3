"""The BARN Challenge's score (eval.navigate.records.score, eval.navigate.score) against hand-computed episodes: the clip at 2 OT and 8 OT, the
path cells converted to metres as the Challenge's run.py does, the polyline from the start through the path to the
goal, the geodesic where a world has no path, and the score beside success in budget.md."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from cuniform_torch.envs import Environment, Rect
from eval.navigate.budget import judge_folder, render
from eval.navigate.records.cycle_hist import cycle_histogram
from eval.navigate.records.score import barn_path_xy, barn_reference_length, barn_score, score_summary
from eval.navigate.records.store import EpisodeStore
from eval.navigate.score import episode_scores, geodesic_length, reference_lengths
from precompute.worlds.barn import CHALLENGE_GOAL, CHALLENGE_START, load_barn


@pytest.mark.parametrize("success, time, length, want", [
    (True, 20.0, 10.0, 5 / 20),      # OT 5 s, inside [2 OT, 8 OT]
    (True, 6.0, 10.0, 5 / 10),       # faster than 2 OT: clipped up to 10 s, the maximum 0.5
    (True, 100.0, 10.0, 5 / 40),     # slower than 8 OT: clipped down to 40 s, 1/8
    (False, 20.0, 10.0, 0.0),        # a failure scores 0
    (True, 33.0, 13.0, 6.5 / 33),
])
def test_score_of_hand_computed_episodes(success, time, length, want):
    assert barn_score(success, time, length) == pytest.approx(want, abs=1e-12)


def test_score_refuses_what_is_no_episode():
    with pytest.raises(ValueError, match="reference length"):
        barn_score(True, 10.0, 0.0)
    with pytest.raises(ValueError, match="time"):
        barn_score(True, float("nan"), 10.0)


def test_path_cells_become_metres_as_the_challenge_converts_them():
    # run.py: x = c * 0.15 - 0.075 - 30 * 0.15, y = r * 0.15 + 0.075 + 5
    np.testing.assert_allclose(barn_path_xy(np.array([[0, 0], [30, 1], [15, 29]])),
                               [[-4.575, 5.075], [-0.075, 5.225], [-2.325, 9.425]], atol=1e-12)


def test_reference_length_runs_from_the_start_through_the_path_to_the_goal():
    cells = np.array([[15, 0], [15, 10]])  # (-2.325, 5.075) and (-2.325, 6.575)
    want = math.hypot(0.075, 2.075) + 1.5 + math.hypot(0.075, 6.425)
    assert barn_reference_length(cells, CHALLENGE_START, CHALLENGE_GOAL) == pytest.approx(want, abs=1e-12)


def test_shipped_map_reference_as_the_challenge_loop_computes_it():
    """Map 0's path, by the Challenge's own loop (point by point), and its score at a hand time."""
    m = load_barn()[0]
    points = [(CHALLENGE_START[0], CHALLENGE_START[1])]
    for x, y in m.path.tolist():
        points.append((x * 0.15 - 0.075 - 4.5, y * 0.15 + 5.075))
    points.append(CHALLENGE_GOAL)
    length = sum(math.dist(a, b) for a, b in zip(points[:-1], points[1:]))
    got, note = reference_lengths({"suite": "barn", "barn_file": None}, [0])
    assert note == "" and got[0] == pytest.approx(length, rel=1e-6)
    assert barn_score(True, 20.0, got[0]) == pytest.approx(length / 2 / 20.0, rel=1e-6)


def test_geodesic_length_where_a_world_has_no_path():
    bounds = (0.0, -3.0, 10.0, 3.0)
    open_field = SimpleNamespace(bounds=bounds, goal=(9.05, 0.05), start=(1.05, 0.05, 0.0),
                                 environment=Environment([]))
    assert geodesic_length(open_field) == pytest.approx(8.0, abs=0.11)
    # a wall from y = -3 to 1 at x = 5 forces a detour over its top (y > 1): longer than the straight line
    walled = SimpleNamespace(bounds=bounds, goal=(9.05, 0.05), start=(1.05, 0.05, 0.0),
                             environment=Environment([Rect(4.9, -3.0, 5.1, 1.0)]))
    detour = 2 * math.hypot(4.0, 1.0)  # via the wall's top corner (5, 1)
    assert detour - 0.05 < geodesic_length(walled) < detour * 1.09


def test_score_summary_is_the_mean_with_its_interval():
    got = score_summary([0.2, 0.3, 0.25, 0.25])
    sd = float(np.std([0.2, 0.3, 0.25, 0.25], ddof=1))
    assert got["score_mean"] == pytest.approx(0.25)
    assert got["score_low"] == pytest.approx(0.25 - 1.96 * sd / 2)
    assert got["score_high"] == pytest.approx(0.25 + 1.96 * sd / 2)
    assert score_summary([])["score_mean"] is None


def _settings() -> dict:
    robot = dict(system="dubins", params=dict(speed=0.5, dt=0.2), radius=0.2, horizon=6)
    return dict(suite="barn", seed=0, sensing_range=3.0, horizon=6, lambda_=0.5, collision_penalty=1e6,
                cost_resolution=0.01, robot=robot, time_limit=100.0, barn_file=None,
                sources=dict(table="00000000000000aa", coverage_table=None, policy=None))


def _record(task: int, method: str, success: bool, time: float) -> dict:
    return dict(key=f"barn/{task}/{method}/16/0", suite="barn", task_id=task, method=method, budget=16, seed=task,
                repeat=0, outcome="goal" if success else "collision", success=success, time=time, path_length=9.0,
                steps=10, cycles=10, cycle_hist=cycle_histogram([0.001] * 10), wall_s=0.1)


def test_scores_of_a_folder_beside_success_in_budget_md(tmp_path):
    lengths, _ = reference_lengths(_settings(), [0, 2])
    recs = [_record(0, "mppi_1.0", True, 20.0), _record(2, "mppi_1.0", False, 30.0),
            _record(0, "cu_table", True, 30.0), _record(2, "cu_table", True, 200.0),
            _record(0, "uniform", True, 20.0), _record(1, "uniform", True, 20.0)]  # no map 1 in the file
    store = EpisodeStore(tmp_path / "run")
    store.open(_settings())
    for r in recs:
        store.append(r)
    scores, note = episode_scores(_settings(), recs)
    assert "no BARN map 1" in note and "barn/1/uniform/16/0" not in scores
    ot0, ot2 = lengths[0] / 2, lengths[2] / 2
    hand = {"mppi_1.0": (ot0 / min(max(20.0, 2 * ot0), 8 * ot0) + 0.0) / 2,
            "cu_table": (ot0 / min(max(30.0, 2 * ot0), 8 * ot0) + ot2 / (8 * ot2)) / 2}
    res = judge_folder(tmp_path / "run", [5])
    by_method = {c["method"]: c for c in res["cells"]}
    for method, want in hand.items():
        assert by_method[method]["score_mean"] == pytest.approx(want, rel=1e-9)
    assert by_method["uniform"]["score_mean"] is None  # one of its episodes has no reference: no partial mean
    md = render(res)
    assert "BARN score [95% CI]" in md and f"{hand['cu_table']:.2f} [" in md and "no BARN map 1" in md
