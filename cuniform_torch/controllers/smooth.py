"""Smooth samplers of the MPPI core: noise on the action rate (smooth MPPI) and on a few kernel-interpolated control
points (kernel MPPI), as batched proposals and as controllers.

Shapes: B robots, K samples per robot, T horizon, q action dimensions, n control points.

* :class:`SmoothProposal` / :class:`SmoothMPPI` (SMPPI; Kim, Kwon, Lee, Chung, Yoon, Kim, "Smooth Model Predictive
  Path Integral Control without Smoothing", IEEE RA-L 7(4), 2022): the input is lifted to the action's rate. Each
  sample draws white rates ``v = clip(v_bar + eps, +-rate_max)``, ``eps ~ N(0, noise_std^2)`` per step (action units
  per second), and integrates them along the horizon from the action applied last, ``a_t = a_(-1) + dt *
  sum_(s <= t) v_s`` (clipped to the action bounds), so every sample is a random walk around the nominal: the
  deviation from it grows as ``dt * noise_std * sqrt(t + 1)`` and neighbouring actions differ by ``dt * v`` only.
  ``v_bar`` is the nominal's own rate, so the mean sample is MPPI's warm start (the weighted sequence shifted one
  step). The controller adds the paper's action-sequence cost ``smoothness * sum_t ||a_t - a_(t-1)||^2`` (from the
  action applied last) to the user's cost.
* :class:`KernelProposal` / :class:`KernelMPPI` (KMPPI; Miura, Akai, Honda, Hara, "Spline-Interpolated Model
  Predictive Path Integral Control with Stein Variational Inference for Reactive Navigation", ICRA 2024, as
  pytorch_mppi's ``KMPPI``): Gaussian noise on ``n`` control points at the steps ``linspace(0, T - 1, n)``, the
  sequence their RBF-kernel interpolation ``a = K(t, t_k) K(t_k, t_k)^-1 theta`` (``exp(-d^2 / (2 sigma^2))``,
  ``sigma`` in steps), which passes through every control point. The control points drawn around are the least-
  squares fit of the nominal sequence (exact when the nominal is itself an interpolation, as a weighted mean of
  interpolations is), so the warm start is MPPI's.

How they differ from pytorch_mppi 0.9.1's ``SMPPI`` / ``KMPPI`` (which are one-robot controllers with their own
iteration): SMPPI there adds ``dt * (U + eps)`` to a stored action sequence step by step, integrating the rate across
commands rather than along the horizon; here the samples are the lifted system's rollouts (rates integrated along
the horizon from the applied action), the form of the paper's input-lifted dynamics. Its noise-likelihood term
``lambda * U Sigma^-1 eps`` is left out, as the core's MPPI leaves it out, and its action-sequence cost sums the
jumps within the sequence only, where this one also counts the jump from the action applied last (what makes
consecutive commands smooth). KMPPI there shifts the control points by
interpolating at ``t_k + 1`` (the last one extrapolated); here they are refit to the shifted nominal (its last
action repeated). Both draw from each robot's own stream (a batch commands what its robots would alone).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, cast

import torch
from torch import Tensor

from cuniform_torch.controllers.core import CostFn
from cuniform_torch.controllers.mppi import MPPI
from cuniform_torch.controllers.proposals import GaussianProposal, _start_rows
from cuniform_torch.controllers.result import MPPIResult
from cuniform_torch.controllers.streams import RobotStreams
from cuniform_torch.sampling.rollout import open_loop
from cuniform_torch.systems import System

__all__ = ["SmoothProposal", "SmoothMPPI", "SmoothnessCost", "rbf_interpolation", "KernelProposal", "KernelMPPI"]


def _positive(name: str, value: object, allow_inf: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or math.isnan(value) or value <= 0 \
            or (math.isinf(value) and not allow_inf):
        raise ValueError(f"{name} must be a {'' if allow_inf else 'finite '}number > 0, got {value!r}")
    return float(value)


def _roll_out(system: System, states: Tensor, actions: Tensor) -> tuple[Tensor, Tensor]:
    """Each robot's ``actions [B, K, T, q]`` rolled out from its ``states [B, d]``: ``[B, K, T+1, d]``, the actions."""
    b, k, t, q = actions.shape
    trajectories = open_loop(system, _start_rows(states, k), actions.view(b * k, t, q))  # [B*K, T+1, d]
    return trajectories.view(b, k, t + 1, -1), actions


