"""A mixture proposal: the budget K split among any proposals, all K rollouts costed and weighted together.

Shapes: B robots, K samples per robot (K_i of part i), T horizon, d state dimensions, q action dimensions.

:class:`MixtureProposal` puts its parts' proposals side by side, ``[B, K_1 + ... + K_P, ...]``; the core costs all
of them and weighs them with one softmax, so a share of C-Uniform rollouts and a share of Gaussian ones compete in
one weighted mean (Biased-MPPI's mixtures; the one-pass CU-MPPI is a two-part one with its own warm start). Every
part draws from the same per-robot streams, in part order (a batch repeats what its robots would draw alone). After
a command each part warm-starts from the whole command's weighted sequence (``command``, ``nominal``) and its own
rows of the proposals, costs and weights (which sum to that part's share of the weight, not to 1): a Gaussian part
samples around the mixture's weighted sequence next.

:func:`split_budget` splits K by shares (largest remainders: the parts sum to K exactly, each gets at least one);
:class:`MixtureMPPI` is the core with a mixture, :class:`CUniformMixtureMPPI` the common one: a share of C-Uniform
rollouts of a policy beside Gaussian MPPI rollouts.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any, cast

import torch
from torch import Tensor

from cuniform_torch.controllers.core import CostFn, MPPICore
from cuniform_torch.controllers.proposals import Closeable, GaussianProposal, PolicyProposal, Proposal
from cuniform_torch.controllers.result import MPPIResult
from cuniform_torch.controllers.streams import RobotStreams
from cuniform_torch.sampling.rollout import Policy, same_device
from cuniform_torch.systems import System

__all__ = ["split_budget", "MixtureProposal", "MixtureMPPI", "CUniformMixtureMPPI"]


def split_budget(total: int, shares: Sequence[float]) -> list[int]:
    """``total`` samples split in proportion to ``shares`` (positive numbers, any scale): the floor of each part's
    exact share, the rest one each to the largest remainders (a tie to the earlier part), every part at least 1
    (taken from the largest). The parts sum to ``total`` exactly. ValueError for bad shares or ``total`` below the
    number of parts."""
    shares = list(shares)
    if not shares:
        raise ValueError("give at least one share")
    if any(isinstance(s, bool) or not isinstance(s, (int, float)) or not (math.isfinite(s) and s > 0) for s in shares):
        raise ValueError(f"shares must be finite numbers > 0, got {shares}")
    if isinstance(total, bool) or not isinstance(total, int) or total < len(shares):
        raise ValueError(f"cannot split {total!r} samples among {len(shares)} parts: give an integer K >= "
                         f"{len(shares)} (at least one sample per part)")
    whole = sum(shares)
    exact = [total * s / whole for s in shares]
    parts = [math.floor(e) for e in exact]
    by_remainder = sorted(range(len(shares)), key=lambda i: (-(exact[i] - parts[i]), i))
    for i in by_remainder[:total - sum(parts)]:
        parts[i] += 1
    for i in range(len(parts)):
        if parts[i] == 0:  # a tiny share still draws one sample, from the largest part
            parts[max(range(len(parts)), key=lambda j: (parts[j], -j))] -= 1
            parts[i] = 1
    return parts


def _part_result(result: MPPIResult, start: int, stop: int) -> MPPIResult:
    """The rows ``start:stop`` of a result's proposals, costs and weights, with the whole command and nominal."""
    if result.costs.ndim == 1:  # one robot's
        return MPPIResult(result.command, result.nominal, result.states[start:stop], result.actions[start:stop],
                          result.costs[start:stop], result.weights[start:stop])
    return MPPIResult(result.command, result.nominal, result.states[:, start:stop], result.actions[:, start:stop],
                      result.costs[:, start:stop], result.weights[:, start:stop])


