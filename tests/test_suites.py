"""precompute.worlds.suites: seeded forest and gap maps as data; inflation, sensing and reachability against slow references."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from cuniform_torch.envs import Circle, simulate
from cuniform_torch.systems import Dubins
from precompute.worlds.geometry import inflate, reachable, sensed
from precompute.worlds.suites import GAP_WIDTHS, SuiteError, forest, gaps, make_suite, validate_task

SEEDS = range(12)


@pytest.fixture(scope="module")
def forests():
    return [forest(s) for s in SEEDS]


def _raw_clearance(task, xy: np.ndarray) -> np.ndarray:
    """Slow reference: ``xy [P, 2]`` -> distance from each point to the raw discs, walls and bounds (a loop)."""
    best = np.full(xy.shape[0], np.inf)
    for x, y, r in task.discs:
        best = np.minimum(best, np.hypot(xy[:, 0] - x, xy[:, 1] - y) - r)
    for x0, y0, x1, y1 in task.walls:
        nx, ny = np.clip(xy[:, 0], x0, x1), np.clip(xy[:, 1], y0, y1)
        outside = np.hypot(xy[:, 0] - nx, xy[:, 1] - ny)
        inside = -np.minimum.reduce([xy[:, 0] - x0, x1 - xy[:, 0], xy[:, 1] - y0, y1 - xy[:, 1]])
        best = np.minimum(best, np.where(outside > 0, outside, inside))
    xmin, ymin, xmax, ymax = task.bounds
    return np.minimum(best, np.minimum.reduce([xy[:, 0] - xmin, xmax - xy[:, 0], xy[:, 1] - ymin, ymax - xy[:, 1]]))


# ------------------------------------------------------------------------------------------------ forest

def test_same_seed_same_map_and_no_global_rng():
    np.random.seed(1)
    state = np.random.get_state()[1].copy()
    a = forest(7)
    assert np.array_equal(np.random.get_state()[1], state), "forest touched numpy's global RNG"
    np.random.seed(99)  # a different global state must not change the map
    b = forest(7)
    assert np.array_equal(a.discs, b.discs) and np.array_equal(a.walls, b.walls)
    assert (a.start, a.goal, a.bounds, a.attempt) == (b.start, b.goal, b.bounds, b.attempt)
    c = forest(8)
    assert a.discs.shape != c.discs.shape or not np.allclose(a.discs, c.discs)


def test_suite_is_consecutive_seeds(forests):
    suite = make_suite("forest", 3, seed=4)
    assert [t.task_id for t in suite] == [4, 5, 6]
    for t, ref in zip(suite, forests[4:7]):
        assert np.array_equal(t.discs, ref.discs)


def test_disc_counts_within_range_both_ends_drawn(forests):
    counts = [t.discs.shape[0] for t in forests]
    assert all(10 <= n <= 30 for n in counts), counts
    assert all(np.all(t.discs[:, 2] == 1.0) for t in forests)
    # a two-value range: both ends must occur over 30 seeds (chance of missing one: 2^-29)
    small = {forest(s, num_discs=(3, 4), resolution=0.25).discs.shape[0] for s in range(30)}
    assert small == {3, 4}


def test_inflated_environment_matches_raw_clearance(forests):
    """Slow reference: a point collides on the inflated map exactly when the raw geometry is within r of it."""
    rng = np.random.default_rng(0)
    for task in forests[:4] + [gaps(0.8)]:
        xmin, ymin, xmax, ymax = task.bounds
        xy = rng.uniform((xmin, ymin), (xmax, ymax), size=(4000, 2))
        ref = _raw_clearance(task, xy)
        far = np.abs(ref - task.robot_radius) > 1e-9  # not on the boundary
        hit = task.environment.in_collision(torch.from_numpy(xy)).numpy()
        assert np.array_equal(hit[far], (ref <= task.robot_radius)[far])


def test_start_and_goal_free_with_a_ring(forests):
    ring = torch.linspace(0, 2 * math.pi, 720)
    for task in forests:
        env = task.environment
        pts = torch.tensor([task.start[:2], task.goal], dtype=torch.float64)
        assert not env.in_collision(pts).any()
        raw = inflate(task.discs, task.walls, task.bounds, 0.0)  # the robot's body must not touch the raw map
        for cx, cy in pts.tolist():
            body = torch.stack((cx + task.robot_radius * ring.cos(), cy + task.robot_radius * ring.sin()), -1)
            assert not raw.in_collision(body.double()).any()
        validate_task(task)
        keep_out = 1.0 + task.robot_radius + 0.5  # disc radius + robot radius + start_clearance
        for anchor in (task.start[:2], task.goal):
            assert np.hypot(*(task.discs[:, :2] - anchor).T).min() > keep_out


def test_start_in_collision_is_rejected(forests):
    task = forests[0]
    bad = inflate(np.array([[1.0, 0.2, 0.3]]), task.walls, task.bounds, task.robot_radius)
    with pytest.raises(SuiteError, match="start"):
        validate_task(dataclasses.replace(task, environment=bad))


def test_goal_reachable_and_flood_fill_can_say_no(forests):
    for task in forests:
        assert reachable(task.environment, task.start[:2], task.goal)
    task = forests[0]
    L = task.bounds[2]
    fence = np.array([[L / 2, task.bounds[1], L / 2 + 0.1, task.bounds[3]]])  # across the whole corridor
    blocked = inflate(task.discs, np.concatenate((task.walls, fence)), task.bounds, task.robot_radius)
    assert not reachable(blocked, task.start[:2], task.goal)


def test_redraw_is_deterministic():
    """A seed whose first draw is unreachable (found by the suite itself) keeps its redraw every time."""
    redrawn = next(t for t in (forest(s, num_discs=(30, 30)) for s in range(40)) if t.attempt > 0)
    again = forest(redrawn.task_id, num_discs=(30, 30))
    assert again.attempt == redrawn.attempt and np.array_equal(again.discs, redrawn.discs)


def test_sensed_matches_brute_force(forests):
    rng = np.random.default_rng(1)
    for task in forests[:4]:
        env = task.environment
        for _ in range(20):
            xy = torch.tensor(rng.uniform((0, -5), (35, 5)))
            rng_m = float(rng.uniform(0.5, 6.0))
            got = sensed(env, xy, rng_m)
            want = [o for o in env.obstacles if float(o.signed_distance(xy)) <= rng_m]
            assert got.obstacles == want and got.bounds == env.bounds
        # through the task: raw discs whose surface is within sensing_range of the robot
        xy = torch.tensor([10.0, 0.0], dtype=torch.float64)
        seen = {o.center for o in task.sensed_environment(xy).obstacles if isinstance(o, Circle) and o.radius > 1}
        d = np.hypot(task.discs[:, 0] - 10.0, task.discs[:, 1]) - task.discs[:, 2]
        assert seen == {(x, y) for (x, y, _), di in zip(task.discs.tolist(), d) if di <= task.sensing_range}


# ------------------------------------------------------------------------------------------------ gaps

@pytest.mark.parametrize("width", [0.5, 0.4, 0.1])
def test_gap_narrower_than_robot_refused(width):
    with pytest.raises(SuiteError, match=rf"{width}.*0\.5"):
        gaps(width)
    gaps(0.51)  # just wider: fine


def test_straight_line_through_gap():
    task = gaps(1.0)
    half, r = 0.5, task.robot_radius
    xs = torch.linspace(task.start[0], task.goal[0], 2001, dtype=torch.float64)

    def line(y):
        return torch.stack((xs, torch.full_like(xs, y)), -1)

    assert task.start[1] == task.goal[1] == 0.0
    assert not task.environment.in_collision(line(0.0)).any()
    assert not task.environment.in_collision(line(half - r - 0.01)).any()  # the centre's free band
    assert task.environment.in_collision(line(half - r + 0.01)).any()  # the body would touch the wall
    assert inflate(task.discs, task.walls, task.bounds, 0.0).in_collision(line(half + 0.01)).any()  # raw wall
    # open loop: a Dubins car driving straight reaches the goal; started off by more than the half width, it hits
    car = Dubins()
    straight = type("Straight", (), {"command": lambda self, x: x.new_zeros(1)})()
    x0 = torch.tensor(task.start, dtype=torch.float64)
    res = simulate(car, straight, x0, task.environment, task.goal, task.goal_tolerance, task.time_limit)
    assert res.outcome == "goal"
    off = x0.clone()
    off[1] = half + 0.05
    res = simulate(car, straight, off, task.environment, (task.goal[0], off[1]), task.goal_tolerance, task.time_limit)
    assert res.outcome == "collision" and task.walls[0, 0] - r <= float(res.path[-1, 0]) <= task.walls[0, 2]


def test_gaps_suite_sweep():
    suite = make_suite("gaps", 4)
    widths = [t.params["width"] for t in suite]
    assert widths == pytest.approx(np.linspace(*GAP_WIDTHS, 4).tolist()) and widths[1] == 0.8
    assert [t.task_id for t in suite] == [0, 1, 2, 3]
    for t in suite:
        gap = t.walls[1, 1] - t.walls[0, 3]
        assert gap == pytest.approx(t.params["width"])
        assert reachable(t.environment, t.start[:2], t.goal, resolution=0.02)


def test_make_suite_errors():
    with pytest.raises(SuiteError, match="forest, gaps"):
        make_suite("maze", 3)
    with pytest.raises(SuiteError, match="count must be >= 1"):
        make_suite("forest", 0)
    with pytest.raises(SuiteError, match="width"):
        make_suite("gaps", 2, width=0.9)
    with pytest.raises(SuiteError, match="robot_radius"):
        forest(0, width=0.4)
