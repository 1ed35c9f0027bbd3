"""Per-robot random streams of a batched controller: :class:`RobotStreams`.

Shapes: B robots.

A controller of B robots keeps one ``torch.Generator`` per robot, so that robot ``b`` of a batched controller
draws exactly what a controller of that robot alone, seeded the same, would draw. A command draws all of its
randomness up front, one call per robot (:meth:`RobotStreams.rand`, :meth:`RobotStreams.randn`), into one
``[B, ...]`` tensor; everything after that is one tensor program over the batch. Those B generator calls are
the only per-robot loop of a command.
"""

from __future__ import annotations

import numbers
from collections.abc import Sequence
from typing import cast

import torch
from torch import Tensor

__all__ = ["RobotStreams", "robot_seeds", "shifted"]

_SPREAD = 1_000_003
"""robot ``b`` of a controller seeded ``s`` is seeded ``s + b * _SPREAD`` (a prime far from the ``+ 1`` that the
controllers use for a second stream, so no two streams of a batch share a seed)"""


def robot_seeds(seed: int | Sequence[int] | None, num_robots: int) -> list[int | None]:
    """The seed of each of ``num_robots`` robots: a sequence gives one per robot; an int ``s`` gives
    ``s + b * 1_000_003`` to robot ``b`` (robot 0: ``s``, what a one-robot controller seeded ``s`` uses); None gives
    fresh entropy to each. TypeError / ValueError naming what is wrong."""
    if seed is None:
        return [None] * num_robots
    if isinstance(seed, bool) or not isinstance(seed, (numbers.Integral, Sequence)) or isinstance(seed, str):
        raise TypeError(f"seed must be an int or None (or a sequence of {num_robots} ints, one per robot), got "
                        f"{type(seed).__name__} ({seed!r:.40})")
    if isinstance(seed, numbers.Integral):
        return [int(seed) + b * _SPREAD for b in range(num_robots)]
    seeds = list(cast(Sequence[int], seed))
    if len(seeds) != num_robots or any(isinstance(s, bool) or not isinstance(s, numbers.Integral) for s in seeds):
        raise ValueError(f"seed as a sequence must hold {num_robots} ints (one per robot), got {seed!r:.80}")
    return [int(s) for s in seeds]


def shifted(seed: int | Sequence[int] | None, by: int) -> int | list[int] | None:
    """A second stream's seed: ``seed + by`` (each robot's, for a sequence; None stays None)."""
    if seed is None:
        return None
    if isinstance(seed, Sequence):
        return [int(s) + by for s in seed]
    return int(seed) + by


class RobotStreams:
    """One ``torch.Generator`` per robot, all on one device. ``generators[b]`` is robot ``b``'s stream."""

    def __init__(self, generators: Sequence[torch.Generator]):
        if not generators:
            raise ValueError("a controller needs at least one robot")
        self.generators = list(generators)
        self.device = self.generators[0].device

    @classmethod
    def seeded(cls, seeds: Sequence[int | None], device: torch.device | str) -> RobotStreams:
        """Generators on ``device`` seeded by ``seeds`` (None: fresh entropy)."""
        gens = []
        for s in seeds:
            g = torch.Generator(device=torch.device(device))
            g.manual_seed(s) if s is not None else g.seed()
            gens.append(g)
        return cls(gens)

    def __len__(self) -> int:
        return len(self.generators)

    def _draw(self, fill: str, shape: tuple[int, ...], dtype: torch.dtype, rows: Sequence[int] | None) -> Tensor:
        gens = self.generators if rows is None else [self.generators[b] for b in rows]
        out = torch.empty((len(gens), *shape), dtype=dtype, device=self.device)
        draw = torch.rand if fill == "rand" else torch.randn
        for b, g in enumerate(gens):  # one call per robot: each robot's own stream, in its own order
            draw(shape, generator=g, dtype=dtype, device=self.device, out=out[b])
        return out

    def rand(self, shape: tuple[int, ...], dtype: torch.dtype, rows: Sequence[int] | None = None) -> Tensor:
        """Uniforms in ``[0, 1)``: ``[B, *shape]`` (``rows``: only those robots' streams, in that order)."""
        return self._draw("rand", shape, dtype, rows)

    def randn(self, shape: tuple[int, ...], dtype: torch.dtype, rows: Sequence[int] | None = None) -> Tensor:
        """Standard normals: ``[B, *shape]`` (``rows`` as in :meth:`rand`)."""
        return self._draw("randn", shape, dtype, rows)
