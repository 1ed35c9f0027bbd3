"""eval.navigate.gym_env: the gymnasium NavigationEnv follows simulate()'s closed loop exactly, and its API contracts."""

from __future__ import annotations

import importlib
import math
import sys
import warnings

import numpy as np
import pytest
import torch

gymnasium = pytest.importorskip("gymnasium")
from gymnasium.utils.env_checker import check_env  # noqa: E402

from cuniform_torch.envs import Circle, simulate  # noqa: E402
from eval.navigate import gym_env  # noqa: E402
from eval.navigate.gym_env import ENV_ID, NavigationEnv, make_env, register_envs  # noqa: E402
from precompute.worlds.robot import NAV_ROBOT  # noqa: E402
from precompute.worlds.suites import forest, gaps  # noqa: E402


class Constant:
    """Open loop: the same turn rate (rad/s) every cycle."""

    def __init__(self, omega: float) -> None:
        self.omega = omega

    def command(self, state: torch.Tensor) -> torch.Tensor:
        return state.new_tensor([self.omega])


class GoalSeeker:
    """Closed loop: turn toward the goal, 2 (rad/s)/rad of heading error, clipped to the robot's 1.5 rad/s."""

    def __init__(self, goal: tuple[float, float]) -> None:
        self.goal = goal

    def command(self, state: torch.Tensor) -> torch.Tensor:
        x, y, th = state.tolist()
        err = math.remainder(math.atan2(self.goal[1] - y, self.goal[0] - x) - th, 2 * math.pi)
        return state.new_tensor([max(-1.5, min(1.5, 2.0 * err))])


@pytest.fixture(scope="module")
def tasks() -> dict:
    """empty: 18 m straight at 0.5 m/s is 36 s of the 60 s limit (the default 35 m corridor would time out)."""
    return dict(gaps=gaps(width=1.0), forest=forest(0), empty=forest(0, length=20.0, num_discs=(0, 0)),
                short=gaps(width=1.0, time_limit=2.1))


def run_gym(env: NavigationEnv, controller, **reset) -> tuple[dict, list[float], bool, bool, dict]:
    """Drive ``env`` with ``controller.command`` until it ends; (observation, rewards, terminated, truncated, info)."""
    obs, info = env.reset(**reset)
    rewards: list[float] = []
    terminated = truncated = False
    assert env.observation_space.contains(obs)
    while not (terminated or truncated):
        u = controller.command(torch.as_tensor(obs["state"])).numpy()  # rad/s -> the normalised action
        obs, reward, terminated, truncated, info = env.step(env.to_action(u))
        rewards.append(reward)
        assert env.observation_space.contains(obs), {k: v for k, v in obs.items() if k in ("state", "goal")}
    return obs, rewards, terminated, truncated, info


def run_sim(task, controller):
    x0 = torch.tensor(task.start, dtype=torch.float64)
    return simulate(NAV_ROBOT.make_system(), controller, x0, task.environment, task.goal, task.goal_tolerance,
                    task.time_limit)


@pytest.mark.parametrize("make", [
    lambda t: NavigationEnv(t["forest"]), lambda t: NavigationEnv([t["gaps"], t["empty"]]),
    lambda t: make_env("gaps", index=None), lambda t: make_env("barn", index=0),
    lambda t: NavigationEnv(t["gaps"], system=NAV_ROBOT.__class__(system="ks_speed", params={}).make_system()),
    lambda t: (register_envs(), gymnasium.make(ENV_ID, suite="forest", index=0))[1],
    lambda t: (register_envs(), gymnasium.make(ENV_ID, tasks=t["gaps"]))[1],
], ids=["forest", "two-tasks", "gaps-all", "barn", "ks_speed", "make-suite", "make-tasks"])
def test_check_env_passes_without_warnings(tasks, make):
    """gymnasium's advice (a [-1, 1] action box, finite observation bounds) is followed: any warning fails."""
    env = make(tasks)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_env(env.unwrapped, skip_render_check=True)  # a made env: gymnasium asks for the unwrapped one
    assert env.action_space.low.tolist() == [-1.0] * env.action_space.shape[0]
    assert np.isfinite(env.observation_space["state"].low).all() and np.isfinite(env.observation_space["state"].high).all()


def test_observation_stays_inside_its_space_when_the_robot_leaves_the_bounds(tasks):
    """The last state of a run out of the workspace is one step outside it: still inside the state box."""
    task = tasks["empty"]
    away = (task.start[0] - 100.0, task.start[1])  # turn around and drive out behind the start
    obs, _, terminated, _, info = run_gym(NavigationEnv(task), GoalSeeker(away))
    xmin, ymin, xmax, ymax = task.environment.bounds
    assert terminated and info["outcome"] == "collision" and not xmin <= obs["state"][0] <= xmax