class MixtureProposal:
    """The parts' proposals side by side (module docstring): ``num_samples`` is the sum of theirs; ``offsets[i]:
    offsets[i + 1]`` are part ``i``'s rows. The parts must share the horizon, the number of robots, the device, the
    dtype and the system's state and action dimensions (ValueError naming the part that differs).

    :param parts: the batched proposals (at least one), each made with its own ``num_samples``
    """

    def __init__(self, parts: Sequence[Proposal]):
        self.parts = list(parts)
        if not self.parts:
            raise ValueError("a mixture needs at least one proposal")
        for i, p in enumerate(self.parts):
            if not isinstance(p, Proposal):
                raise TypeError(f"mixture part {i} ({type(p).__name__}) is not a batched Proposal (it needs "
                                f"propose_batch, update, reset, system, num_samples, horizon, num_robots, device, "
                                f"dtype)")
        first = self.parts[0]
        self.system, self.horizon, self.num_robots = first.system, first.horizon, first.num_robots
        self.device, self.dtype = torch.device(first.device), first.dtype
        dims = self._dims(first)
        for i, p in enumerate(self.parts[1:], start=1):
            same = (p.horizon == self.horizon, p.num_robots == self.num_robots,
                    same_device(torch.device(p.device), self.device), p.dtype == self.dtype, self._dims(p) == dims)
            if not all(same):
                raise ValueError(
                    f"mixture part {i} ({type(p).__name__}: horizon {p.horizon}, {p.num_robots} robots, {p.device}, "
                    f"{p.dtype}, state/action dims {self._dims(p)}) differs from part 0 ({type(first).__name__}: "
                    f"horizon {self.horizon}, {self.num_robots} robots, {self.device}, {self.dtype}, {dims}): make "
                    f"every part for the same system, horizon, robots, device and dtype")
        sizes = [int(p.num_samples) for p in self.parts]
        self.sizes = sizes
        """K_i of each part"""
        self.offsets = [0, *[sum(sizes[:i + 1]) for i in range(len(sizes))]]
        """part ``i``'s rows are ``offsets[i]:offsets[i + 1]``"""
        self.num_samples = self.offsets[-1]
        extra = [g for p in self.parts for g in self._extra(p)]
        self.extra_streams = RobotStreams(extra) if extra else None
        """the parts' own further streams (a two-stage part's first stage), for a CUDA graph to register"""

    @staticmethod
    def _dims(p: Proposal) -> tuple[int, int]:
        actions = p.system.action_set(dtype=p.dtype, device=p.device)  # [A, q]
        return len(p.system.periodic), int(actions.shape[1])

    @staticmethod
    def _extra(p: Proposal) -> list[torch.Generator]:
        extra = getattr(p, "extra_streams", None)
        return list(extra.generators) if isinstance(extra, RobotStreams) else []

    @classmethod
    def split(cls, num_samples: int, shares: Sequence[float],
              factories: Sequence[Callable[[int], Proposal]]) -> MixtureProposal:
        """A mixture of ``factories[i](K_i)``, ``K_i`` of :func:`split_budget` ``(num_samples, shares)``."""
        if len(factories) != len(shares):
            raise ValueError(f"give one share per proposal: {len(shares)} shares for {len(factories)} proposals")
        return cls([make(k) for make, k in zip(factories, split_budget(num_samples, shares))])

    def propose_batch(self, states: Tensor, streams: RobotStreams) -> tuple[Tensor, Tensor]:
        drawn = [p.propose_batch(states, streams) for p in self.parts]  # each robot's stream, part after part
        return torch.cat([x for x, _ in drawn], dim=1), torch.cat([u for _, u in drawn], dim=1)

    def update(self, result: MPPIResult) -> None:
        """Each part warm-starts from the whole command and its own rows (module docstring)."""
        for p, start, stop in zip(self.parts, self.offsets[:-1], self.offsets[1:]):
            p.update(_part_result(result, start, stop))

    def reset(self, robots: Tensor | None = None) -> None:
        for p in self.parts:
            p.reset(robots)

    def close(self) -> None:
        for p in self.parts:
            if isinstance(p, Closeable):
                p.close()


class MixtureMPPI(MPPICore):
    """The MPPI core with a :class:`MixtureProposal` of ``parts``: all their rollouts costed and weighted together.
    ``seed`` / ``generator`` seed the one stream per robot that every part draws from; the rest is
    :class:`~cuniform_torch.controllers.core.MPPICore`'s.

    :param parts: batched proposals, each made with its share of the budget (:func:`split_budget`)
    :param cost_fn: as :class:`~cuniform_torch.controllers.mppi.MPPI`'s, and so are ``lambda_``, ``terminal_cost``,
        ``seed``, ``debug`` and ``cuda_graph``
    """

    def __init__(self, parts: Sequence[Proposal], cost_fn: CostFn, lambda_: float = 0.567,
                 terminal_cost: Callable[[Tensor], Tensor] | None = None, seed: int | Sequence[int] | None = None,
                 **kwargs: Any):
        self.mixture = MixtureProposal(parts)
        super().__init__(self.mixture, cost_fn, lambda_, terminal_cost, seed, **kwargs)


class CUniformMixtureMPPI(MixtureMPPI):
    """A share of C-Uniform rollouts of ``policy`` beside Gaussian MPPI rollouts (std ``noise_std`` around the
    warm-started weighted sequence), all weighted together: ``round(cuniform_fraction * K)`` (by
    :func:`split_budget`) C-Uniform ones (:class:`~cuniform_torch.controllers.proposals.PolicyProposal`), the rest
    Gaussian (:class:`~cuniform_torch.controllers.proposals.GaussianProposal`).

    :param policy: a table, an MLP, any Policy with a ``system``, or a distilled checkpoint dict
    :param cost_fn: as :class:`~cuniform_torch.controllers.mppi.MPPI`'s, and so are ``num_samples`` (K per robot,
        both shares), ``lambda_``, ``terminal_cost``, ``seed``, ``num_robots``, ``debug`` and ``cuda_graph``
    :param cuniform_fraction: the C-Uniform share of K, in (0, 1)
    :param noise_std: the Gaussian share's std (scalar or ``[q]``)
    :param horizon: T (default: the policy's)
    :param device: the policy's device when a checkpoint dict is given
    """

    def __init__(self, policy: Policy | dict[str, Any], cost_fn: CostFn, num_samples: int = 1000,
                 cuniform_fraction: float = 0.5, noise_std: float | Tensor = 1.0, lambda_: float = 0.567,
                 horizon: int | None = None, terminal_cost: Callable[[Tensor], Tensor] | None = None,
                 device: torch.device | str | None = None, seed: int | Sequence[int] | None = None,
                 num_robots: int = 1, **kwargs: Any):
        if isinstance(cuniform_fraction, bool) or not isinstance(cuniform_fraction, (int, float)) \
                or not 0 < cuniform_fraction < 1:
            raise ValueError(f"cuniform_fraction must be in (0, 1), got {cuniform_fraction!r}")
        k_cu, k_gauss = split_budget(num_samples, (cuniform_fraction, 1 - cuniform_fraction))
        cu = PolicyProposal(policy, k_cu, horizon, device, num_robots)
        system = cast(System, cu.system)  # a PolicyProposal refuses a policy without one
        gauss = GaussianProposal(system, k_gauss, cu.horizon, noise_std, cu.device, cu.dtype, num_robots)
        self.cuniform_fraction, self.noise_std = float(cuniform_fraction), noise_std
        self.policy = cu.policy
        super().__init__([cast(Proposal, cu), gauss], cost_fn, lambda_, terminal_cost, seed, **kwargs)
