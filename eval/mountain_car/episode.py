"""One closed-loop episode of gymnasium's MountainCarContinuous-v0 under one controller (``eval.mountain_car.run``).

The cost, the same for every controller and fixed before any run (:func:`trajectory_cost`): the env's own
reward, negated, over the horizon, plus a distance shaping term. Per model step ``t`` (``repeat`` env steps,
the force ``u_t`` held), until the first step whose state reaches the goal position 0.45 (that step included,
none after: the env ends the episode there): ``0.1 repeat u_t^2`` (the env's action cost) ``+ (0.45 - p_t)+``
(distance to the goal position, in position units); minus 100 (the env's goal reward) when the trajectory
reaches the goal. Every Gaussian sampler (MPPI, pytorch_mppi, CU-MPPI's local pass) has noise std
:data:`NOISE_STD`, half the force range; every softmax has temperature :data:`LAMBDA` (the library's
default). The controller commands once per model step; the env steps ``repeat`` times with that force.
"""

from __future__ import annotations

import functools
import importlib.util
import statistics
import time
import warnings
from typing import Any

import numpy as np
import torch
from torch import Tensor

from cuniform_torch import CUMPPI, MPPI, CUniformMPPI, load_table
from cuniform_torch.sampling import StartMismatchWarning
from cuniform_torch.systems.classic import MOUNTAIN_CAR, MountainCar

__all__ = ["METHODS", "SET_METHODS", "NOISE_STD", "LAMBDA", "ENV_ID", "GYM_MISSING", "trajectory_cost",
           "run_episode", "episode_job", "have_gymnasium", "have_pytorch_mppi"]

METHODS = ("mppi", "pytorch_mppi", "cuniform", "cumppi")
"""ours (Gaussian), the peer pytorch_mppi, C-Uniform MPPI and CU-MPPI on the start-aware table set"""
SET_METHODS = ("cuniform", "cumppi")
"""the methods that sample from the table set"""
NOISE_STD = 0.5
LAMBDA = 0.567
GOAL = MOUNTAIN_CAR["goal_position"]
GOAL_REWARD = 100.0
ACTION_COST = 0.1  # the env's reward: -0.1 u^2 per env step
ENV_ID = "MountainCarContinuous-v0"
GYM_MISSING = 'eval.mountain_car.run needs gymnasium (the ground-truth env): pip install -e ".[gym]"'


def have_gymnasium() -> bool:
    """Whether gymnasium (the optional extra ``gym``) is installed."""
    return importlib.util.find_spec("gymnasium") is not None


def have_pytorch_mppi() -> bool:
    """Whether pytorch_mppi (the optional extra ``bench``) is installed."""
    return importlib.util.find_spec("pytorch_mppi") is not None


def trajectory_cost(next_states: Tensor, actions: Tensor, repeat: int) -> Tensor:
    """The cost (module docstring) of ``next_states [K, T, 2]`` (the state after each model step) and
    ``actions [K, T, 1]`` -> ``[K]``."""
    p = next_states[..., 0]  # [K, T]
    reached = torch.cummax((p >= GOAL).to(p.dtype), dim=1).values  # [K, T]: reached by step t
    active = 1.0 - torch.cat((torch.zeros_like(reached[:, :1]), reached[:, :-1]), dim=1)  # not reached before t
    step = ACTION_COST * repeat * actions[..., 0] ** 2 + (GOAL - p).clamp(min=0.0)
    return (active * step).sum(dim=1) - GOAL_REWARD * reached[:, -1]


class _Peer:
    """pytorch_mppi's MPPI driven as in eval/bench/controllers.py, with the same cost (as its terminal trajectory cost)."""

    def __init__(self, system: MountainCar, num_samples: int, horizon: int, seed: int):
        from pytorch_mppi import MPPI as PeerMPPI

        torch.manual_seed(seed)  # pytorch_mppi draws from torch's global stream
        self.mppi = PeerMPPI(system.step, lambda x, u: torch.zeros(x.shape[0], dtype=x.dtype), 2,
                             noise_sigma=torch.eye(1) * NOISE_STD**2, num_samples=num_samples, horizon=horizon,
                             lambda_=LAMBDA, u_min=torch.tensor([-1.0]), u_max=torch.tensor([1.0]),
                             terminal_state_cost=lambda s, u: trajectory_cost(s[0], u[0], system.repeat))

    def command(self, state: Tensor) -> Tensor:
        return self.mppi.command(state)


