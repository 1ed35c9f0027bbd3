"""The suites where time matters (precompute.worlds.dynamic): moving discs and the sudden obstacle.

Seeded generators, a disc's position at a time, collisions judged at each step's true time (the simulator's and the
cost's), splits, and the benchmark's runner telling the cost the time.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from cuniform_torch.envs import Environment, MovingDiscs, NavigationCost, collision_mask, simulate
from precompute.worlds.dynamic import SUDDEN_APPEAR, moving, sudden, sudden_id, sudden_position
from precompute.worlds.robot import NAV_ROBOT
from precompute.worlds.suites import SuiteError
from precompute.worlds.tasks import make_task, make_tasks, split_of

DT = 0.2


def _crossing(x: float, t_cross: float, radius: float = 0.04, speed: float = 10.0) -> MovingDiscs:
    """One small fast disc moving along +y that crosses the x axis at ``(x, 0)`` at time ``t_cross`` only: it
    covers the point ``(x, 0)`` for ``2 radius / speed`` s (8 ms by default), a sliver of one 0.2 s step."""
    return MovingDiscs([[x, -speed * t_cross]], [[0.0, speed]], [radius])


class Straight:
    """Drives straight: turn rate 0."""

    def command(self, state: torch.Tensor) -> torch.Tensor:
        return torch.zeros(1, dtype=state.dtype)


# ------------------------------------------------------------------------------------------------ moving discs

def test_a_disc_is_where_its_velocity_puts_it():
    d = MovingDiscs([[1.0, 2.0], [0.0, 0.0]], [[0.5, -1.0], [0.0, 2.0]], [0.3, 0.4])
    assert torch.equal(d.centres(2.0), torch.tensor([[2.0, 0.0], [0.0, 4.0]], dtype=torch.float64))
    t = torch.tensor([[0.0, 1.0, 3.0]])  # [1, 3]
    c = d.centres(t)  # [1, 3, M, 2]
    assert c.shape == (1, 3, 2, 2)
    assert torch.allclose(c[0, 2], torch.tensor([[2.5, -1.0], [0.0, 6.0]]))
    held = d.held(2.0)  # still where it is at t = 2
    assert torch.equal(held.centres(0.0), d.centres(2.0)) and torch.equal(held.centres(9.0), d.centres(2.0))


def test_contains_at_times_matches_a_loop():
    """The batched test (points [N, T], times [T]) against a loop over points, times and discs."""
    g = torch.Generator().manual_seed(3)
    d = MovingDiscs(torch.rand(5, 2, generator=g) * 4, torch.randn(5, 2, generator=g), 0.3 + torch.rand(5, generator=g))
    xy = torch.rand(7, 6, 2, generator=g, dtype=torch.float64) * 4  # [N, T, 2]
    ts = torch.linspace(0.0, 2.0, 6, dtype=torch.float64)  # [T]
    got = d.contains(xy, ts)  # [N, T]
    want = torch.zeros(7, 6, dtype=torch.bool)
    for i in range(7):
        for k in range(6):
            for m in range(5):
                centre = d.start[m] + d.velocity[m] * float(ts[k])
                want[i, k] |= bool(torch.linalg.vector_norm(xy[i, k] - centre) <= d.radius[m])
    assert torch.equal(got, want) and bool(want.any()) and not bool(want.all())


def test_an_environment_with_moving_discs_needs_the_time():
    env = Environment([], bounds=(-5, -5, 5, 5), moving=_crossing(0.5, 1.0))
    with pytest.raises(ValueError, match="moving discs; give at="):
        env.in_collision(torch.zeros(2))
    with pytest.raises(ValueError, match="give dt"):
        NavigationCost(env, (4.0, 0.0))
    with pytest.raises(ValueError, match="shape"):
        MovingDiscs([[0.0, 0.0]], [[1.0, 0.0]], [[0.5]])
    with pytest.raises(ValueError, match="> 0"):
        MovingDiscs([[0.0, 0.0]], [[1.0, 0.0]], [0.0])


# ------------------------------------------------------------------------------------------------ the right step

def test_the_simulator_hits_a_moving_disc_at_the_step_it_is_there():
    """Straight at 0.5 m/s: step k is at x = 0.1 k, time 0.2 k. A sliver disc crosses (0.5, 0) at t = 1.0 only, so
    step 5 collides; checking step k against the discs at (k - 1) dt (or k + 1) misses it."""
    system = NAV_ROBOT.make_system()
    env = Environment([], bounds=(-5, -5, 5, 5), moving=_crossing(0.5, 5 * DT))
    x0 = torch.zeros(3)
    res = simulate(system, Straight(), x0, env, (4.0, 0.0), 0.1, 3.0)
    assert (res.outcome, res.steps) == ("collision", 5)
    assert abs(float(res.path[-1, 0]) - 0.5) < 1e-5
    late = Environment([], bounds=(-5, -5, 5, 5), moving=_crossing(0.5, 5 * DT + 0.05))  # gone past before 1.05 s
    assert simulate(system, Straight(), x0, late, (4.0, 0.0), 0.1, 3.0).outcome != "collision"


def test_the_cost_tests_each_rollout_step_at_its_time():
    """A rollout from time 0.4 s: step k is at 0.4 + 0.2 k. The sliver disc at (0.5, 0) at t = 1.4 s meets step 5
    only (x = 0.5); one step off in time and it meets none."""
    T = 8
    states = torch.zeros(1, T + 1, 3)
    states[0, :, 0] = 0.1 * torch.arange(T + 1)  # [T+1] x = 0.1 k
    env = Environment([], bounds=(-5, -5, 5, 5), moving=_crossing(0.5, 0.4 + 5 * DT))
    cost = NavigationCost(env, (4.0, 0.0), collision_penalty=1e6, per_state=True, time=0.4, dt=DT)
    plain = NavigationCost(Environment([], bounds=(-5, -5, 5, 5)), (4.0, 0.0), per_state=True)
    actions = torch.zeros(1, T, 1)
    assert float(cost(states, actions) - plain(states, actions)) == 1e6  # one colliding state: step 5
    assert bool(collision_mask(states, env, time=0.4, dt=DT)[0])
    cost.set_time(0.2)  # the same rollout one step earlier: the disc crosses x = 0.5 at its step 6, at x = 0.6
    assert float(cost(states, actions) - plain(states, actions)) == 0.0


# ------------------------------------------------------------------------------------------------ generators

def test_moving_is_reproducible_from_its_seed():
    np.random.seed(1)
    state = np.random.get_state()[1].copy()
    a = moving(4, robot_radius=0.2)
    assert np.array_equal(np.random.get_state()[1], state), "moving touched numpy's global RNG"
    np.random.seed(7)
    b = moving(4, robot_radius=0.2)
    for f in ("start", "velocity", "radius"):
        assert torch.equal(getattr(a.moving, f), getattr(b.moving, f))
        assert torch.equal(getattr(a.environment.moving, f), getattr(b.environment.moving, f))
    assert a.attempt == b.attempt and a.task_id == 4
    c = moving(5, robot_radius=0.2)
    assert len(c.moving) != len(a.moving) or not torch.equal(c.moving.start, a.moving.start)
    assert torch.allclose(a.environment.moving.radius, a.moving.radius + 0.2)


def test_moving_discs_cross_the_corridor_near_the_robot_and_never_hit_start_or_goal():
    task = moving(2, robot_radius=0.2)
    d = task.moving
    lo, hi = task.params["disc_speed"]
    speed = torch.linalg.vector_norm(d.velocity, dim=1)
    assert bool(((speed >= lo - 1e-12) & (speed <= hi + 1e-12)).all())
    assert bool((d.velocity[:, 1].abs() >= speed * math.cos(math.radians(30)) - 1e-9).all())  # across
    ts = torch.linspace(0.0, task.time_limit, 601, dtype=torch.float64)  # [S] every 0.1 s
    for p in (task.start[:2], task.goal):
        pts = torch.tensor(p, dtype=torch.float64).expand(len(ts), 2)  # [S, 2]
        assert not bool(task.environment.in_collision(pts, at=ts).any())
    corridor = ts[:, None, None] * 0 + d.centres(ts)  # [S, M, 2]: each disc is inside the corridor at some time
    inside = (corridor[..., 1].abs() < task.bounds[3]).any(dim=0)  # [M]
    assert bool(inside.all())


def test_a_walled_off_corridor_is_refused():
    """Every disc crosses a 1 m corridor at t = 0 (a robot speed so high that t_c is 0): no draw is open."""
    with pytest.raises(SuiteError, match="walled off"):
        moving(0, width=1.0, num_discs=(40, 40), disc_radius=(0.5, 0.5), robot_speed=1e6, crossing_jitter=0.0,
               time_limit=1.0, check_every=1.0, robot_radius=0.2)


def test_sudden_is_reproducible_and_sensed_late():
    a, b = sudden(3, 2, robot_radius=0.2), sudden(3, 2, robot_radius=0.2)
    assert a.params["offset"] == b.params["offset"] and np.array_equal(a.discs, b.discs)
    assert {sudden(3, k).params["offset"] for k in range(len(SUDDEN_APPEAR))} == {a.params["offset"]}
    assert sudden(4, 2).params["offset"] != a.params["offset"]
    assert sudden(3, 2, seed=1).params["offset"] != a.params["offset"]
    assert abs(a.params["offset"]) <= 0.5 and a.task_id == sudden_id(3, 2)
    assert sudden_position(a.task_id) == (3, 2)
    (disc,) = a.environment.obstacles
    assert disc.appear_time == SUDDEN_APPEAR[2]
    on_it = torch.from_numpy(a.discs[:1, :2].copy())  # [1, 2] the disc's centre
    assert bool(a.environment.in_collision(on_it)) and not bool(a.environment.in_collision(on_it, time=0.0))


# ------------------------------------------------------------------------------------------------ splits

@pytest.mark.parametrize("suite", ["moving", "sudden"])
def test_splits_are_disjoint_and_cover_all(suite):
    def key(t):
        return t.params["position"] if suite == "sudden" else t.task_id

    count = 10
    tasks = {s: make_tasks(suite, 0.2, count=count, split=s) for s in ("train", "test", "all")}
    for s in ("train", "test"):
        assert len(tasks[s]) == count and {split_of(key(t)) for t in tasks[s]} == {s}
    train, test = ({key(t) for t in tasks[s]} for s in ("train", "test"))
    assert not train & test
    assert [t.task_id for t in tasks["all"]] == sorted(t.task_id for t in tasks["all"])
    if suite == "sudden":  # a position's appearance times stay together
        assert [t.params["appear"] for t in tasks["test"][:len(SUDDEN_APPEAR)]] == list(SUDDEN_APPEAR)
    one = make_task(suite, tasks["test"][1].task_id, 0.2)
    assert one.task_id == tasks["test"][1].task_id and np.array_equal(one.discs, tasks["test"][1].discs)
    if suite == "moving":
        assert torch.equal(one.moving.start, tasks["test"][1].moving.start)


# ------------------------------------------------------------------------------------------------ the runner

def test_the_benchmark_tells_the_cost_when_the_obstacle_appears(tmp_path):
    """A disc sensed from 1 s on: the runner passes the cost to the simulator, so the cost sees it then and the
    robot turns away; a cost never told the time (stuck at 0) would never see it and drive into it."""
    from eval.navigate.episode import NavContext, NavJob, run_nav_episode
    from eval.navigate.robot_files import ensure_table

    robot = replace(NAV_ROBOT, horizon=6)  # a 6-step table builds in about a second
    ctx = NavContext(table=str(ensure_table(robot, tmp_path, quiet=True)), horizon=6)
    task = sudden(1, 0, appear=(1.0,), robot_radius=0.2)
    assert run_nav_episode(NavJob(task, "mppi_1.0", 64, seed=3), ctx)["outcome"] == "goal"
    never = replace(task, environment=Environment([replace(task.environment.obstacles[0], appear_time=math.inf)],
                                                  bounds=task.environment.bounds))
    assert run_nav_episode(NavJob(never, "mppi_1.0", 64, seed=3), ctx)["outcome"] == "collision"


def test_the_benchmark_refuses_what_cannot_see_time():
    from eval.navigate.run import NavConfig, check_config

    for suite in ("moving", "sudden"):
        with pytest.raises(ValueError, match="cfu_mppi cannot drive"):
            check_config(NavConfig(suite=suite, methods=("mppi_1.0", "cfu_mppi")))
        with pytest.raises(ValueError, match="--cost-to-go cannot serve"):
            check_config(NavConfig(suite=suite, methods=("mppi_1.0",), cost_to_go=True))
    check_config(NavConfig(suite="moving", methods=("mppi_1.0", "cu_table")))


def test_moving_and_sudden_are_scored_against_their_still_obstacles():
    """The moving suite's reference is the corridor's length (the discs left out); the sudden one's goes around
    its disc, so it is longer than the 4 m straight line."""
    from eval.navigate.score import reference_lengths

    settings = {"seed": 0, "robot": {"radius": 0.2}}
    lengths, note = reference_lengths({**settings, "suite": "moving"}, [0, 1])
    assert note == "" and all(17.8 <= v <= 18.0 * 1.08 for v in lengths.values()), lengths
    lengths, note = reference_lengths({**settings, "suite": "sudden"}, [0, 7])
    assert note == "" and all(4.0 < v < 4.0 * 1.5 for v in lengths.values()), lengths


@pytest.mark.parametrize("suite", ["moving", "sudden"])
def test_the_gym_environment_refuses_a_world_that_changes(suite):
    pytest.importorskip("gymnasium")
    from eval.navigate.gym_env import make_env

    index = 1 if suite == "sudden" else 0  # sudden task 0 is its disc visible from the start: a still world
    if suite == "sudden":
        make_env(suite, index=0)
    with pytest.raises(ValueError, match="still world known from the start"):
        make_env(suite, index=index)