def _system_dt(system: System, dt: float | None) -> float:
    """``dt`` given, else the system's ``dt`` (ValueError naming both when neither is a positive number)."""
    if dt is not None:
        return _positive("dt", dt)
    found = getattr(system, "dt", None)
    if isinstance(found, bool) or not isinstance(found, (int, float)) or not (math.isfinite(found) and found > 0):
        raise ValueError(f"smooth MPPI integrates rates over the time step: give dt= (s), or a system with a positive "
                         f"dt attribute ({type(system).__name__} has dt={found!r})")
    return float(found)


# ------------------------------------------------------------------------------------------ smooth (SMPPI)

class SmoothProposal(GaussianProposal):
    """SMPPI's proposal (module docstring): white noise of std ``noise_std`` on the action rate (action units per
    second), integrated along the horizon from the action applied last (``last [B, q]``, zero at an episode's
    start), clipped to ``rate_max`` (a bound on ``|rate|``, scalar or ``[q]``; None: none) and to the action bounds.

    ``nominal`` is the action sequence drawn around (MPPI's: zero at first, then the weighted sequence shifted one
    step); :meth:`update` also records the command as the last action."""

    def __init__(self, system: System, num_samples: int, horizon: int, noise_std: float | Tensor = 1.0,
                 dt: float | None = None, rate_max: float | Tensor | None = None, device: torch.device | str = "cpu",
                 dtype: torch.dtype = torch.float32, num_robots: int = 1):
        self.dt = _system_dt(system, dt)
        super().__init__(system, num_samples, horizon, noise_std, device, dtype, num_robots)
        q = self.low.shape[0]
        if rate_max is None:
            bound = torch.full((q,), math.inf, dtype=self.dtype, device=self.device)
        else:
            bound = torch.as_tensor(rate_max, dtype=self.dtype, device=self.device).expand(q).clone()
            if bool((bound.isnan() | (bound <= 0)).any()):
                raise ValueError(f"rate_max must be > 0 (a scalar or one per action dimension, [{q}]), got {rate_max!r}")
        self.rate_max = bound  # [q]
        self._last = torch.zeros((self.num_robots, q), dtype=self.dtype, device=self.device)  # [B, q]

    @property
    def last(self) -> Tensor:
        """``[B, q]`` (``[q]`` for one robot): the action applied last, where each sample's integration starts."""
        return (self._last[0] if self.num_robots == 1 else self._last).clone()

    def _sequences_around(self, streams: RobotStreams) -> Tensor:
        """``[B, K, T, q]`` action sequences: rates around the nominal's, integrated from the last action."""
        k, t, q = self.num_samples, self.horizon, self.low.shape[0]
        eps = self._noise(streams, k * t).view(-1, k, t, q)  # [B, K, T, q] rate noise (std noise_std)
        start = self._last.unsqueeze(1)  # [B, 1, q]
        rate_bar = torch.diff(self._nominal, dim=1, prepend=start).div_(self.dt)  # [B, T, q] the nominal's rates
        rates = eps.add_(rate_bar.unsqueeze(1)).clamp_(-self.rate_max, self.rate_max)  # [B, K, T, q]
        return rates.cumsum_(dim=2).mul_(self.dt).add_(start.unsqueeze(1)).clamp_(self.low, self.high)

    def propose_batch(self, states: Tensor, streams: RobotStreams) -> tuple[Tensor, Tensor]:
        return _roll_out(self.system, states, self._sequences_around(streams))

    def update(self, result: MPPIResult) -> None:
        """The command becomes the last action; the nominal is the weighted sequence shifted one step."""
        nominal = result.nominal if result.nominal.ndim == 3 else result.nominal.unsqueeze(0)  # [B, T, q]
        self._last.copy_(nominal[:, 0])
        super().update(result)

    def reset(self, robots: Tensor | None = None) -> None:
        """Zero nominal and zero last action for ``robots`` (None: all)."""
        super().reset(robots)
        if robots is None:
            self._last.zero_()
        else:
            self._last.index_fill_(0, robots.to(self.device), 0.0)


