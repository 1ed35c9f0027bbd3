"""The benchmark's cost raster (:func:`eval.navigate.episode.rasterize`) marks exactly the cells that testing every
cell centre against every obstacle marks: circles, rects, boxes at the map's edge, and chunks of boxes."""

from __future__ import annotations

import math

import numpy as np
import pytest

import eval.navigate.episode as episode
from cuniform_torch.envs import Circle, Environment, Rect
from precompute.worlds.barn import load_barn
from precompute.worlds.geometry import clearance
from precompute.worlds.tasks import barn_task


def _brute_force(environment: Environment, h: float) -> np.ndarray:
    """Every cell centre's clearance to every obstacle: the definition the raster must match, ``[H, W]``."""
    xmin, ymin, xmax, ymax = environment.bounds
    W, H = math.ceil((xmax - xmin) / h), math.ceil((ymax - ymin) / h)
    gx, gy = np.meshgrid(xmin + h * (np.arange(W) + 0.5), ymin + h * (np.arange(H) + 0.5))
    d = clearance(Environment(environment.obstacles), np.stack((gx.ravel(), gy.ravel()), axis=1))
    return (d < h * math.sqrt(0.5)).reshape(H, W)


def _marked(environment: Environment, h: float) -> np.ndarray:
    return episode.rasterize(environment, h).obstacles[0].occupied.numpy()  # [H, W]


@pytest.mark.parametrize("chunk", [1 << 22, 7])  # one chunk per kind, or many small ones
def test_raster_equals_the_brute_force_definition(monkeypatch, chunk):
    monkeypatch.setattr(episode, "_RASTER_CHUNK", chunk)
    task = barn_task(load_barn()[0], robot_radius=0.2)
    obstacles = [*task.environment.obstacles[:40],
                 Rect(-1.0, 2.0, 0.5, 2.3),  # a wall
                 Rect(-9.0, -9.0, -5.9, 3.0),  # crosses the map's lower-left edge
                 Circle(center=(1.45, 14.9), radius=0.3)]  # crosses the upper-right corner
    env = Environment(obstacles, bounds=task.environment.bounds)
    for h in (0.05, 0.013):
        expected = _brute_force(env, h)
        assert expected.any() and not expected.all()
        np.testing.assert_array_equal(_marked(env, h), expected)


def test_raster_of_an_empty_map_is_free():
    env = Environment([], bounds=(0.0, 0.0, 1.0, 2.0))
    assert not _marked(env, 0.1).any()
