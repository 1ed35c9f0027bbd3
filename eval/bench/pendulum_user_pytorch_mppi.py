"""A pytorch_mppi user's script: the pendulum swing-up of pytorch_mppi's example (tests/pendulum.py), with gym's
Pendulum-v1 equations in a few lines of numpy instead of gym. The twin files pendulum_user_pytorch_mppi.py and
pendulum_user_cuniform.py differ by the import line only; ``python -m eval.bench switch_pendulum`` runs both
(``run(seed)``: one episode's total reward) and prints their returns side by side.
"""

import math  # noqa: I001 (a user script: its twin imports MPPI from cuniform_torch, a first-party name, in place)

import numpy as np
import torch
from pytorch_mppi import MPPI

TIMESTEPS = 15  # T
N_SAMPLES = 100  # K
STEPS = 200
d = "cpu"
dtype = torch.double
noise_sigma = torch.tensor(10, device=d, dtype=dtype)
lambda_ = 1.0
g, m, l, dt = 10.0, 1.0, 1.0, 0.05


def angle_normalize(x):
    return ((x + math.pi) % (2 * math.pi)) - math.pi


def dynamics(state, perturbed_action):
    """The model MPPI plans with: [K, 2] (angle, speed), [K, 1] -> [K, 2]."""
    th, thdot = state[:, 0:1], state[:, 1:2]
    u = torch.clamp(perturbed_action, -2, 2)
    newthdot = torch.clamp(thdot + (3 * g / (2 * l) * torch.sin(th) + 3.0 / (m * l**2) * u) * dt, -8, 8)
    return torch.cat((th + newthdot * dt, newthdot), dim=1)


def running_cost(state, action):
    return angle_normalize(state[:, 0]) ** 2 + 0.1 * state[:, 1] ** 2


class Pendulum:
    """gym's Pendulum-v1 in numpy: state (angle, speed), reward -(angle^2 + 0.1 speed^2 + 0.001 u^2)."""

    def __init__(self, state):
        self.state = np.array(state, dtype=np.float64)

    def step(self, action):
        th, thdot = self.state
        u = float(np.clip(action, -2, 2).reshape(-1)[0])
        reward = -(angle_normalize(th) ** 2 + 0.1 * thdot**2 + 0.001 * u**2)
        newthdot = np.clip(thdot + (3 * g / (2 * l) * np.sin(th) + 3.0 / (m * l**2) * u) * dt, -8, 8)
        self.state = np.array([th + newthdot * dt, newthdot])
        return self.state, reward


def run(seed=0, steps=STEPS):
    """The total reward of one episode from hanging down (angle pi, speed 1)."""
    torch.manual_seed(seed)
    env = Pendulum([np.pi, 1.0])
    mppi = MPPI(dynamics, running_cost, 2, noise_sigma, num_samples=N_SAMPLES, horizon=TIMESTEPS, lambda_=lambda_)
    total = 0.0
    for _ in range(steps):
        state = env.state.copy()
        action = mppi.command(state)
        _, reward = env.step(action.cpu().numpy())
        total += reward
    return total

