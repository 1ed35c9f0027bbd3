"""The paper's navigation cost (l_state + l_obs) for batches of rollouts.

Shapes used in this module: N rollouts, T horizon, d state dimensions (the first two are x, y), q action
dimensions.

Paper: ``l(x) = l_state(x) + l_obs(x)`` with ``l_state = |x_p - x_goal|^2`` and ``l_obs = inf`` inside an
obstacle. Here, per rollout:

* goal cost: ``|xy_t - goal|^2`` summed over steps ``t = 1..T`` *until the rollout first comes within
  ``goal_tolerance`` of the goal*, and zero from that step on (a constant-speed car cannot stop, so without the
  cut-off the cheapest rollouts would orbit the goal);
* collision cost: a large finite ``collision_penalty``, once, if any state at steps ``1..T`` is in collision
  with the obstacles sensed at the cost's ``time`` (finite, so MPPI weights ``softmax(-cost / lambda)`` never
  become NaN when every rollout collides); with ``per_state=True``, once for every such state (the paper's
  per-state ``l_obs`` summed over the horizon, so that when every rollout collides the ones that spend fewer
  steps in collision still weigh more). With ``stop_at_goal=True`` the collision term ends, like the goal
  term, at the rollout's first arrival at the goal (that state still counts): what the authors' controllers
  do, and right for a closed loop that ends at the goal, where a rollout's states after its arrival are never
  driven (charging them makes a rollout that reaches a goal near a wall look like a crash).

``goal_distance`` (a cost-to-go, e.g. a planner's geodesic distance) replaces the straight-line distance in the
goal term.

Moving discs (an environment with ``moving``): the state at step ``k`` of a rollout is tested against the discs
where they are at ``time + k dt`` (``dt``, the rollout's step, is then required): the discs' constant-velocity
motion predicted along the rollout (:mod:`cuniform_torch.envs.moving`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import torch
from torch import Tensor

from cuniform_torch.common.compiled import optional_loop
from cuniform_torch.envs.environment import Environment

__all__ = ["TrajectoryCost", "NavigationCost", "goal_cost", "collision_mask"]


class TrajectoryCost(Protocol):
    """A cost of whole rollouts: ``states [N, T+1, d]``, ``actions [N, T, q]`` -> ``[N]``."""

    def __call__(self, states: Tensor, actions: Tensor) -> Tensor: ...


def _check_states(states: Any, who: str) -> None:
    if not isinstance(states, torch.Tensor) or not states.is_floating_point():
        raise ValueError(f"{who}: states must be a floating-point tensor [N, T+1, d], got "
                         f"{getattr(states, 'dtype', type(states).__name__)}")
    if states.ndim != 3 or states.shape[1] < 1 or states.shape[2] < 2:
        raise ValueError(f"{who}: states must have shape [N, T+1, d] with T+1 >= 1 and d >= 2 (x, y first), "
                         f"got {list(states.shape)}")


def _goal_xy(goal: Any, states: Tensor, who: str) -> Tensor | tuple[float, float]:
    """The goal as Python floats, or as a ``[2]`` tensor on the states' device and in their dtype."""
    if isinstance(goal, torch.Tensor):
        if goal.shape != (2,):
            raise ValueError(f"{who}: goal must have shape [2], got {list(goal.shape)}")
        if goal.device != states.device:
            raise ValueError(f"{who}: goal is on {goal.device} but states are on {states.device}")
        return goal.to(states.dtype)
    return _goal_pair(goal, who)


def _goal_pair(goal: Any, who: str) -> tuple[float, float]:
    if isinstance(goal, torch.Tensor):
        goal = goal.detach().cpu().reshape(-1).tolist()
    try:
        gx, gy = (float(v) for v in goal)
    except (TypeError, ValueError):
        raise ValueError(f"{who}: goal must be a pair of numbers (x, y), got {goal!r}") from None
    if not (math.isfinite(gx) and math.isfinite(gy)):
        raise ValueError(f"{who}: goal must be finite, got {goal!r}")
    return gx, gy


def _tolerance(tol: Any, who: str) -> float:
    if isinstance(tol, bool) or not isinstance(tol, (int, float)) or not math.isfinite(tol) or tol < 0:
        raise ValueError(f"{who}: goal_tolerance must be a finite number >= 0, got {tol!r}")
    return float(tol)


def goal_cost(states: Tensor, goal: Sequence[float] | Tensor, tol: float) -> Tensor:
    """``states [N, T+1, d]`` -> ``[N]``: squared xy distance to ``goal`` summed over steps ``1..T``, stopping
    (zero from then on) at the first step within ``tol`` of the goal. The dtype and device of ``states``."""
    _check_states(states, "goal_cost")
    tol = _tolerance(tol, "goal_cost")
    g = _goal_xy(goal, states, "goal_cost")
    dist2 = _goal_dist2(states, g)  # [N, T]
    before = _before_arrival(dist2 <= tol * tol)  # [N, T]
    return torch.where(before, dist2, torch.zeros_like(dist2)).sum(dim=1)


