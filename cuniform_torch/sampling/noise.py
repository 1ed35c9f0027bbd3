"""Continuous noise samplers around a nominal action sequence (the MPPI and log-MPPI proposals).

Shapes: N samples, T horizon, q action dimensions.

* :class:`GaussianSampler`: ``u_t = clip(nominal_t + eps)``, ``eps ~ N(0, std^2)`` per action dimension (MPPI).
  The paper writes the noise as Sigma in {0.03, 0.1, 0.3}; here ``std`` is the standard deviation.
* :class:`NormalLogNormalSampler`: ``u_t = clip(nominal_t + n * l)`` with ``n ~ N(0, std^2)`` and
  ``l ~ LogNormal(mu, sigma^2)`` independent (Mohamed et al., log-MPPI). The log-normal factor is given by
  its own mean ``m`` and variance ``v``: ``sigma^2 = ln(1 + v / m^2)``, ``mu = ln(m) - sigma^2 / 2``. The product
  has mean 0 and variance ``std^2 (v + m^2)``, with heavier tails than a Gaussian of that variance.

Both clip to the system's action bounds (the range of its discrete action set). They are noise laws: the
MPPI and log-MPPI proposals (:mod:`cuniform_torch.controllers.proposals`) draw whole sequences with :meth:`perturb`; each is
also an :class:`~cuniform_torch.sampling.rollout.ActionSampler` (``sample(x, t, generator)``, one step's actions around
its own ``nominal``), so :func:`~cuniform_torch.sampling.rollout.rollout` runs it too, declaring its ``horizon`` (the
nominal's length), ``device`` and ``dtype`` as :class:`~cuniform_torch.sampling.rollout.PolicyTraits`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from cuniform_torch.sampling.rollout import check_generator

__all__ = ["GaussianSampler", "NormalLogNormalSampler", "lognormal_params"]


def lognormal_params(mean: float, var: float) -> tuple[float, float]:
    """``(mu, sigma)`` of the log-normal law with the given mean and variance (mean > 0, var >= 0)."""
    if not (mean > 0 and var >= 0 and math.isfinite(mean) and math.isfinite(var)):
        raise ValueError(f"log-normal needs mean > 0 and variance >= 0, got mean={mean}, var={var}")
    sigma2 = math.log1p(var / mean**2)
    return math.log(mean) - sigma2 / 2, math.sqrt(sigma2)


def _as_std(std: float | Tensor, q: int, like: Tensor) -> Tensor:
    s = torch.as_tensor(std, dtype=like.dtype, device=like.device).reshape(-1)
    if s.numel() == 1:
        s = s.expand(q)
    if s.shape != (q,) or bool((s < 0).any()) or not bool(torch.isfinite(s).all()):
        raise ValueError(f"noise std must be a non-negative scalar or a [{q}] vector, got {std!r}")
    return s


@dataclass
class GaussianSampler:
    """Gaussian noise around ``nominal [T, q]``, clipped to ``[low, high]`` (``[q]`` each)."""

    nominal: Tensor
    std: float | Tensor
    low: Tensor
    high: Tensor

    def __post_init__(self) -> None:
        if self.nominal.ndim != 2:
            raise ValueError(f"nominal must be [T, q], got {list(self.nominal.shape)}")
        self.std = _as_std(self.std, self.nominal.shape[1], self.nominal)

    @property
    def horizon(self) -> int:
        """steps of the nominal: the longest rollout this sampler serves"""
        return self.nominal.shape[0]

    @property
    def device(self) -> torch.device:
        return self.nominal.device

    @property
    def dtype(self) -> torch.dtype:
        return self.nominal.dtype

    def noise(self, n: int, generator: torch.Generator | None) -> Tensor:
        """``[n, q]`` zero-mean noise (TypeError when ``generator`` is neither None nor a torch.Generator)."""
        check_generator(generator, self.nominal.device)
        q = self.nominal.shape[1]
        eps = torch.randn((n, q), generator=generator, dtype=self.nominal.dtype, device=self.nominal.device)
        return eps.mul_(self.std)

    def sample(self, x: Tensor, t: int, generator: torch.Generator | None) -> Tensor:
        """``x [N, d]`` at step ``t`` -> ``[N, q]`` actions (ValueError when ``x`` is not of the sampler's dtype)."""
        if x.dtype != self.nominal.dtype:
            raise ValueError(f"states are {x.dtype} but the sampler is {self.nominal.dtype}")
        return torch.clamp(self.nominal[t] + self.noise(x.shape[0], generator), self.low, self.high)

    def sample_sequences(self, n: int, horizon: int, generator: torch.Generator | None) -> Tensor:
        """The whole open-loop action sequences at once: ``[n, horizon, q]`` (noise does not depend on the state)."""
        if horizon > self.nominal.shape[0]:
            raise ValueError(f"the sampler's nominal sequence has {self.nominal.shape[0]} steps, fewer than horizon {horizon}")
        return self.perturb(self.nominal[:horizon], n, generator)

    def perturb(self, nominal: Tensor, n: int, generator: torch.Generator | None) -> Tensor:
        """``n`` noisy copies of any ``nominal [T, q]`` (of this law's dtype and device), clipped: ``[n, T, q]``.

        Pure tensor ops, no host sync: what a proposal calls every command with its current nominal."""
        horizon, q = nominal.shape
        noise = self.noise(n * horizon, generator).reshape(n, horizon, q)  # a fresh tensor: updated in place
        return noise.add_(nominal).clamp_(self.low, self.high)


@dataclass
class NormalLogNormalSampler(GaussianSampler):
    """log-MPPI noise: normal x log-normal around ``nominal [T, q]``; see the module docstring."""

    lognormal_mean: float = 1.0
    lognormal_var: float = 1.0

    def __post_init__(self) -> None:
        super().__post_init__()
        self.mu, self.sigma = lognormal_params(self.lognormal_mean, self.lognormal_var)

    def noise(self, n: int, generator: torch.Generator | None) -> Tensor:
        check_generator(generator, self.nominal.device)
        q = self.nominal.shape[1]
        dtype, device = self.nominal.dtype, self.nominal.device
        normal = torch.randn((n, q), generator=generator, dtype=dtype, device=device).mul_(self.std)
        lognormal = torch.randn((n, q), generator=generator, dtype=dtype, device=device)
        lognormal = lognormal.mul_(self.sigma).add_(self.mu).exp_()
        return normal.mul_(lognormal)