@pytest.mark.parametrize("name, make, expected", [
    ("gaps", lambda t: Constant(0.0), "goal"),
    ("gaps", lambda t: Constant(0.3), "collision"),
    ("gaps", lambda t: Constant(1.5), "timeout"),
    ("forest", lambda t: Constant(0.0), "collision"),
    ("forest", lambda t: Constant(-0.2), "collision"),
    ("forest", lambda t: GoalSeeker(t.goal), None),
    ("empty", lambda t: GoalSeeker(t.goal), "goal"),
])
def test_same_run_as_simulate(tasks, name, make, expected):
    task = tasks[name]
    ref = run_sim(task, make(task))
    if expected is not None:
        assert ref.outcome == expected  # the case really happens
    obs, rewards, terminated, truncated, info = run_gym(NavigationEnv(task), make(task))
    assert info["outcome"] == ref.outcome and info["steps"] == ref.steps == len(rewards)
    assert terminated == (ref.outcome != "timeout") and truncated == (ref.outcome == "timeout")
    np.testing.assert_allclose(obs["state"], ref.path[-1].numpy(), rtol=0, atol=1e-9)
    assert info["time"] == pytest.approx(ref.time) and info["path_length"] == pytest.approx(ref.path_length, abs=1e-9)


def test_straight_driver_collides_ahead_and_reaches_an_empty_goal(tasks):
    env = NavigationEnv(tasks["forest"])
    start = np.array(tasks["forest"].start[:2])
    *_, rewards, _, _, info = run_gym(env, Constant(0.0))
    obs = env._observation()
    assert info["outcome"] == "collision" and rewards[-1] < -5
    hit = [o for o in tasks["forest"].environment.obstacles if bool(o.contains(torch.as_tensor(obs["state"][:2])))]
    assert hit and all(isinstance(o, Circle) for o in hit)  # a disc ahead, not a wall or the bounds
    assert obs["state"][1] == pytest.approx(0.0, abs=1e-9) and obs["state"][0] > start[0]

    env = NavigationEnv(tasks["empty"])
    obs0, _ = env.reset()
    d0 = float(np.hypot(*(obs0["state"][:2] - obs0["goal"])))
    obs, rewards, terminated, truncated, info = run_gym(env, Constant(0.0))
    d1 = float(np.hypot(*(obs["state"][:2] - obs["goal"])))
    assert info["outcome"] == "goal" and terminated and not truncated
    assert sum(rewards) == pytest.approx(d0 - d1 + gym_env.GOAL_REWARD)  # progress + the goal bonus


def test_time_limit_truncates(tasks):
    env = NavigationEnv(tasks["short"])  # 2.1 s at dt 0.2 s -> 11 steps
    obs, rewards, terminated, truncated, info = run_gym(env, Constant(0.0))
    assert truncated and not terminated and info["outcome"] == "timeout"
    assert info["steps"] == 11 == len(rewards) and info["time"] == pytest.approx(2.2)
    with pytest.raises(ValueError, match="episode has ended"):
        env.step(np.zeros(1, dtype=np.float32))


def test_start_at_goal_is_already_done(tasks):
    task = gaps(width=1.0, goal_tolerance=20.0)
    ref = run_sim(task, Constant(0.0))
    _, info = NavigationEnv(task).reset()
    assert ref.steps == 0 and info["outcome"] == ref.outcome == "goal"


@pytest.mark.parametrize("action, message", [
    (np.zeros(2), r"shape \(1,\)"), (np.float32(0.0), r"shape \(1,\)"), (np.array([np.nan]), "finite"),
    ("left", "1 real numbers"), (np.array([0.5 + 1j]), "1 real numbers.*complex"),
    (np.array([0.5], dtype=object), "1 real numbers.*object"), (np.array([True]), "1 real numbers.*bool"),
    ([True], "1 real numbers.*bool"), ([0.5 + 1j], "1 real numbers.*complex"),
])
def test_bad_action_raises(tasks, action, message):
    env = NavigationEnv(tasks["gaps"])
    with pytest.raises(ValueError, match="reset"):
        env.step(np.zeros(1))
    env.reset()
    with pytest.raises(ValueError, match=message):
        env.step(action)