class SmoothnessCost:
    """``cost_fn`` plus SMPPI's action-sequence cost ``weight * sum_t ||a_t - a_(t-1)||^2``, ``a_(-1)`` each robot's
    last action (``proposal.last``): a batched cost (``[B, K, T+1, d]``, ``[B, K, T, q]`` -> ``[B, K]``) that calls
    ``cost_fn`` batched or on the flattened rollouts, as the core would."""

    batched = True

    def __init__(self, cost_fn: CostFn, weight: float, proposal: SmoothProposal | None = None):
        self.cost_fn, self.weight = cost_fn, float(weight)
        self.proposal = proposal
        """whose ``last`` actions start the sum (set by :class:`SmoothMPPI` once its proposal is made)"""
        self._inner_batched = getattr(cost_fn, "batched", False) is True

    def __call__(self, states: Tensor, actions: Tensor) -> Tensor:
        b, k = states.shape[:2]
        if self._inner_batched:
            costs = self.cost_fn(states, actions)
        else:
            costs = self.cost_fn(states.reshape(b * k, *states.shape[2:]),
                                 actions.reshape(b * k, *actions.shape[2:]))
            if isinstance(costs, Tensor) and costs.shape == (b * k,):
                costs = costs.view(b, k)  # else left as it is: the core names the bad shape
        if self.weight == 0 or self.proposal is None:
            return costs
        start = self.proposal._last[:b].unsqueeze(1).expand(b, k, -1).unsqueeze(2)  # [B, K, 1, q]
        jumps = torch.diff(actions, dim=2, prepend=start)  # [B, K, T, q]
        return costs + self.weight * jumps.square().sum(dim=(2, 3))


class SmoothMPPI(MPPI):
    """Smooth MPPI (SMPPI, Kim et al., RA-L 2022): the core with a :class:`SmoothProposal` (noise on the action
    rate, integrated along the horizon) and the paper's action-sequence cost added to ``cost_fn``; the other
    parameters are :class:`~cuniform_torch.controllers.mppi.MPPI`'s.

    :param noise_std: the rate noise's std (action units per second; scalar or ``[q]``): a sample's deviation from
        the nominal at step ``t`` has std ``dt * noise_std * sqrt(t + 1)``
    :param smoothness: the weight of ``sum_t ||a_t - a_(t-1)||^2`` (from the action applied last); 0: none
    :param rate_max: a bound on each sampled rate's magnitude (scalar or ``[q]``; None: none)
    :param dt: the integration step (s); default the system's ``dt``
    """

    def __init__(self, system: System, cost_fn: CostFn, num_samples: int = 1000, horizon: int = 15,
                 lambda_: float = 0.567, noise_std: float | Tensor = 1.0, smoothness: float = 1.0,
                 rate_max: float | Tensor | None = None, dt: float | None = None,
                 terminal_cost: Callable[[Tensor], Tensor] | None = None, **kwargs: Any):
        if isinstance(smoothness, bool) or not isinstance(smoothness, (int, float)) \
                or not (math.isfinite(smoothness) and smoothness >= 0):
            raise ValueError(f"smoothness must be a finite number >= 0 (0: no action-sequence cost), got {smoothness!r}")
        if cost_fn is None or not callable(cost_fn):
            raise TypeError(f"cost_fn must be callable (states, actions) -> [K], got {type(cost_fn).__name__}")
        self.rate_max, self.dt, self.smoothness = rate_max, dt, float(smoothness)
        self.user_cost = cost_fn
        """the cost given; ``cost_fn`` is it plus the action-sequence cost (:class:`SmoothnessCost`)"""
        smoothed = SmoothnessCost(cost_fn, self.smoothness)
        super().__init__(system, smoothed, num_samples, horizon, lambda_, noise_std, terminal_cost, **kwargs)
        smoothed.proposal = cast(SmoothProposal, self.proposal)

    def _proposal(self, system, num_samples, horizon, noise_std, device, dtype,  # type: ignore[override]
                  num_robots) -> SmoothProposal:  # an instance method: it reads self.dt and self.rate_max
        return SmoothProposal(system, num_samples, horizon, noise_std, self.dt, self.rate_max, device, dtype,
                              num_robots)


# ------------------------------------------------------------------------------------------ kernel (KMPPI)

def rbf_interpolation(times: Tensor, support: Tensor, sigma: float) -> Tensor:
    """``[len(times), n]`` float64: ``K(times, support) K(support, support)^-1`` with the RBF kernel
    ``exp(-(t - s)^2 / (2 sigma^2))``: control-point values ``theta [n, ...]`` -> ``it @ theta``, the interpolation
    at ``times`` (exactly ``theta`` where a time is a support point). ValueError when the support points' kernel
    matrix is too ill-conditioned to solve (points too close for ``sigma``: fewer points or a smaller sigma)."""
    sigma = _positive("sigma", sigma)
    t = times.to(torch.float64).reshape(-1, 1)
    s = support.to(torch.float64).reshape(-1, 1)
    if s.shape[0] > 1 and bool((s[1:] <= s[:-1]).any()):
        raise ValueError(f"the support points must be increasing, got {support.tolist()}")

    def kernel(a: Tensor, b: Tensor) -> Tensor:  # [m, 1], [n, 1] -> [m, n]
        return torch.exp(-(a - b.T).square() / (2 * sigma * sigma))

    gram = kernel(s, s)  # [n, n]
    cond = float(torch.linalg.cond(gram))
    if not math.isfinite(cond) or cond > 1e8:
        raise ValueError(f"the kernel matrix of {s.shape[0]} control points with sigma {sigma:g} steps is ill-"
                         f"conditioned (condition number {cond:.3g}): use fewer control points or a smaller sigma")
    return torch.linalg.solve(gram, kernel(t, s), left=False)  # [len(times), n]


