"""The cost floor's fast paths give the slow paths' answers: the compiled navigation cost
(:mod:`cuniform_torch.envs.cost_loops`) against the torch path of :class:`NavigationCost`, the sorted obstacle tables
against :meth:`Environment.visible`, and the map rollout's Dubins step against the torch step."""

from __future__ import annotations

import random

import pytest
import torch

import cuniform_torch.envs.costs as costs
from cuniform_torch.envs import Circle, Environment, NavigationCost, Rect

if costs._cost_loop() is None:
    pytest.skip("needs numba", allow_module_level=True)


def _world(seed: int, bounds: bool) -> Environment:
    rng = random.Random(seed)
    obstacles: list = []
    for _ in range(rng.randint(0, 30)):
        x, y = rng.uniform(-3, 3), rng.uniform(-3, 3)
        appear = rng.choice([0.0, 0.0, 1.0, 2.5, float("inf")])
        if rng.random() < 0.6:
            obstacles.append(Circle(center=(x, y), radius=rng.uniform(0.05, 0.8), appear_time=appear))
        else:
            obstacles.append(Rect(x, y, x + rng.uniform(0.05, 1.5), y + rng.uniform(0.05, 1.5), appear_time=appear))
    return Environment(obstacles, bounds=(-3.5, -3.0, 3.5, 3.0) if bounds else None)


