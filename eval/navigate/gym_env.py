"""A gymnasium environment over the navigation suites: the closed loop of :func:`cuniform_torch.envs.simulate`.

Shapes used in this module: d state dimensions (x, y, heading first), q action dimensions, C = ``max_circles``
circle slots, R = ``max_rects`` rectangle slots.

One :meth:`NavigationEnv.step` is one control cycle of :func:`~cuniform_torch.envs.simulate`, with the same
rules, so a controller meets the same task on both: ``system.step(x[None], u[None])[0]`` in float64 on the CPU;
a non-finite state raises ``ValueError``; the new position is checked against the *true* inflated environment
(``task.environment``: every obstacle, sensed or not, and the bounds), then against the goal (xy distance <=
``goal_tolerance``), then against the time limit (``max(1, ceil(time_limit / dt - 1e-9))`` steps). A step that
both collides and reaches the goal is a collision. A start within the goal tolerance is already at the goal:
:meth:`~NavigationEnv.reset` then reports ``info["outcome"] == "goal"`` and the episode has no step.

Action: a float32 ``[q]`` in the normalised box ``[-1, 1]`` (gymnasium's advice); :meth:`NavigationEnv.step`
clips it to ``[-1, 1]`` and scales it affinely onto the box spanned by ``system.action_set()`` (the Dubins robot:
-1 -> -1.5 rad/s, 0 -> 0, 1 -> 1.5 rad/s). :meth:`~NavigationEnv.to_action` and :meth:`~NavigationEnv.to_control`
convert between the two.

Observation (a ``Dict``; the robot's centre is a point, every obstacle is already inflated by the robot radius).
Every Box has finite bounds that the contents provably stay inside, derived from the tasks at construction
(nothing is clipped): W is the union of the tasks' inflated workspace bounds (``task.environment.bounds``).

* ``"state"``: float64 ``[d]``, the simulated state (m, m, rad, ...), exactly. Space: x, y in W widened by
  one step's travel (|v| dt: the episode ends at the first step that leaves W, so the last state is at most one
  step outside it), the heading in ``[-pi, pi]`` (the systems wrap it; a start heading outside widens it), a
  speed in ``[min_speed, max_speed]``. A system without ``speed`` / ``max_speed`` leaves x, y and any further
  dimension unbounded (then check_env warns);
* ``"goal"``: float64 ``[2]``, the goal (m); space: W and the tasks' goals;
* ``"bounds"``: float64 ``[4]``, (xmin, ymin, xmax, ymax) the centre must stay inside (m); space: W;
* ``"obstacles"``: float64 ``[C, 3]``, the sensed inflated circles (x, y, radius) in the environment's order,
  then zero rows; ``"obstacle_mask"``: int8 ``[C]``, 1 for a real row. Space: per column, the least and the
  greatest value over every task's circles (a sensed circle is one of its task's circles), W's for x and y
  and 0 (the padding); the radius's top at least 1 m (no circle at all would leave a degenerate ``[0, 0]``);
* ``"rects"``: float64 ``[R, 4]``, the sensed inflated rectangles (xmin, ymin, xmax, ymax), then zero rows;
  ``"rect_mask"``: int8 ``[R]``. Space: per column, the least and the greatest over every task's rects, W's
  x or y and 0. (The suites' walls inflate to two rects and four corner circles each, see
  :func:`precompute.worlds.geometry.inflate`; the circles go to ``"obstacles"``.)

Reward per step: progress toward the goal (previous xy distance - new xy distance, m), plus
:data:`GOAL_REWARD` on reaching the goal, minus :data:`COLLISION_PENALTY` on a collision (no goal bonus then).
``terminated`` on goal or collision; ``truncated`` at the time limit.

``info`` after :meth:`~NavigationEnv.reset` and every step: ``"outcome"`` (``"goal"``, ``"collision"``,
``"timeout"`` or None while running), ``"time"`` (s), ``"path_length"`` (m, sum of xy segment lengths),
``"steps"``, ``"task_index"`` and ``"environment"``: the :class:`~cuniform_torch.envs.Environment` the robot
senses now (``task.sensed_environment(xy)``), ready for a :class:`~cuniform_torch.envs.NavigationCost`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

try:
    import gymnasium
    from gymnasium import spaces
except ImportError as err:  # gymnasium is the optional extra "gym"
    raise ImportError("the gymnasium environment needs gymnasium: pip install -e '.[gym]'") from err

from cuniform_torch.envs import COLLISION, GOAL, TIMEOUT, Circle, Environment, Rect
from precompute.worlds.robot import NAV_ROBOT
from precompute.worlds.suites import NavTask, make_suite
from precompute.worlds.tasks import DEFAULT_COUNTS, make_tasks

__all__ = ["NavigationEnv", "register_envs", "make_env", "ENV_ID", "MAX_CIRCLES", "MAX_RECTS", "GOAL_REWARD",
           "COLLISION_PENALTY"]

ENV_ID = "cuniform/Navigation-v0"
MAX_CIRCLES = 400
"""default circle slots: BARN maps have up to about 365 circles; a forest up to 30 discs + 8 wall corners"""
MAX_RECTS = 16
"""default rectangle slots: forest and gaps have 2 walls -> 4 inflated rects; BARN none"""
GOAL_REWARD = 10.0
COLLISION_PENALTY = 10.0

_DTYPE = torch.float64


# ------------------------------------------------------------------------------------------------ helpers

def _as_tasks(tasks: NavTask | Sequence[NavTask]) -> list[NavTask]:
    """One task or a non-empty sequence of tasks -> a list; anything else raises ValueError."""
    items = [tasks] if isinstance(tasks, NavTask) else tasks
    if isinstance(items, (str, bytes)) or not isinstance(items, Sequence) or len(items) == 0:
        raise ValueError(f"NavigationEnv: tasks must be a NavTask or a non-empty list of them, got {tasks!r}")
    for k, task in enumerate(items):
        if not isinstance(task, NavTask):
            raise ValueError(f"NavigationEnv: task {k} must be a NavTask, got {type(task).__name__}")
    return list(items)


def _count_shapes(env: Environment, who: str) -> tuple[int, int]:
    """(circles, rects) in ``env``; any other obstacle type raises ValueError (the observation has no slot)."""
    circles = rects = 0
    for k, obs in enumerate(env.obstacles):
        if isinstance(obs, Circle):
            circles += 1
        elif isinstance(obs, Rect):
            rects += 1
        else:
            raise ValueError(f"{who}: obstacle {k} is a {type(obs).__name__}; the observation holds only Circle and Rect")
    return circles, rects


def _padded_tables(env: Environment, max_circles: int, max_rects: int) -> dict[str, np.ndarray]:
    """The circles ``[C, 3]``, rects ``[R, 4]`` of ``env`` zero-padded, with their int8 masks ``[C]``, ``[R]``."""
    circles = [(*o.center, o.radius) for o in env.obstacles if isinstance(o, Circle)]
    rects = [(o.xmin, o.ymin, o.xmax, o.ymax) for o in env.obstacles if isinstance(o, Rect)]
    out = dict(obstacles=np.zeros((max_circles, 3)), obstacle_mask=np.zeros(max_circles, dtype=np.int8),
               rects=np.zeros((max_rects, 4)), rect_mask=np.zeros(max_rects, dtype=np.int8))
    if circles:
        out["obstacles"][:len(circles)] = circles
        out["obstacle_mask"][:len(circles)] = 1
    if rects:
        out["rects"][:len(rects)] = rects
        out["rect_mask"][:len(rects)] = 1
    return out


def _slots(value: Any, what: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
        raise ValueError(f"NavigationEnv: {what} must be an integer >= 0, got {value!r}")
    return int(value)


def _speed_range(system: Any) -> tuple[float, float] | None:
    """(least, greatest) signed speed (m/s) of a built-in ``(x, y, heading[, speed])`` system: ``(-speed, speed)``
    of a fixed-speed one (dubins, ks), ``(min_speed, max_speed)`` of ks_speed; None when it declares neither."""
    lo, hi = getattr(system, "min_speed", None), getattr(system, "max_speed", None)
    if lo is None or hi is None:
        speed = getattr(system, "speed", None)
        lo, hi = (None, None) if speed is None else (-abs(speed), abs(speed))
    ok = all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in (lo, hi))
    return (float(lo), float(hi)) if ok else None


def _max_travel(system: Any) -> float | None:
    """The most the centre moves in one step (m): |v| dt with the speed's bound, plus 1e-6 m against rounding."""
    speeds = _speed_range(system)
    return None if speeds is None else max(abs(speeds[0]), abs(speeds[1])) * float(system.dt) + 1e-6