class KernelProposal(GaussianProposal):
    """KMPPI's proposal (module docstring): Gaussian noise of std ``noise_std`` on ``num_points`` control points
    (default ``T // 2``, at least 2) at the steps ``linspace(0, T - 1, n)``, each clipped to the action bounds, the
    sequence their RBF interpolation (``sigma`` in steps), clipped again. ``interp [T, n]`` maps control points to a
    sequence, ``fit [n, T]`` a sequence to its least-squares control points (``fit @ interp = I``)."""

    def __init__(self, system: System, num_samples: int, horizon: int, noise_std: float | Tensor = 1.0,
                 num_points: int | None = None, sigma: float = 1.0, device: torch.device | str = "cpu",
                 dtype: torch.dtype = torch.float32, num_robots: int = 1):
        super().__init__(system, num_samples, horizon, noise_std, device, dtype, num_robots)
        n = max(2, self.horizon // 2) if num_points is None else num_points
        if isinstance(n, bool) or not isinstance(n, int) or not 2 <= n <= self.horizon:
            raise ValueError(f"num_points must be an integer in [2, horizon = {self.horizon}], got {num_points!r}")
        self.num_points, self.sigma = n, _positive("sigma", sigma)
        steps = torch.arange(self.horizon, dtype=torch.float64)
        self.support = torch.linspace(0, self.horizon - 1, n, dtype=torch.float64)
        """``[n]`` the control points' steps"""
        interp = rbf_interpolation(steps, self.support, self.sigma)  # [T, n]
        fit = torch.linalg.pinv(interp)  # [n, T]: least squares, exact on interpolations
        self.interp = interp.to(device=self.device, dtype=self.dtype)
        self.fit = fit.to(device=self.device, dtype=self.dtype)

    def control_points(self, actions: Tensor) -> Tensor:
        """``[..., T, q]`` -> ``[..., n, q]``: the least-squares control points of action sequences."""
        return self.fit @ actions

    def _points_around(self, streams: RobotStreams) -> Tensor:
        """``[B, K, n, q]`` control points around those of each robot's nominal, clipped to the action bounds."""
        k, n, q = self.num_samples, self.num_points, self.low.shape[0]
        eps = self._noise(streams, k * n).view(-1, k, n, q)  # [B, K, n, q]
        centre = self.control_points(self._nominal).unsqueeze(1)  # [B, 1, n, q]
        return eps.add_(centre).clamp_(self.low, self.high)

    def propose_batch(self, states: Tensor, streams: RobotStreams) -> tuple[Tensor, Tensor]:
        actions = (self.interp @ self._points_around(streams)).clamp_(self.low, self.high)  # [B, K, T, q]
        return _roll_out(self.system, states, actions)


class KernelMPPI(MPPI):
    """Kernel-interpolation MPPI (KMPPI, Miura et al. 2024; pytorch_mppi's ``KMPPI``): the core with a
    :class:`KernelProposal`; the other parameters are :class:`~cuniform_torch.controllers.mppi.MPPI`'s.

    :param noise_std: the control points' noise std (action units; scalar or ``[q]``)
    :param num_points: control points per sequence, in [2, horizon] (default ``horizon // 2``)
    :param sigma: the RBF kernel's width in steps (default 1, pytorch_mppi's)
    """

    def __init__(self, system: System, cost_fn: CostFn, num_samples: int = 1000, horizon: int = 15,
                 lambda_: float = 0.567, noise_std: float | Tensor = 1.0, num_points: int | None = None,
                 sigma: float = 1.0, terminal_cost: Callable[[Tensor], Tensor] | None = None, **kwargs: Any):
        self.num_points, self.sigma = num_points, sigma
        super().__init__(system, cost_fn, num_samples, horizon, lambda_, noise_std, terminal_cost, **kwargs)

    def _proposal(self, system, num_samples, horizon, noise_std, device, dtype,  # type: ignore[override]
                  num_robots) -> KernelProposal:  # an instance method: it reads self.num_points and self.sigma
        return KernelProposal(system, num_samples, horizon, noise_std, self.num_points, self.sigma, device, dtype,
                              num_robots)