def test_actions_are_normalised_and_clipped(tasks):
    """[-1, 1] scales onto the robot's [-1.5, 1.5] rad/s; beyond it is clipped; to_action inverts to_control."""
    hi, lo = NavigationEnv(tasks["gaps"]), NavigationEnv(tasks["gaps"])
    assert hi.action_space.low.tolist() == [-1.0] and hi.action_space.high.tolist() == [1.0]
    assert hi.to_control(np.array([-1.0, ])).tolist() == [-1.5] and hi.to_control([0.5]).tolist() == [0.75]
    assert hi.to_control([9.0]).tolist() == [1.5] and hi.to_action([0.75]).tolist() == [0.5]
    hi.reset(), lo.reset()
    a, *_ = hi.step(np.array([9.0], dtype=np.float32))
    b, *_ = lo.step(np.array([1.0], dtype=np.float32))
    x0 = torch.tensor(tasks["gaps"].start, dtype=torch.float64)
    turned = NAV_ROBOT.make_system().step(x0[None], x0.new_tensor([[1.5]]))[0]  # full left: 1.5 rad/s
    assert a["state"].tolist() == b["state"].tolist() == turned.tolist()


def test_reset_seed_is_reproducible():
    env = make_env("gaps", index=None, count=5)
    picks = [env.reset(seed=s)[1]["task_index"] for s in range(20)]
    assert picks == [env.reset(seed=s)[1]["task_index"] for s in range(20)]
    assert len(set(picks)) > 1  # the seed does choose the task
    a, b = env.reset(seed=7)[0], env.reset(seed=7)[0]
    assert all(np.array_equal(a[k], b[k]) for k in a)
    assert env.reset(options={"task_index": 3})[1]["task_index"] == 3
    with pytest.raises(ValueError, match="task_index"):
        env.reset(options={"task_index": 5})


def test_observation_is_the_sensed_environment(tasks):
    task = tasks["forest"]
    env = NavigationEnv(task)
    obs, info = env.reset()
    sensed = info["environment"]
    assert 0 < len(sensed.obstacles) < len(task.environment.obstacles)  # the sensing range matters here
    circles = [(*o.center, o.radius) for o in sensed.obstacles if isinstance(o, Circle)]
    n, m = len(circles), len(sensed.obstacles) - len(circles)
    assert obs["obstacle_mask"].sum() == n and obs["obstacle_mask"][:n].all()
    np.testing.assert_array_equal(obs["obstacles"][:n], circles)
    assert not obs["obstacles"][n:].any() and obs["rect_mask"].sum() == m
    assert tuple(obs["bounds"]) == task.environment.bounds and tuple(obs["goal"]) == task.goal
    with pytest.raises(ValueError, match="max_circles=5"):
        NavigationEnv(task, max_circles=5)


def test_register_make_and_render(tasks):
    register_envs()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # gymnasium warns when an id is registered over
        register_envs()  # idempotent
    env = gymnasium.make(ENV_ID, tasks=tasks["gaps"], render_mode="rgb_array")
    env.reset(seed=0)
    env.step(np.zeros(1, dtype=np.float32))
    frame = env.render()
    assert frame.dtype == np.uint8 and frame.ndim == 3 and frame.shape[2] == 3 and frame.std() > 0
    env.close()


def test_make_env_picks_the_suite_task():
    forest1 = make_env("forest", index=1).tasks[0]
    assert forest1.task_id == 1 and forest1.robot_radius == 0.2 and forest1.time_limit == 120.0
    gap = make_env("gaps", index=5).tasks[0]  # the benchmark's gap task 5: width 0.9 m, 1.5 m off the line
    assert (gap.params["width"], gap.params["offset"], gap.robot_radius) == pytest.approx((0.9, 1.5, 0.2))
    assert make_env("barn", index=0).tasks[0].start == pytest.approx((-2.25, 3.0, 1.57))
    with pytest.raises(ValueError, match="past the 3 tasks"):
        make_env("gaps", index=3, count=3)


def test_missing_gymnasium_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "gymnasium", None)  # import gymnasium now raises ImportError
    monkeypatch.delitem(sys.modules, "eval.navigate.gym_env")
    with pytest.raises(ImportError, match=r"pip install -e '\.\[gym\]'"):
        importlib.import_module("eval.navigate.gym_env")


def test_integer_actions_are_numbers(tasks):
    env = NavigationEnv(tasks["gaps"])
    env.reset(seed=0)
    env.step(np.zeros(1, dtype=np.int64))  # an integer is a real number: accepted


@pytest.mark.parametrize("options", [{"unknown": 1}, {"task_index": 0, "seed": 3}, ["task_index"]])
def test_unknown_reset_options_are_refused(tasks, options):
    env = NavigationEnv(tasks["gaps"])
    with pytest.raises(ValueError, match="reset options may hold 'task_index' only"):
        env.reset(options=options)
    env.reset(options={"task_index": 0})  # the one option


def test_gymnasium_make_takes_make_envs_keywords():
    register_envs()
    env = gymnasium.make(ENV_ID, suite="gaps", index=5)
    assert env.unwrapped.tasks[0].params == make_env("gaps", index=5).tasks[0].params
    env.reset(seed=0)
    env.step(np.zeros(1, dtype=np.float32))
    env.close()