def _check_system(system: Any) -> None:
    """The closed loop needs ``step``, ``dt``, ``periodic`` (d >= 3: x, y, heading) and ``action_set``."""
    for name in ("step", "action_set"):
        if not callable(getattr(system, name, None)):
            raise ValueError(f"NavigationEnv: system must have a {name}() method, got {type(system).__name__}")
    if not hasattr(system, "dt") or not hasattr(system, "periodic"):
        raise ValueError(f"NavigationEnv: system must have dt and periodic, got {type(system).__name__}")
    dt = system.dt
    if isinstance(dt, bool) or not isinstance(dt, (int, float)) or not math.isfinite(dt) or dt <= 0:
        raise ValueError(f"NavigationEnv: system.dt must be a finite number > 0, got {dt!r}")
    if len(system.periodic) < 3:
        raise ValueError(f"NavigationEnv: the system's state must be (x, y, heading, ...), got d = {len(system.periodic)}")


# ------------------------------------------------------------------------------------------------ environment

class NavigationEnv(gymnasium.Env):
    """Drive ``system`` (default ``NAV_ROBOT.make_system()``) through one :class:`~precompute.worlds.suites.NavTask`, or
    one of ``tasks`` per :meth:`reset` (``options={"task_index": k}``, else drawn from the reset's seed).

    The action is a float ``[q]`` in ``[-1, 1]`` (normalised; values outside are **clipped** to it), scaled onto
    the box spanned by ``system.action_set()`` (its per-dimension min and max: the Dubins robot's turn rate,
    -1.5 to 1.5 rad/s) before the step; :meth:`to_action` turns a control (rad/s) into the action. A state of more than 3 dimensions
    starts at ``(*task.start, 0, ...)``. ``max_circles`` / ``max_rects``: observation slots (module docstring);
    a task with more obstacles than slots, or without workspace bounds, is refused.

    :param tasks: one task or a non-empty list of them (one per reset)
    :param system: the robot, ``(x, y, heading, ...)`` states; default ``NAV_ROBOT.make_system()``
    :param max_circles: circle slots C of the observation
    :param max_rects: rectangle slots R of the observation
    :param render_mode: None or ``"rgb_array"`` ``render_mode="rgb_array"`` draws with matplotlib (Agg).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 5}

    def __init__(self, tasks: NavTask | Sequence[NavTask], system: Any = None, max_circles: int = MAX_CIRCLES,
                 max_rects: int = MAX_RECTS, render_mode: str | None = None) -> None:
        self.tasks = _as_tasks(tasks)
        self.system = NAV_ROBOT.make_system() if system is None else system
        _check_system(self.system)
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"NavigationEnv: render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.render_mode = render_mode
        self.max_circles, self.max_rects = _slots(max_circles, "max_circles"), _slots(max_rects, "max_rects")
        self._check_slots()
        actions = self.system.action_set(dtype=_DTYPE, device="cpu")  # [A, q]
        self._low, self._high = actions.min(dim=0).values, actions.max(dim=0).values  # [q] each, float64
        self._mid, self._half = (self._low + self._high) / 2, (self._high - self._low) / 2  # [q]: -1 -> low, 1 -> high
        self.dt = float(self.system.dt)
        q = self._low.shape[0]
        self.action_space = spaces.Box(-1.0, 1.0, shape=(q,), dtype=np.float32)
        self.observation_space = self._make_observation_space(len(self.system.periodic))
        self._x: torch.Tensor | None = None

    def _check_slots(self) -> None:
        """Every task's full environment (what can ever be sensed) must fit the observation's slots and have
        bounds (the observation's boxes are finite)."""
        for k, task in enumerate(self.tasks):
            if task.environment.moving is not None or any(o.appear_time > 0 for o in task.environment.obstacles):
                raise ValueError(f"NavigationEnv: task {k} ({task.suite} {task.task_id}) has moving discs or an obstacle "
                                 "that appears late; the observation is a still world known from the start (the "
                                 "benchmark, python -m eval.navigate, runs those suites)")
            if task.environment.bounds is None:
                raise ValueError(f"NavigationEnv: task {k}'s environment has no bounds; the observation needs "
                                 "finite workspace bounds (give the task's Environment bounds)")
            circles, rects = _count_shapes(task.environment, f"NavigationEnv: task {k}")
            if circles > self.max_circles or rects > self.max_rects:
                raise ValueError(f"NavigationEnv: task {k} has {circles} circles and {rects} rects; the observation "
                                 f"holds max_circles={self.max_circles}, max_rects={self.max_rects} (raise them)")

    def _make_observation_space(self, d: int) -> spaces.Dict:
        """Finite boxes every observation stays inside (module docstring: how each is derived)."""
        ws = np.array([t.environment.bounds for t in self.tasks], dtype=np.float64)  # [N, 4]
        w_lo, w_hi = ws[:, :2].min(axis=0), ws[:, 2:].max(axis=0)  # [2] each: W
        goals = np.array([t.goal for t in self.tasks], dtype=np.float64)  # [N, 2]
        goal_lo, goal_hi = np.minimum(w_lo, goals.min(axis=0)), np.maximum(w_hi, goals.max(axis=0))
        starts = np.array([t.start for t in self.tasks], dtype=np.float64)  # [N, 3]
        state_lo, state_hi = np.full(d, -np.inf), np.full(d, np.inf)
        travel = _max_travel(self.system)
        if travel is not None:  # the state leaves W by at most one step (that step ends the episode)
            state_lo[:2] = np.minimum(w_lo, starts[:, :2].min(axis=0)) - travel
            state_hi[:2] = np.maximum(w_hi, starts[:, :2].max(axis=0)) + travel
        state_lo[2], state_hi[2] = min(-math.pi, starts[:, 2].min()), max(math.pi, starts[:, 2].max())
        speeds = _speed_range(self.system)
        if d == 4 and speeds is not None:  # (x, y, heading, speed): clipped to [min_speed, max_speed] each step
            state_lo[3], state_hi[3] = speeds
        circles = np.zeros((1, 3))  # [1 + M, 3]: the zero padding row, then every circle of every task
        rects = np.zeros((1, 4))
        for task in self.tasks:
            tables = _padded_tables(task.environment, self.max_circles, self.max_rects)
            circles = np.concatenate([circles, tables["obstacles"][tables["obstacle_mask"] == 1]])
            rects = np.concatenate([rects, tables["rects"][tables["rect_mask"] == 1]])
        x_lo, x_hi = np.array([*w_lo, *w_lo]), np.array([*w_hi, *w_hi])  # [4]: (x, y, x, y) of W
        c_lo, c_hi = np.minimum(circles.min(axis=0), [*w_lo, 0.0]), np.maximum(circles.max(axis=0), [*w_hi, 0.0])
        r_lo, r_hi = np.minimum(rects.min(axis=0), x_lo), np.maximum(rects.max(axis=0), x_hi)
        c_hi[2] = max(c_hi[2], 1.0)  # no circles in any task: radius [0, 1] m, not a degenerate [0, 0]

        def box(lo: Any, hi: Any, shape: tuple[int, ...]) -> spaces.Box:
            return spaces.Box(np.broadcast_to(np.asarray(lo, dtype=np.float64), shape).copy(),
                              np.broadcast_to(np.asarray(hi, dtype=np.float64), shape).copy(), dtype=np.float64)

        return spaces.Dict(dict(
            state=box(state_lo, state_hi, (d,)),
            goal=box(goal_lo, goal_hi, (2,)),
            bounds=box(x_lo, x_hi, (4,)),
            obstacles=box(c_lo, c_hi, (self.max_circles, 3)),
            obstacle_mask=spaces.MultiBinary(self.max_circles),
            rects=box(r_lo, r_hi, (self.max_rects, 4)),
            rect_mask=spaces.MultiBinary(self.max_rects),
        ))

    def to_action(self, control: Any) -> np.ndarray:
        """``control [q]`` in the system's units (rad/s) -> the normalised float64 action ``[q]`` (``[-1, 1]`` inside
        the action set's box); the inverse of :meth:`to_control` there."""
        u = torch.as_tensor(np.asarray(control, dtype=np.float64))
        a = torch.where(self._half > 0, (u - self._mid) / torch.where(self._half > 0, self._half, 1.0), 0.0)
        return a.numpy()

    def to_control(self, action: Any) -> np.ndarray:
        """Normalised ``action [q]`` -> the float64 control ``[q]`` :meth:`step` applies (clipped to ``[-1, 1]``,
        scaled onto the action set's box)."""
        return self._action(action).numpy()

    # -------------------------------------------------------------------------------------------- episode

    def _pick_task(self, options: dict | None) -> int:
        """``options["task_index"]`` if given, else one task drawn from ``self.np_random`` (0 for one task)."""
        if options is not None and (not isinstance(options, dict) or set(options) - {"task_index"}):
            unknown = sorted(map(str, set(options) - {"task_index"})) if isinstance(options, dict) else options
            raise ValueError(f"NavigationEnv: reset options may hold 'task_index' only, got {unknown!r}")
        k = (options or {}).get("task_index")
        if k is None:
            return int(self.np_random.integers(len(self.tasks))) if len(self.tasks) > 1 else 0
        if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or not 0 <= k < len(self.tasks):
            raise ValueError(f"NavigationEnv: options['task_index'] must be an integer in [0, {len(self.tasks)}), "
                             f"got {k!r}")
        return int(k)

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        """Start a task at its start pose; returns ``(observation, info)`` (module docstring)."""
        super().reset(seed=seed)
        self.task_index = self._pick_task(options)
        self.task = self.tasks[self.task_index]
        d = len(self.system.periodic)
        x0 = torch.zeros(d, dtype=_DTYPE)
        x0[:3] = torch.tensor(self.task.start, dtype=_DTYPE)
        self._x = x0
        self._goal = x0.new_tensor(self.task.goal)  # [2]
        self._path = [x0[:2].clone()]
        self._length = x0.new_zeros(())  # a tensor sum, like simulate's, for the same rounding
        self.steps = 0
        self.max_steps = max(1, math.ceil(self.task.time_limit / self.dt - 1e-9))
        at_goal = float(torch.linalg.vector_norm(x0[:2] - self._goal)) <= self.task.goal_tolerance
        self.outcome: str | None = GOAL if at_goal else None
        self._sensed = self.task.sensed_environment(x0[:2])
        return self._observation(), self._info()

    def _action(self, action: Any) -> torch.Tensor:
        """Normalised ``action [q]`` (array-like) -> the float64 control ``[q]``: clipped to ``[-1, 1]``, then
        scaled onto ``[low, high]`` (and clamped there against rounding); a bad shape, type or value raises."""
        q = self._low.shape[0]
        try:
            raw = np.asarray(action)
            if raw.dtype.kind not in "iuf":  # bool, complex (its imaginary part dropped), object, text: refused
                raise TypeError(f"dtype {raw.dtype}")
            u = torch.as_tensor(raw.astype(np.float64))
        except (TypeError, ValueError) as exc:
            raise ValueError(f"NavigationEnv: the action must be {q} real numbers (integer or float), got {action!r} "
                             f"({exc})") from None
        if u.shape != (q,):
            raise ValueError(f"NavigationEnv: the action must have shape ({q},), got {tuple(u.shape)}")
        if not bool(torch.isfinite(u).all()):
            raise ValueError(f"NavigationEnv: the action must be finite, got {u.tolist()}")
        u = self._mid + self._half * u.clamp(-1.0, 1.0)
        return torch.minimum(torch.maximum(u, self._low), self._high)

    def step(self, action: Any) -> tuple[dict, float, bool, bool, dict]:
        """One control cycle: ``(observation, reward, terminated, truncated, info)`` (module docstring)."""
        if self._x is None:
            raise ValueError("NavigationEnv: call reset() before step()")
        if self.outcome is not None:
            raise ValueError(f"NavigationEnv: the episode has ended ({self.outcome}); call reset()")
        u = self._action(action)
        x = self._x
        x_new = self.system.step(x[None], u[None])[0]  # [d]
        self.steps += 1
        if not bool(torch.isfinite(x_new).all()):
            raise ValueError(f"NavigationEnv: non-finite state {x_new.tolist()} at step {self.steps}")
        self._length = self._length + torch.linalg.vector_norm(x_new[:2] - x[:2])
        before = float(torch.linalg.vector_norm(x[:2] - self._goal))
        after = float(torch.linalg.vector_norm(x_new[:2] - self._goal))
        self._x = x_new
        self._path.append(x_new[:2].clone())
        reward = before - after
        if bool(self.task.environment.in_collision(x_new[:2])):  # the truth, checked before the goal
            self.outcome, reward = COLLISION, reward - COLLISION_PENALTY
        elif after <= self.task.goal_tolerance:
            self.outcome, reward = GOAL, reward + GOAL_REWARD
        elif self.steps >= self.max_steps:
            self.outcome = TIMEOUT
        self._sensed = self.task.sensed_environment(x_new[:2])
        terminated = self.outcome in (GOAL, COLLISION)
        return self._observation(), float(reward), terminated, self.outcome == TIMEOUT, self._info()

    def _observation(self) -> dict[str, np.ndarray]:
        bounds = self._sensed.bounds
        return dict(
            state=self._x.numpy().copy(),
            goal=self._goal.numpy().copy(),
            bounds=np.array(bounds if bounds is not None else (-np.inf, -np.inf, np.inf, np.inf), dtype=np.float64),
            **_padded_tables(self._sensed, self.max_circles, self.max_rects),
        )

    def _info(self) -> dict[str, Any]:
        return dict(outcome=self.outcome, time=self.steps * self.dt, path_length=float(self._length),
                    steps=self.steps, task_index=self.task_index, environment=self._sensed)

    # -------------------------------------------------------------------------------------------- render

    def render(self) -> np.ndarray | None:
        """``render_mode="rgb_array"``: uint8 ``[H, W, 3]`` of the inflated obstacles (sensed dark, others
        light), the bounds, the path so far and the goal disc; None without a render mode."""
        if self.render_mode is None:
            return None
        if self._x is None:
            raise ValueError("NavigationEnv: call reset() before render()")
        return _draw(self.task, self._sensed, torch.stack(self._path).numpy())


def _draw(task: NavTask, sensed_env: Environment, path: np.ndarray) -> np.ndarray:
    """The picture of :meth:`NavigationEnv.render`; ``path [S+1, 2]`` (m)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.patches import Circle as CirclePatch
    from matplotlib.patches import Rectangle

    fig = Figure(figsize=(6, 4), dpi=80)
    canvas = FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    seen = {id(o) for o in sensed_env.obstacles}
    for obs in task.environment.obstacles:
        color = "0.3" if id(obs) in seen else "0.8"
        if isinstance(obs, Circle):
            ax.add_patch(CirclePatch(obs.center, obs.radius, color=color))
        elif isinstance(obs, Rect):
            ax.add_patch(Rectangle((obs.xmin, obs.ymin), obs.xmax - obs.xmin, obs.ymax - obs.ymin, color=color))
    ax.add_patch(CirclePatch(task.goal, max(task.goal_tolerance, 0.05), color="tab:green", alpha=0.5))
    ax.plot(path[:, 0], path[:, 1], color="tab:blue")
    xmin, ymin, xmax, ymax = task.bounds
    ax.set_xlim(xmin, xmax)
    ax.set_ylim(ymin, ymax)
    ax.set_aspect("equal")
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[..., :3].copy()


# ------------------------------------------------------------------------------------------------ registry

def register_envs() -> None:
    """Register :data:`ENV_ID`: ``gymnasium.make(ENV_ID, tasks=...)`` (:class:`NavigationEnv`'s keywords) or
    ``gymnasium.make(ENV_ID, suite="forest", index=0, ...)`` (:func:`make_env`'s); calling it again does nothing."""
    if ENV_ID not in gymnasium.registry:
        gymnasium.register(id=ENV_ID, entry_point="eval.navigate.gym_env:make_registered")


def make_registered(**kwargs: Any) -> NavigationEnv:
    """The entry point of :data:`ENV_ID`: :func:`make_env` when ``suite`` is given, else :class:`NavigationEnv`."""
    return make_env(**kwargs) if "suite" in kwargs else NavigationEnv(**kwargs)


def make_env(suite: str, index: int | None = 0, count: int | None = None, seed: int = 0,
             system: Any = None, render_mode: str | None = None, **suite_params: Any) -> NavigationEnv:
    """A :class:`NavigationEnv` on task ``index`` of a suite (``index=None``: all ``count`` tasks, one per
    reset).

    Without ``suite_params``: the benchmark's own tasks (:func:`precompute.worlds.tasks.make_tasks`: ``barn``, ``forest``
    or ``gaps``, the benchmark robot's radius and time limits); ``count`` defaults to ``index + 1`` (BARN: the
    first maps; forest: task ``index`` is seed ``seed + index``), for gaps to the benchmark's 9 tasks, so that
    gap task ``index`` is the benchmark's. With ``suite_params``: ``precompute.worlds.suites.make_suite(suite, count, seed,
    **suite_params)`` (forest or gaps with other parameters)."""
    if index is not None and (isinstance(index, bool) or not isinstance(index, (int, np.integer)) or index < 0):
        raise ValueError(f"make_env: index must be an integer >= 0 or None, got {index!r}")
    if suite_params:
        tasks = make_suite(suite, count or (1 if index is None else int(index) + 1), seed, **suite_params)
    else:
        if count is None:
            count = DEFAULT_COUNTS["gaps"] if suite == "gaps" else (None if index is None else int(index) + 1)
        tasks = make_tasks(suite, NAV_ROBOT.radius, count, seed=seed)
    if index is not None and index >= len(tasks):
        raise ValueError(f"make_env: index {index} is past the {len(tasks)} tasks of the suite (count={count})")
    chosen = tasks if index is None else tasks[index]
    return NavigationEnv(chosen, system=system, render_mode=render_mode)