def _rollouts(seed: int, n: int, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """``states [n, 13, 3]``: random walks from random starts (some cross the goal, the bounds, obstacles; one has a
    NaN, one an inf), ``actions [n, 12, 1]``."""
    gen = torch.Generator().manual_seed(seed)
    start = torch.rand(n, 1, 3, generator=gen, dtype=dtype) * 6 - 3
    steps = torch.randn(n, 12, 3, generator=gen, dtype=dtype) * 0.3
    states = torch.cat([start, start + steps.cumsum(dim=1)], dim=1)  # [n, 13, 3]
    states[0, 5, 0] = float("nan")
    states[1, 7, 1] = float("inf")
    states[2, 3, :2] = torch.tensor([0.5, -0.25], dtype=dtype)  # exactly on the goal: arrives at step 3
    return states, torch.zeros(n, 12, 1, dtype=dtype)


def _torch_path(monkeypatch, cost: NavigationCost, states, actions) -> torch.Tensor:
    with monkeypatch.context() as m:
        m.setattr(costs, "_cost_loop", lambda: None)
        return cost(states, actions)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("per_state", [False, True])
@pytest.mark.parametrize("stop_at_goal", [False, True])
def test_the_compiled_cost_is_the_torch_paths(monkeypatch, dtype, per_state, stop_at_goal):
    rtol = 1e-6 if dtype == torch.float32 else 1e-13  # the goal term's sum may add in another order
    for seed in range(10):
        env = _world(seed, bounds=seed % 2 == 0)
        states, actions = _rollouts(seed, 64, dtype)
        for time in (0.0, 1.0, 3.0, None):
            cost = NavigationCost(env, goal=(0.5, -0.25), goal_tolerance=0.3, collision_penalty=1e4, time=time,
                                  per_state=per_state, stop_at_goal=stop_at_goal)
            got, want = cost(states, actions), _torch_path(monkeypatch, cost, states, actions)
            assert got.dtype == dtype and got.shape == (64,)
            torch.testing.assert_close(got, want, rtol=rtol, atol=0.0, equal_nan=True)


def test_points_on_edges_and_the_bounds_count_as_the_torch_path_counts_them(monkeypatch):
    """Closed shapes and bounds: a point exactly on a disc's rim, a rectangle's side or the bounds' edge."""
    env = Environment([Circle(center=(1.0, 0.0), radius=0.5), Rect(-2.0, -1.0, -1.0, 1.0)], bounds=(-3.0, -2.0, 3.0, 2.0))
    edge = torch.tensor([[1.5, 0.0], [-1.0, 0.5], [3.0, 0.0], [0.0, -2.0], [3.0001, 0.0], [0.0, 0.0]])  # [6, 2]
    states = torch.zeros(6, 3, 3)
    states[:, 1, :2] = edge
    states[:, 2, :2] = edge
    cost = NavigationCost(env, goal=(9.0, 9.0), collision_penalty=1e3, per_state=True)
    got = cost(states, torch.zeros(6, 2, 1))
    torch.testing.assert_close(got, _torch_path(monkeypatch, cost, states, torch.zeros(6, 2, 1)), rtol=1e-6, atol=0.0)
    assert (got >= 2e3).tolist() == [True, True, False, False, True, False]  # both steps of the first two and the fifth


def test_obstacles_of_other_kinds_and_gradients_take_the_torch_path(monkeypatch):
    class Always:
        appear_time = 0.0

        def contains(self, xy):
            return torch.ones(xy.shape[:-1], dtype=torch.bool)

    states, actions = _rollouts(0, 8, torch.float32)
    cost = NavigationCost(Environment([Always()]), goal=(0.0, 0.0), collision_penalty=1e3)
    assert bool((cost(states, actions)[3:] >= 1e3).all())  # rows 0, 1 hold a NaN, an inf
    grad = states.clone().requires_grad_(True)
    free = NavigationCost(Environment([]), goal=(0.0, 0.0))
    free(grad, actions)[3:].sum().backward()  # the torch path: a gradient of the goal term
    assert grad.grad is not None and bool(grad.grad[3:].abs().sum() > 0)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_sorted_tables_are_the_visible_obstacles(dtype):
    for seed in range(10):
        env = _world(seed, bounds=False)
        for time in (0.0, 0.5, 1.0, 2.5, 100.0, None):
            circles, rects, others = env._visible_tables(time, dtype)
            seen = env.visible(time)
            want_c = sorted((o.center[0], o.center[1], o.radius * o.radius) for o in seen if type(o) is Circle)
            want_r = sorted((o.xmin, o.ymin, o.xmax, o.ymax) for o in seen if type(o) is Rect)
            assert circles.dtype == dtype and rects.dtype == dtype and others == []
            assert sorted(map(tuple, circles.tolist())) == [tuple(torch.tensor(c, dtype=dtype).tolist()) for c in want_c]
            assert sorted(map(tuple, rects.tolist())) == [tuple(torch.tensor(r, dtype=dtype).tolist()) for r in want_r]
    env = Environment([Circle(center=(0.0, 0.0), radius=0.5)])
    assert env._visible_tables(None, torch.float32)[0].shape == (1, 3)
    env.obstacles.append(Circle(center=(2.0, 0.0), radius=0.5, appear_time=1.0))  # the cache follows the list
    assert env._visible_tables(None, torch.float32)[0].shape == (2, 3)
    assert env._visible_tables(0.5, torch.float32)[0].shape == (1, 3)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_a_disc_that_only_touches_the_points_box_is_kept(monkeypatch, dtype):
    """The prefilter drops discs away from the points' bounding box; one that reaches it only at its rim (the
    rollout stands on the rim, so the box is that point) must stay, whatever the rounding of r^2."""
    for radius in (0.5, 0.3, 0.7071, 1.1):
        env = Environment([Circle(center=(0.0, 0.0), radius=radius), Circle(center=(5.0, 5.0), radius=0.1)])
        states = torch.zeros(2, 4, 3, dtype=dtype)
        states[:, 1:, 0] = radius  # [2, 3] every step on the rim (exactly, as the torch path rounds it)
        cost = NavigationCost(env, goal=(9.0, 9.0), collision_penalty=1e3, per_state=True)
        got = cost(states, torch.zeros(2, 3, 1, dtype=dtype))
        want = _torch_path(monkeypatch, cost, states, torch.zeros(2, 3, 1, dtype=dtype))
        torch.testing.assert_close(got, want, rtol=1e-6, atol=0.0)


def test_the_map_rollouts_dubins_step_is_the_fmod_step():
    """The map kernel's step (:func:`dubins_advance`, now on the shared fmod-free wrap and sincos polynomial):
    headings bit for bit ``wrap(theta + rate dt)`` with fmod, for headings all round the circle and turn rates small
    and large (sums beyond [-2 pi, 4 pi) take the fmod branch); positions move by ``speed dt (cos, sin)``."""
    import numpy as np

    from cuniform_torch.systems.dubins_loops import dubins_advance

    pi, two_pi, dt, speed = np.float32(np.pi), np.float32(2 * np.pi), np.float32(0.2), np.float32(0.5)
    heads = np.linspace(-np.pi, np.pi, 2001, dtype=np.float32)[:-1]
    rates = np.float32([-50.0, -1.5, -0.5, 0.0, 0.5, 1.5, 50.0])
    head, rate = (a.ravel() for a in np.meshgrid(heads, rates))
    states = np.zeros((2, 3, head.shape[0]), dtype=np.float32)  # [T+1, 3, N]
    states[0, 0] = np.linspace(-1, 1, head.shape[0], dtype=np.float32)
    states[0, 2] = head
    for i in range(head.shape[0]):
        dubins_advance(states, 0, i, rate[i], dt, speed, pi, two_pi)
    a = rate * dt + head + pi  # float32, as the step rounds it
    m = np.fmod(a, two_pi)
    np.testing.assert_array_equal(states[1, 2], np.where(m < 0, m + two_pi, m) - pi)
    assert (np.abs(a) > 4 * np.pi).any() and (a < -2 * np.pi).any()
    th = states[1, 2].astype(np.float64)
    np.testing.assert_allclose(states[1, 0], states[0, 0] + 0.1 * np.cos(th), atol=2e-7, rtol=0)
    np.testing.assert_allclose(states[1, 1], 0.1 * np.sin(th), atol=2e-7, rtol=0)


def test_the_map_kernels_bilinear_read_is_grid_samples():
    """The map kernel's probe read (taps and weights found once for all channels) against ``grid_sample``
    (``align_corners=False``, zero padding), at points all over a random feature map and off its edges."""
    import numpy as np

    from cuniform_torch.maps.rollout_loops import read_channels

    gen = torch.Generator().manual_seed(0)
    C, H, W, n = 4, 9, 13, 3000
    fmap = torch.randn(C, H, W, generator=gen)  # [C, H, W]
    ix = torch.rand(n, generator=gen) * (W + 3) - 2.0  # [n] columns, some off the map
    iy = torch.rand(n, generator=gen) * (H + 3) - 2.0  # [n] rows
    feat = np.zeros((n, C + 2), dtype=np.float32)
    fmap_np = fmap.numpy()
    for i in range(n):
        read_channels(fmap_np, np.float32(ix[i]), np.float32(iy[i]), feat, i, 2)
    grid = torch.stack(((2 * ix + 1) / W - 1, (2 * iy + 1) / H - 1), dim=1).view(1, 1, n, 2)  # [1, 1, n, 2]
    want = torch.nn.functional.grid_sample(fmap[None], grid, mode="bilinear", padding_mode="zeros",
                                           align_corners=False)[0, :, 0].T  # [n, C]
    torch.testing.assert_close(torch.from_numpy(feat[:, 2:]), want, atol=2e-5, rtol=1e-5)
    assert (feat[:, :2] == 0).all()  # only its own columns written
