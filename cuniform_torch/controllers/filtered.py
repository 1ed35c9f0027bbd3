"""Time-correlated Gaussian noise, the samplers MPC users switch to from white noise: colored (power-law) noise and
low-pass (first-order) noise, as batched proposals of the MPPI core and as controllers.

Shapes: B robots, K samples per robot, T horizon, q action dimensions.

Both are MPPI's proposal (:class:`~cuniform_torch.controllers.proposals.GaussianProposal`: ``clip(nominal + eps)``,
the same warm start) with ``eps`` white noise mixed along time by one fixed ``[T, T]`` matrix, so each sample's noise
keeps the standard deviation ``noise_std`` at every step but is correlated across steps:

* :class:`ColoredNoiseProposal` / :class:`ColoredMPPI`: power spectral density ``~ 1 / f^beta`` along the horizon
  (``beta = 0`` white, 1 pink, 2 red), the circulant filter ``f^(-beta / 2)`` on the horizon's frequencies (the
  zero frequency takes the lowest one's gain), as in colored-noise MPPI samplers (MPPI-Generic's
  ``sampling_distributions``; Eberhard et al., "Pink noise is all you need", CoRL 2022);
* :class:`LowPassProposal` / :class:`LowPassMPPI`: the stationary first-order low-pass (AR(1)) filter
  ``e_t = a e_{t-1} + sqrt(1 - a^2) w_t``, ``e_0 = w_0``; ``a = exp(-2 pi f_c dt)`` for a cutoff ``f_c`` (Hz) at the
  system's time step (navigation2's smoothed samplers).

The mixing is one matrix product per command (``[B K q, T] @ [T, T]``), drawn from each robot's own stream like
MPPI's noise (a batch commands what its robots would alone).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor

from cuniform_torch.controllers.callables import DynamicsFn
from cuniform_torch.controllers.core import CostFn
from cuniform_torch.controllers.mppi import MPPI
from cuniform_torch.controllers.proposals import GaussianProposal
from cuniform_torch.controllers.streams import RobotStreams
from cuniform_torch.systems import System

__all__ = ["colored_filter", "low_pass_filter", "FilteredNoiseProposal", "ColoredNoiseProposal", "LowPassProposal",
           "ColoredMPPI", "LowPassMPPI"]


def colored_filter(horizon: int, beta: float) -> Tensor:
    """``[T, T]`` float64: white noise ``w [.., T]`` times it has power spectrum ``~ 1 / f^beta`` and unit variance
    at every step (a circulant filter: every step alike)."""
    if not (math.isfinite(beta) and 0 <= beta <= 4):
        raise ValueError(f"beta must be a number in [0, 4] (0 white, 1 pink, 2 red), got {beta!r}")
    freqs = torch.fft.rfftfreq(horizon, dtype=torch.float64)  # [T//2 + 1], cycles per step
    gain = freqs.clone()
    if horizon > 1:
        gain[0] = freqs[1]  # the mean (zero frequency) takes the lowest frequency's gain
    else:
        gain[0] = 1.0
    gain = gain.pow(-beta / 2)
    eye = torch.eye(horizon, dtype=torch.float64)
    mixed = torch.fft.irfft(torch.fft.rfft(eye, dim=1) * gain, n=horizon, dim=1)  # [T, T]: row i = filtered e_i
    return mixed / mixed.square().sum(dim=0, keepdim=True).sqrt()  # unit variance at every step


def low_pass_filter(horizon: int, a: float) -> Tensor:
    """``[T, T]`` float64 of the stationary AR(1) filter ``e_t = a e_{t-1} + sqrt(1 - a^2) w_t`` (``e = w @ it``)."""
    if not (math.isfinite(a) and 0 <= a < 1):
        raise ValueError(f"the low-pass coefficient must be in [0, 1) (0: white noise), got {a!r}")
    t = torch.arange(horizon, dtype=torch.float64)
    lag = t[None, :] - t[:, None]  # [s, t]: t - s
    weights = torch.where(lag >= 0, a ** lag.clamp(min=0), torch.zeros_like(lag)) * math.sqrt(1 - a * a)
    weights[0] = torch.where(lag[0] >= 0, a ** lag[0].clamp(min=0), torch.zeros_like(lag[0]))  # e_0 = w_0
    return weights  # [T (source s), T (step t)]


class FilteredNoiseProposal(GaussianProposal):
    """MPPI's proposal with white noise mixed along time by ``mix [T, T]`` (unit variance per step); the subclasses
    make the two usual ones."""

    def __init__(self, system: System, num_samples: int, horizon: int, mix: Tensor,
                 noise_std: float | Tensor | None = 0.3,
                 device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32, num_robots: int = 1):
        super().__init__(system, num_samples, horizon, noise_std, device, dtype, num_robots)
        if mix.shape != (self.horizon, self.horizon):
            raise ValueError(f"mix must be [{self.horizon}, {self.horizon}], got {list(mix.shape)}")
        self.mix = mix.to(device=self.device, dtype=self.dtype)

    def _sequences(self, streams: RobotStreams, k: int, t: int) -> Tensor:
        """``[B, K, T, q]``: white noise per robot, mixed along time, scaled by the std."""
        q = self.low.shape[0]
        white = streams.randn((k, q, t), self.dtype)  # [B, K, q, T] from each robot's stream
        return (white @ self.mix).transpose(2, 3).mul_(self.std)  # [B, K, T, q]


class ColoredNoiseProposal(FilteredNoiseProposal):
    """Colored (power-law) noise around the nominal: spectrum ``~ 1 / f^beta`` along the horizon."""

    def __init__(self, system: System, num_samples: int, horizon: int, noise_std: float | Tensor | None = 0.3,
                 beta: float = 1.0, device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32,
                 num_robots: int = 1):
        self.beta = float(beta)
        super().__init__(system, num_samples, horizon, colored_filter(horizon, self.beta), noise_std, device, dtype,
                         num_robots)


class LowPassProposal(FilteredNoiseProposal):
    """Low-pass (AR(1)) noise around the nominal: ``a = exp(-2 pi cutoff dt)``, or ``a`` given."""

    def __init__(self, system: System, num_samples: int, horizon: int, noise_std: float | Tensor | None = 0.3,
                 a: float = 0.8, device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32,
                 num_robots: int = 1):
        self.a = float(a)
        super().__init__(system, num_samples, horizon, low_pass_filter(horizon, self.a), noise_std, device, dtype,
                         num_robots)


class ColoredMPPI(MPPI):
    """MPPI with colored noise (:class:`ColoredNoiseProposal`, ``beta``: 0 white, 1 pink, 2 red); the other
    parameters are :class:`~cuniform_torch.controllers.mppi.MPPI`'s.

    :param beta: the spectrum's exponent, in [0, 4]
    """

    def __init__(self, system: System | DynamicsFn, cost_fn: CostFn | None = None, num_samples: int = 1000,
                 horizon: int = 15, lambda_: float | str = 0.567, noise_std: float | Tensor | None = None, beta: float = 1.0,
                 terminal_cost: Callable[[Tensor], Tensor] | None = None, **kwargs: Any):
        self.beta = beta
        super().__init__(system, cost_fn, num_samples, horizon, lambda_, noise_std, terminal_cost, **kwargs)

    def _proposal(self, system, num_samples, horizon, noise_std, device, dtype,  # type: ignore[override]
                  num_robots) -> ColoredNoiseProposal:  # an instance method: it reads self.beta (as LogMPPI does)
        return ColoredNoiseProposal(system, num_samples, horizon, noise_std, self.beta, device, dtype, num_robots)


class LowPassMPPI(MPPI):
    """MPPI with low-pass noise (:class:`LowPassProposal`); ``cutoff`` (Hz, at the system's ``dt``) or ``a`` sets
    the filter; the other parameters are :class:`~cuniform_torch.controllers.mppi.MPPI`'s.

    :param cutoff: the filter's cutoff frequency in Hz (needs ``system.dt``); or
    :param a: the AR(1) coefficient in [0, 1) itself (default 0.8 when no cutoff is given)
    """

    def __init__(self, system: System | DynamicsFn, cost_fn: CostFn | None = None, num_samples: int = 1000,
                 horizon: int = 15, lambda_: float | str = 0.567, noise_std: float | Tensor | None = None, cutoff: float | None = None,
                 a: float | None = None, terminal_cost: Callable[[Tensor], Tensor] | None = None, **kwargs: Any):
        if cutoff is not None and a is not None:
            raise ValueError("give a cutoff (Hz) or the coefficient a, not both")
        if cutoff is not None:
            dt = getattr(system, "dt", None)
            if not isinstance(dt, (int, float)) or not dt > 0 or not (math.isfinite(cutoff) and cutoff > 0):
                raise ValueError(f"cutoff needs a positive number (Hz) and a system with a positive dt; got cutoff="
                                 f"{cutoff!r}, dt={dt!r} (or give a)")
            a = math.exp(-2 * math.pi * cutoff * dt)
        self.a = 0.8 if a is None else a
        super().__init__(system, cost_fn, num_samples, horizon, lambda_, noise_std, terminal_cost, **kwargs)

    def _proposal(self, system, num_samples, horizon, noise_std, device, dtype,  # type: ignore[override]
                  num_robots) -> LowPassProposal:  # an instance method: it reads self.a
        return LowPassProposal(system, num_samples, horizon, noise_std, self.a, device, dtype, num_robots)
