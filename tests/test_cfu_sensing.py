"""CFU-MPPI's sensing by one compiled loop (cuniform_torch.maps.sensing_loops) against the torch path it replaces.

Both must read the same cells, bit for bit: BARN's field of discs, rectangles, workspace bounds, poses off the
map and not finite, obstacles that appear later, float64, a limited range, and many poses at once.
"""

from __future__ import annotations

import math

import pytest
import torch

from cuniform_torch.envs import Circle, Environment, Rect
from cuniform_torch.maps import sensing
from cuniform_torch.maps.encoder import PatchSpec
from cuniform_torch.maps.sensing import sense_patch
from precompute.worlds.barn import load_barn
from precompute.worlds.robot import NAV_ROBOT

pytestmark = pytest.mark.skipif(sensing._loop() is None, reason="needs numba")

SPEC = PatchSpec((72, 72), 0.05, (-1.8, -1.8))


def _poses(n: int, seed: int, lo=(-5.0, 1.0), hi=(1.0, 15.0)) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    u = torch.rand(n, 3, generator=g)
    return torch.stack((lo[0] + u[:, 0] * (hi[0] - lo[0]), lo[1] + u[:, 1] * (hi[1] - lo[1]),
                        (u[:, 2] - 0.5) * 2 * math.pi), dim=1)


def _mixed() -> Environment:
    """Discs and rectangles that appear at different times, in bounds; rectangles touching the discs."""
    obstacles = [Circle((0.3, 0.2), 0.25), Circle((-0.6, 0.9), 0.4, appear_time=2.0), Circle((1.1, -0.7), 0.05),
                 Rect(0.5, 0.5, 0.9, 1.6), Rect(-1.5, -1.2, -1.0, -0.2, appear_time=1.0), Rect(0.0, -2.0, 0.05, 2.0)]
    return Environment(obstacles, bounds=(-2.0, -1.5, 1.8, 2.2))


def _same(world, poses, **kw) -> torch.Tensor:
    fast = sense_patch(world, poses, SPEC, compiled=True, **kw)
    slow = sense_patch(world, poses, SPEC, compiled=False, **kw)
    assert fast.shape == slow.shape and fast.dtype == torch.bool
    assert torch.equal(fast, slow), f"{int((fast != slow).sum())} cells differ"
    return fast


def test_barn_patches_are_the_torch_paths():
    env = load_barn()[0].environment(NAV_ROBOT.radius)
    seen = _same(env, _poses(48, 0))
    assert 0.02 < float(seen.float().mean()) < 0.5  # patches with obstacles in them


@pytest.mark.parametrize("time", [None, 0.0, 1.5, 3.0])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_discs_rectangles_bounds_and_times(time, dtype):
    poses = _poses(24, 1, lo=(-2.5, -2.0), hi=(2.5, 2.5)).to(dtype)
    poses[3] = torch.tensor([0.3, 0.2, 0.0], dtype=dtype)  # at a disc's centre
    seen = _same(_mixed(), poses, time=time)
    assert bool(seen.any()) and not bool(seen.all())


def test_one_pose_a_limited_range_and_poses_that_are_not_finite():
    world = _mixed()
    _same(world, torch.tensor([0.1, -0.3, 0.7]), max_range=1.0)
    poses = _poses(4, 2, lo=(-1.0, -1.0), hi=(1.0, 1.0))
    poses[1, 0], poses[2, 2] = math.nan, math.inf
    seen = _same(world, poses)
    assert bool(seen[1].all()) and bool(seen[2].all())  # no finite cell: all count as collisions
    _same(Environment([]), poses)  # nothing to hit but the non-finite cells


def test_other_obstacles_and_grids_take_the_torch_path():
    class Blob(Circle):  # a subclass keeps its own contains: not in the compiled tables
        pass

    env = Environment([Blob((0.0, 0.5), 0.3)])
    assert sensing._sense_compiled(env, _poses(2, 3), sensing.patch_centres(SPEC), None) is None
    _same(env, _poses(2, 3, lo=(-0.5, -0.5), hi=(0.5, 0.5)))


def test_a_world_that_changes_is_sensed_anew():
    world = _mixed()
    pose = torch.tensor([[0.2, 0.1, 0.4]])
    before = _same(world, pose)
    world.obstacles.append(Circle((0.7, 0.1), 0.3))  # a new obstacle ahead
    added = _same(world, pose)
    world.bounds = (-1.0, -1.0, 1.0, 1.0)  # a smaller workspace
    bounded = _same(world, pose)
    assert int(added.sum()) > int(before.sum()) and int(bounded.sum()) > int(added.sum())
