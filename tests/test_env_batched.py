"""``Environment.in_collision`` tests all Circles and Rects at once; its answers are those of each obstacle's own
``contains``, to the last bit, in float32 and float64, on boundaries, in chunks, and with obstacles of other kinds."""

from __future__ import annotations

import random
from dataclasses import dataclass

import pytest
import torch

import cuniform_torch.envs.environment as environment
from cuniform_torch.envs import Circle, Environment, Rect


def _world(seed: int) -> list:
    rng = random.Random(seed)
    obstacles: list = []
    for _ in range(rng.randint(1, 40)):
        x, y = rng.uniform(-3, 3), rng.uniform(-3, 3)
        if rng.random() < 0.6:
            obstacles.append(Circle(center=(x, y), radius=rng.uniform(0.01, 1.0)))
        else:
            obstacles.append(Rect(x, y, x + rng.uniform(0.01, 2), y + rng.uniform(0.01, 2)))
    return obstacles


def _one_by_one(obstacles: list, xy: torch.Tensor) -> torch.Tensor:
    hit = ~torch.isfinite(xy).all(dim=-1)
    for obs in obstacles:
        hit |= obs.contains(xy)
    return hit


@dataclass(frozen=True)
class _Ring(Circle):
    """A subclass with its own contains: a ring, not a disc (the batch must not treat it as a Circle)."""

    def contains(self, xy):
        d2 = (xy[..., 0] - self.center[0]) ** 2 + (xy[..., 1] - self.center[1]) ** 2
        return (d2 <= self.radius ** 2) & (d2 >= (0.5 * self.radius) ** 2)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("chunk", [1 << 22, 5])
@pytest.mark.parametrize("compiled", [False, True])
def test_batched_collisions_equal_each_obstacles_own(monkeypatch, dtype, chunk, compiled):
    monkeypatch.setattr(environment, "_CONTAINS_CHUNK", chunk)
    monkeypatch.setattr(environment, "_COMPILED_PAIRS", 0 if compiled else 1 << 62)
    if compiled and environment._compiled() is None:
        pytest.skip("needs numba")
    for seed in range(8):
        obstacles = _world(seed) + [_Ring(center=(0.0, 0.0), radius=1.0)]
        xy = torch.rand(400, 3, 2, generator=torch.Generator().manual_seed(seed), dtype=dtype) * 8 - 4  # [400, 3, 2]
        edges = []  # points exactly on boundaries: the closed shapes' edges count
        for obs in obstacles[:6]:
            if isinstance(obs, Rect):
                edges += [(obs.xmin, obs.ymin), (obs.xmax, 0.5 * (obs.ymin + obs.ymax))]
            else:
                edges += [(obs.center[0] + obs.radius, obs.center[1]), (obs.center[0], obs.center[1] - obs.radius)]
        xy[: len(edges), 0] = torch.tensor(edges, dtype=dtype)
        xy[0, 1, 0] = float("nan")
        got = Environment(obstacles).in_collision(xy)
        assert torch.equal(got, _one_by_one(obstacles, xy))
    assert bool(Environment([_Ring(center=(0.0, 0.0), radius=1.0)]).in_collision(torch.zeros(1, 2)).item()) is False


def test_a_changed_obstacle_list_is_seen():
    env = Environment([Circle(center=(0.0, 0.0), radius=0.5)])
    p = torch.tensor([[2.0, 2.0]])
    assert not env.in_collision(p).item()
    env.obstacles.append(Rect(1.5, 1.5, 2.5, 2.5))  # the cache follows the list
    assert env.in_collision(p).item()
    assert env.in_collision(p, time=0.0).item()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_obstacles_away_from_the_points_are_dropped_without_changing_an_answer(monkeypatch, dtype):
    """A patch of points on a wide world (how a map policy senses): only obstacles meeting the points' box are
    tested, and every answer is still each obstacle's own, boundaries included."""
    monkeypatch.setattr(environment, "_PREFILTER_PAIRS", 0)
    monkeypatch.setattr(environment, "_COMPILED_PAIRS", 0)
    kept = []
    real = environment._near_box
    monkeypatch.setattr(environment, "_near_box", lambda *a: kept.append(real(*a)) or kept[-1])
    for seed in range(12):
        obstacles = _world(seed)
        gen = torch.Generator().manual_seed(seed)
        xy = (torch.rand(600, 2, generator=gen, dtype=dtype) - 0.5) * 1.5 + torch.tensor([0.4, -0.2], dtype=dtype)
        edges = []  # boundary points of obstacles that reach into the patch: the closed shapes' edges count
        for obs in obstacles:
            if isinstance(obs, Rect):
                edges.append((obs.xmin, obs.ymin))
            else:
                edges.append((obs.center[0] - obs.radius, obs.center[1]))
        edges = [e for e in edges if -0.35 <= e[0] <= 1.15 and -0.95 <= e[1] <= 0.55]
        if edges:
            xy[: len(edges)] = torch.tensor(edges, dtype=dtype)
        xy[-1] = float("nan")
        assert torch.equal(Environment(obstacles).in_collision(xy), _one_by_one(obstacles, xy))
    assert sum(len(c) + len(r) for c, r in kept) < sum(len(_world(s)) for s in range(12))  # some were dropped
