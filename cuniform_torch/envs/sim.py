"""Closed-loop simulation: a controller drives a system through an environment until goal, collision or timeout.

Shapes used in this module: S steps simulated, d state dimensions (the first two are x, y), q action dimensions.

One control cycle per system step: at time ``t`` (s) the cost, if given, is told ``t`` (so it sees only the
obstacles sensed by then), the controller picks ``u = controller.command(x)``, the system steps once, and the
new position is checked against the *true* environment (every obstacle, whatever its ``appear_time``, and the
bounds), then against the goal, then against the time limit. A step that both collides and reaches the goal
counts as a collision. Collisions are checked at the simulated states only, not along the segments between
them (the same discretization the cost uses). Moving discs (an environment with ``moving``) are checked where
they are at the new state's time, ``(k + 1) dt`` after ``k`` earlier steps.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import torch
from torch import Tensor

from cuniform_torch.common.checks import positive_int
from cuniform_torch.envs.environment import Environment
from cuniform_torch.systems import System

__all__ = ["Controller", "SimResult", "simulate", "GOAL", "COLLISION", "TIMEOUT"]

GOAL = "goal"
COLLISION = "collision"
TIMEOUT = "timeout"


class Controller(Protocol):
    """Anything that maps the current state to a control; ``reset()`` is optional (called before a run)."""

    def command(self, state: Tensor) -> Tensor:
        """``state [d]`` -> ``[q]`` (same dtype and device)."""
        ...


@dataclass
class SimResult:
    """One closed-loop run."""

    path: Tensor
    """``[S+1, d]`` states, start included (``record=False``: ``[2, d]``, start and final state)"""
    controls: Tensor
    """``[S, q]`` controls applied (``record=False``: ``[0, q]``)"""
    outcome: str
    """``"goal"``, ``"collision"`` or ``"timeout"``"""
    time: float
    """simulated time at the end, ``steps * dt`` (s)"""
    path_length: float
    """sum of the xy lengths of the S segments (m)"""
    steps: int
    """number of control cycles S"""

    @property
    def success(self) -> bool:
        """Reached the goal without a collision within the time limit."""
        return self.outcome == GOAL


MAX_SIM_STEPS = 100_000
"""the most steps :func:`simulate` runs unless its ``step_limit`` says more (5.5 h of robot time at dt 0.2 s; a
benchmark episode is a few hundred)"""


def _positive(value: Any, what: str, allow_zero: bool = False) -> float:
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if not ok or value < 0 or (value == 0 and not allow_zero):
        bound = ">= 0" if allow_zero else "> 0"
        raise ValueError(f"simulate: {what} must be a finite number {bound}, got {value!r}")
    return float(value)


def simulate(
    system: System,
    controller: Controller,
    x0: Tensor,
    env: Environment,
    goal: Sequence[float],
    goal_tolerance: float,
    time_limit: float,
    cost: Any = None,
    record: bool = True,
    step_limit: int | None = None,
) -> SimResult:
    """Run ``controller`` on ``system`` from ``x0 [d]`` until it reaches ``goal`` (xy distance <=
    ``goal_tolerance``), collides (``env.in_collision(xy, time=None)``: the truth) or ``time_limit`` (s) runs out.

    ``cost``, if given, needs ``set_time(t)``; it is called with the current time before every command (for
    obstacles that are sensed only from their ``appear_time`` on). ``controller.reset()`` is called first when it
    exists. Runs on the dtype and device of ``x0``; the controller must answer in the same. A start within
    the goal tolerance returns ``"goal"`` after 0 steps. ``time_limit / dt`` may be at most ``step_limit`` steps
    (default :data:`MAX_SIM_STEPS`; checked before the first step, so a mistyped limit is one clear error rather
    than hours of simulation and gigabytes of recorded states); pass a larger ``step_limit`` to lift it.
    """
    if not callable(getattr(system, "step", None)) or not hasattr(system, "dt") or not hasattr(system, "periodic"):
        raise ValueError(f"simulate: system must have step(x, u), dt and periodic, got {type(system).__name__}")
    if not callable(getattr(controller, "command", None)):
        raise ValueError(f"simulate: controller must have a command(state) method, got {type(controller).__name__}")
    if cost is not None and not callable(getattr(cost, "set_time", None)):
        raise ValueError(f"simulate: cost must have a set_time(t) method, got {type(cost).__name__}")
    if not isinstance(env, Environment):
        raise ValueError(f"simulate: env must be an Environment, got {type(env).__name__}")
    d = len(system.periodic)
    if not isinstance(x0, torch.Tensor) or not x0.is_floating_point():
        raise ValueError(f"simulate: x0 must be a floating-point tensor, got {getattr(x0, 'dtype', type(x0).__name__)}")
    if x0.shape != (d,) or d < 2:
        raise ValueError(f"simulate: x0 must have shape [{d}] (x, y first), got {list(x0.shape)}")
    if not bool(torch.isfinite(x0).all()):
        raise ValueError(f"simulate: x0 contains NaN or infinite values: {x0.tolist()}")
    try:
        gx, gy = (float(v) for v in goal)
    except (TypeError, ValueError):
        raise ValueError(f"simulate: goal must be a pair of numbers (x, y), got {goal!r}") from None
    if not (math.isfinite(gx) and math.isfinite(gy)):
        raise ValueError(f"simulate: goal must be finite, got {goal!r}")
    tol = _positive(goal_tolerance, "goal_tolerance", allow_zero=True)
    limit = _positive(time_limit, "time_limit")
    dt = _positive(system.dt, "system.dt")
    if bool(env.in_collision(x0[:2], at=0.0)):
        raise ValueError(f"simulate: the start state {x0.tolist()} is in collision (or outside the bounds)")

    goal_t = x0.new_tensor((gx, gy))  # [2]
    max_steps = max(1, math.ceil(limit / dt - 1e-9))  # t = k dt >= time_limit ends the run
    cap = MAX_SIM_STEPS if step_limit is None else step_limit
    positive_int("simulate", "step_limit", cap)  # cap is step_limit when one is given
    if max_steps > cap:
        raise ValueError(f"simulate: time_limit {time_limit!r} s at dt {dt!r} s is {max_steps:,} steps, more than the "
                         f"limit of {cap:,}; give a shorter time_limit, or step_limit={max_steps} to allow it")
    reset = getattr(controller, "reset", None)  # optional: not in the Controller protocol
    if callable(reset):
        reset()

    x = x0
    states = [x0]
    controls: list[Tensor] = []
    length = x0.new_zeros(())
    outcome = GOAL if float(torch.linalg.vector_norm(x0[:2] - goal_t)) <= tol else TIMEOUT
    steps = 0
    u: Tensor | None = None
    while outcome != GOAL and steps < max_steps:
        if cost is not None:
            cost.set_time(steps * dt)
        u = controller.command(x)
        if not isinstance(u, torch.Tensor) or u.ndim != 1:
            raise ValueError(f"simulate: controller.command must return a [q] tensor, got "
                             f"{list(u.shape) if isinstance(u, torch.Tensor) else type(u).__name__} at step {steps}")
        if u.dtype != x.dtype or u.device != x.device:
            raise ValueError(f"simulate: controller.command returned {u.dtype} on {u.device}; the state is "
                             f"{x.dtype} on {x.device}")
        x_new = system.step(x[None], u[None])[0]  # [d]
        steps += 1
        length = length + torch.linalg.vector_norm(x_new[:2] - x[:2])
        flags = torch.stack((
            ~torch.isfinite(x_new).all() | ~torch.isfinite(u).all(),
            env.in_collision(x_new[:2], at=steps * dt),  # steps counts x_new: it is at steps * dt
            torch.linalg.vector_norm(x_new[:2] - goal_t) <= tol,
        )).tolist()  # one host sync per cycle
        if flags[0]:
            raise ValueError(f"simulate: non-finite control {u.tolist()} or state {x_new.tolist()} at step {steps}")
        x = x_new
        if record:
            states.append(x)
            controls.append(u)
        if flags[1]:
            outcome = COLLISION
            break
        if flags[2]:
            outcome = GOAL

    if record:
        path = torch.stack(states)  # [S+1, d]
    else:
        path = torch.stack((x0, x))  # [2, d]
    if controls:
        controls_t = torch.stack(controls)  # [S, q]
    else:
        if u is not None:
            q = u.shape[0]
        elif callable(getattr(system, "action_set", None)):
            q = system.action_set(dtype=x0.dtype).shape[1]
        else:
            q = 0
        controls_t = x0.new_zeros((0, q))
    return SimResult(
        path=path,
        controls=controls_t,
        outcome=outcome,
        time=steps * dt,
        path_length=float(length),
        steps=steps,
    )