@functools.lru_cache(maxsize=4)
def _table_set(folder: str):
    """The set's policy, read once per process (its counters are reset every episode)."""
    return load_table(folder)


def _controller(method: str, system: MountainCar, set_dir: str | None, k: int, horizon: int, seed: int) -> tuple[Any, Any]:
    """``(controller with .command(state [2]) -> [1], the table-set policy or None)``."""
    def cost(states: Tensor, actions: Tensor) -> Tensor:  # [K, T+1, 2], [K, T, 1] -> [K]
        return trajectory_cost(states[:, 1:], actions, system.repeat)

    if method == "mppi":
        return MPPI(system, cost, k, horizon, lambda_=LAMBDA, noise_std=NOISE_STD, seed=seed), None
    if method == "pytorch_mppi":
        return _Peer(system, k, horizon, seed), None
    policy = _table_set(set_dir)
    policy.reset_counters()
    if method == "cuniform":
        return CUniformMPPI(policy, cost, k, lambda_=LAMBDA, horizon=horizon, seed=seed), policy
    if method == "cumppi":
        return CUMPPI(policy, cost, k, lambda_=LAMBDA, noise_std=NOISE_STD, horizon=horizon, seed=seed), policy
    raise ValueError(f"unknown method {method!r}; choose from {', '.join(METHODS)}")


def run_episode(method: str, seed: int, budget: int, horizon: int, repeat: int, max_steps: int,
                set_dir: str | None, threads: int = 0) -> dict[str, Any]:
    """One episode: the env reset with ``seed`` (the controller's seed too), at most ``max_steps`` env steps.

    Returns the record: ``method, seed, success`` (the env terminated at the goal), ``steps`` (env steps),
    ``return`` (the sum of gymnasium's rewards), ``commands``, ``command_ms_median``, and for a table-set method
    ``queries`` and ``misses`` of its lookups (``misses / queries`` is the miss rate)."""
    import gymnasium as gym

    if threads:
        torch.set_num_threads(threads)
    system = MountainCar(repeat=repeat)
    env = gym.make(ENV_ID, max_episode_steps=max_steps)
    obs, _ = env.reset(seed=seed)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", StartMismatchWarning)  # the miss rate is measured and reported instead
        controller, policy = _controller(method, system, set_dir, budget, horizon, seed)
        total, steps, success, times = 0.0, 0, False, []
        done = False
        while not done:
            state = torch.as_tensor(np.asarray(obs, dtype=np.float32))
            t0 = time.perf_counter()
            force = float(controller.command(state).reshape(-1)[0])
            times.append(time.perf_counter() - t0)
            for _ in range(repeat):  # the model step: repeat env steps with the force held
                obs, reward, terminated, truncated, _ = env.step(np.array([force], dtype=np.float32))
                total, steps = total + float(reward), steps + 1
                if terminated or truncated:
                    success, done = bool(terminated), True
                    break
    env.close()
    record: dict[str, Any] = {"method": method, "seed": seed, "success": success, "steps": steps, "return": total,
                              "commands": len(times), "command_ms_median": 1e3 * statistics.median(times)}
    if policy is not None:
        record.update(queries=int(policy.queries), misses=int(policy.misses))
    return record


def episode_job(method: str, seed: int, config: dict[str, Any]) -> dict[str, Any]:
    """:func:`run_episode` as a picklable job of :func:`precompute.parallel.run_jobs`."""
    return run_episode(method, seed, config["budget"], config["horizon"], config["repeat"], config["max_steps"],
                       config.get("set_dir"), config.get("threads", 0))

