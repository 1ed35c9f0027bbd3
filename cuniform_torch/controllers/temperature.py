"""The automatic temperature of the MPPI core (``lambda_="auto"``): per command and per robot, the ``lambda`` whose
weights have a target effective sample size.

Shapes: B robots, K proposals per robot, G temperatures tried at once.

MPPI's weights are ``softmax(-(cost - min) / lambda - extra)`` (``extra``: a cost that does not scale with
``1 / lambda``, pytorch_mppi's control cost ``U Sigma^-1 eps``, or 0). Their effective sample size
``ESS = 1 / sum(w^2)`` goes from 1 (all the weight on the best proposal, ``lambda -> 0``) to K (uniform,
``lambda -> inf``) as ``lambda`` grows (with ``extra = 0``; with it, the uniform end is ``softmax(-extra)``).
:func:`auto_temperature` finds the smallest ``lambda`` whose ESS reaches the target by a G-section search in
``log lambda``: each round tries G temperatures per robot at once (one ``[B, G, K]`` softmax) and keeps the grid
cell where the ESS crosses the target. A fixed number of rounds, no Python loop over robots, no host sync: the
command stays one tensor program (and a CUDA graph can capture it).
"""

from __future__ import annotations

import numbers

import torch
from torch import Tensor

from cuniform_torch.controllers.checks import COST_CAP

__all__ = ["auto_temperature", "temperature_weights", "check_target_ess", "LOW_DECADES", "HIGH_DECADES"]

LOW_DECADES = 6.0
"""the search starts ``10^6`` below the spread of a robot's finite costs (ESS ~ 1 there) ..."""
HIGH_DECADES = 3.0
"""... and ends ``10^3`` above it (every finite cost within ``exp(-1e-3)`` of the best: ESS ~ K)"""
_GRID = 16
_ROUNDS = 4
"""16 temperatures a round, 4 rounds: the bracket shrinks 15^4 = 50625 times, to ~4e-4 in ``log lambda``"""


def check_target_ess(target_ess: object, num_samples: int) -> float:
    """``target_ess`` as a float in ``[1, K]`` (ValueError naming the range otherwise); None: K / 10."""
    if target_ess is None:
        return max(1.0, num_samples / 10)
    if isinstance(target_ess, bool) or not isinstance(target_ess, numbers.Real) or not (
            1 <= float(target_ess) <= num_samples):
        raise ValueError(f"target_ess must be a number of samples between 1 and num_samples = {num_samples} (the "
                         f"effective sample size the automatic temperature aims for), got {target_ess!r}")
    return float(target_ess)


def _ess(delta: Tensor, extra: Tensor | None, lambdas: Tensor) -> Tensor:
    """ESS of the weights of ``delta [B, K]`` (costs minus their minimum) at each of ``lambdas [B, G]``:
    ``[B, G]``."""
    logits = delta.unsqueeze(1) / lambdas.unsqueeze(2)  # [B, G, K]
    logits = logits.neg_() if extra is None else logits.neg_().sub_(extra.unsqueeze(1))
    weights = torch.softmax(logits, dim=-1)
    return weights.square_().sum(dim=-1).reciprocal_()


def auto_temperature(costs: Tensor, target_ess: float, extra: Tensor | None = None) -> Tensor:
    """The smallest ``lambda`` (within ~4e-4 relative) whose weights of finite ``costs [B, K]`` have an ESS of at
    least ``target_ess``: ``[B]``. The search spans ``10^-6`` to ``10^3`` times each robot's spread of finite
    costs (capped costs, ``COST_CAP``, left out of the spread); a target beyond reach at either end gives that
    end. ``extra [B, K]``: a cost that does not scale with ``1 / lambda`` (see the module)."""
    delta = costs - costs.amin(dim=-1, keepdim=True)  # [B, K] >= 0
    finite = torch.where(costs < COST_CAP / 2, delta, torch.zeros_like(delta))
    scale = finite.amax(dim=-1).clamp_min(torch.finfo(costs.dtype).eps).log()  # [B] log of the spread
    ln10 = 2.302585092994046
    lo, hi = scale - LOW_DECADES * ln10, scale + HIGH_DECADES * ln10  # [B] log lambda
    frac = torch.linspace(0.0, 1.0, _GRID, dtype=costs.dtype, device=costs.device)  # [G]
    for _ in range(_ROUNDS):  # a fixed number of rounds: no host read decides when to stop
        grid = lo.unsqueeze(1) + (hi - lo).unsqueeze(1) * frac  # [B, G] log lambda, increasing
        above = _ess(delta, extra, grid.exp()) >= target_ess  # [B, G]
        first = torch.where(above.any(dim=1), above.to(costs.dtype).argmax(dim=1),
                            torch.full_like(scale, _GRID - 1, dtype=torch.long))  # [B] first grid point at target
        hi = grid.gather(1, first.unsqueeze(1)).squeeze(1)
        lo = grid.gather(1, (first - 1).clamp_min(0).unsqueeze(1)).squeeze(1)
    return hi.exp()


def temperature_weights(costs: Tensor, lambdas: Tensor, extra: Tensor | None = None) -> Tensor:
    """``softmax(-(cost - min) / lambda - extra)`` of finite ``costs [B, K]`` at one ``lambda`` per robot
    (``lambdas [B]``): ``[B, K]``."""
    logits = (costs - costs.amin(dim=-1, keepdim=True)).div_(lambdas.unsqueeze(1)).neg_()
    if extra is not None:
        logits = logits.sub_(extra)
    return torch.softmax(logits, dim=-1)