def _goal_dist2(states: Tensor, g) -> Tensor:
    """Squared xy distance to the goal at steps ``1..T``: ``[N, T+1, d]`` -> ``[N, T]``."""
    dx = states[:, 1:, 0] - g[0]
    dy = states[:, 1:, 1] - g[1]
    return dx * dx + dy * dy


def _before_arrival(reached: Tensor, inclusive: bool = False) -> Tensor:
    """``reached [N, T]`` (bool) -> ``[N, T]``: the steps before each row's first True (and that step too when
    ``inclusive``)."""
    arrivals = reached.to(torch.int32).cumsum(dim=1)  # [N, T]
    return (arrivals - reached.to(torch.int32) if inclusive else arrivals) == 0


def collision_mask(states: Tensor, env: Environment, time: float | None = None, dt: float | None = None) -> Tensor:
    """``states [N, T+1, d]`` -> ``bool [N]``: whether any state at steps ``1..T`` collides with the obstacles
    sensed at ``time`` (all of them for ``None``) or leaves ``env.bounds``. The start state is not checked. With
    moving discs, step ``k`` is at ``time + k dt`` (both needed)."""
    _check_states(states, "collision_mask")
    at = _step_times(env, states, time, dt, "collision_mask")
    return env.in_collision(states[:, 1:, :2], time, at=at).any(dim=1)  # [N, T] -> [N]


def _step_times(env: Environment, states: Tensor, time: float | None, dt: float | None, who: str) -> Tensor | None:
    """``[T]``: the times of steps ``1..T`` (``time + k dt``) when ``env`` has moving discs, else None."""
    if env.moving is None:
        return None
    if time is None or dt is None:
        raise ValueError(f"{who}: the environment has moving discs; give the current time and dt (the rollout's "
                         "step, s) so each step is tested where the discs are then")
    steps = torch.arange(1, states.shape[1], device=states.device, dtype=states.dtype)  # [T]
    return time + dt * steps


@dataclass
class NavigationCost:
    """The paper's cost as a :class:`TrajectoryCost`: goal cost + ``collision_penalty`` for a colliding rollout.

    Call ``set_time(t)`` each control cycle so that the collision term sees only the obstacles sensed by time
    ``t`` (``time=None``: all obstacles, whatever their ``appear_time``).
    """

    env: Environment
    """obstacles and bounds"""
    goal: tuple[float, float]
    """(x, y) of the goal, m"""
    goal_tolerance: float = 0.2
    """a rollout within this xy distance (m) of the goal has reached it: no goal cost from then on"""
    collision_penalty: float = 1e6
    """cost added once to a rollout that collides (finite stand-in for the paper's inf)"""
    time: float | None = 0.0
    """current time (s): obstacles with ``appear_time <= time`` are seen; None: all"""
    per_state: bool = False
    """charge ``collision_penalty`` for every colliding state at steps 1..T instead of once per rollout"""
    stop_at_goal: bool = False
    """end the collision term, like the goal term, at the rollout's first arrival at the goal (that state still
    counts); False charges collisions over the whole horizon"""
    goal_distance: Callable[[Tensor], Tensor] | None = None
    """a cost-to-go ``xy [N, T, 2] -> [N, T]`` (m) whose square replaces the squared straight-line distance in the
    goal term (e.g. a planner's geodesic distance around the obstacles); arrival is still judged on the straight
    line; None: the straight line"""
    dt: float | None = None
    """s: the rollout's step; needed when ``env`` has moving discs (step ``k`` is at ``time + k dt``)"""

    def __post_init__(self) -> None:
        if not isinstance(self.env, Environment):
            raise ValueError(f"NavigationCost: env must be an Environment, got {type(self.env).__name__}")
        self.goal = _goal_pair(self.goal, "NavigationCost")
        self.goal_tolerance = _tolerance(self.goal_tolerance, "NavigationCost")
        p = self.collision_penalty
        if isinstance(p, bool) or not isinstance(p, (int, float)) or not math.isfinite(p) or p <= 0:
            raise ValueError(f"NavigationCost: collision_penalty must be a finite number > 0, got {p!r}")
        self.collision_penalty = float(p)
        for flag in ("per_state", "stop_at_goal"):
            if not isinstance(getattr(self, flag), bool):
                raise ValueError(f"NavigationCost: {flag} must be a bool, got {getattr(self, flag)!r}")
        if self.dt is not None:
            dt = self.dt
            if isinstance(dt, bool) or not isinstance(dt, (int, float)) or not math.isfinite(dt) or dt <= 0:
                raise ValueError(f"NavigationCost: dt must be a finite number > 0 (s), got {dt!r}")
            self.dt = float(dt)
        if self.env.moving is not None and self.dt is None:
            raise ValueError("NavigationCost: env has moving discs; give dt (the rollout's step, s)")
        self.set_time(self.time)

    def set_time(self, t: float | None) -> None:
        """See the obstacles sensed by time ``t`` (s); None: all obstacles."""
        if t is not None and (isinstance(t, bool) or not isinstance(t, (int, float)) or math.isnan(t)):
            raise ValueError(f"NavigationCost: time must be a number or None, got {t!r}")
        self.time = None if t is None else float(t)

    def __call__(self, states: Tensor, actions: Tensor) -> Tensor:
        """``states [N, T+1, d]``, ``actions [N, T, q]`` -> ``[N]`` (dtype of ``states``, finite for finite
        states). Actions are not used by this cost; their shape is checked."""
        _check_states(states, "NavigationCost")
        N, T1 = states.shape[0], states.shape[1]
        if not isinstance(actions, torch.Tensor) or actions.ndim != 3 or actions.shape[:2] != (N, T1 - 1):
            raise ValueError(f"NavigationCost: actions must have shape [{N}, {T1 - 1}, q] to match states "
                             f"{list(states.shape)}, got {list(getattr(actions, 'shape', []))}")
        if (self.goal_distance is None and self.env.moving is None and states.device.type == "cpu"
                and states.dtype in _COMPILED_DTYPES and not states.requires_grad):
            fused = self._compiled(states)
            if fused is not None:
                return fused
        dist2 = _goal_dist2(states, self.goal)  # [N, T] straight line, squared: arrival is judged on it
        reached = dist2 <= self.goal_tolerance * self.goal_tolerance  # [N, T]
        if self.goal_distance is not None:
            to_go = self.goal_distance(states[:, 1:, :2])  # [N, T]
            if not isinstance(to_go, Tensor) or to_go.shape != reached.shape:
                raise ValueError(f"NavigationCost: goal_distance must map xy {list(states[:, 1:, :2].shape)} to "
                                 f"{list(reached.shape)}, got {list(getattr(to_go, 'shape', []))}")
            to_go = to_go.to(states.dtype)
            dist2 = to_go * to_go
        cost = torch.where(_before_arrival(reached), dist2, torch.zeros_like(dist2)).sum(dim=1)  # goal_cost's sum
        at = _step_times(self.env, states, self.time, self.dt, "NavigationCost")  # [T] or None
        hit = self.env.in_collision(states[:, 1:, :2], self.time, at=at)  # [N, T]
        if self.stop_at_goal:
            hit = hit & _before_arrival(reached, inclusive=True)
        hit = hit.sum(dim=1) if self.per_state else hit.any(dim=1)  # [N]
        return cost + hit.to(cost.dtype) * self.collision_penalty

    def _compiled(self, states: Tensor) -> Tensor | None:
        """``[N]``: :meth:`__call__` by the compiled loop (:mod:`cuniform_torch.envs.cost_loops`) for CPU states
        and an environment of Circles and Rects only; None where that loop cannot serve (numba missing, other
        obstacle kinds sensed): the torch path then."""
        loop = _cost_loop()
        if loop is None:
            return None
        circles, rects, others = self.env._visible_arrays(self.time, states.dtype)
        if others:
            return None
        scalar = _NUMPY_SCALAR[states.dtype]
        bounds = self.env.bounds
        out = torch.empty(states.shape[0], dtype=states.dtype)  # [N]
        loop(states.detach().numpy(), scalar(self.goal[0]), scalar(self.goal[1]),
             scalar(self.goal_tolerance * self.goal_tolerance), circles, rects,
             np.array(bounds if bounds is not None else (0.0, 0.0, 0.0, 0.0), dtype=scalar), bounds is not None,
             self.per_state, self.stop_at_goal, self.collision_penalty, out.numpy())
        return out


_COMPILED_DTYPES = (torch.float32, torch.float64)
"""the states' dtypes the compiled cost serves"""
_NUMPY_SCALAR = {torch.float32: np.float32, torch.float64: np.float64}
"""the numpy scalar type of each: the goal, tolerance and bounds in the states' dtype, as torch's scalars are"""


def _cost_loop():
    """The compiled cost (:func:`cuniform_torch.envs.cost_loops.navigation_cost`), or None without numba."""
    return optional_loop("cuniform_torch.envs.cost_loops", "navigation_cost")

