"""Environments: obstacle containment and signed distance, visibility and bounds, the navigation cost, and the
closed-loop simulator with hand-written controllers on the Dubins car."""

from __future__ import annotations

import math

import pytest
import torch

from cuniform_torch.envs import (
    Circle,
    Environment,
    NavigationCost,
    OccupancyGrid,
    Polygon,
    Rect,
    collision_mask,
    goal_cost,
    simulate,
    u_shape,
)
from cuniform_torch.systems import Dubins, wrap_angle

L_SHAPE = [(0, 0), (2, 0), (2, 1), (1, 1), (1, 2), (0, 2)]  # non-convex: the square [1,2]x[1,2] is cut out


def _xy(*points, dtype=torch.float32):
    return torch.tensor(points, dtype=dtype)


# ------------------------------------------------------------------------------------------------ shapes

def test_circle_contains_and_signed_distance():
    c = Circle((1.0, -1.0), 0.5)
    xy = _xy((1.0, -1.0), (1.5, -1.0), (1.6, -1.0), (4.0, 3.0))
    assert c.contains(xy).tolist() == [True, True, False, False]  # closed disc: the boundary point is inside
    torch.testing.assert_close(c.signed_distance(xy), _xy(-0.5, 0.0, 0.1, 4.5))
    assert c.contains(torch.zeros(4, 5, 2)).shape == (4, 5)


def test_rect_contains_and_signed_distance():
    r = Rect(0.0, 0.0, 2.0, 1.0)
    xy = _xy((1.0, 0.5), (2.0, 1.0), (3.0, 2.0), (1.0, 3.0), (0.2, 0.5))
    assert r.contains(xy).tolist() == [True, True, False, False, True]
    torch.testing.assert_close(r.signed_distance(xy), _xy(-0.5, 0.0, math.sqrt(2.0), 2.0, -0.2))


@pytest.mark.parametrize("reverse", [False, True])
def test_nonconvex_polygon_by_hand(reverse):
    poly = Polygon(L_SHAPE[::-1] if reverse else L_SHAPE)
    xy = _xy((0.5, 0.5), (1.5, 0.5), (0.5, 1.5), (1.5, 1.5), (3.0, 0.5), (-0.5, 1.0), (1.0, 2.5))
    assert poly.contains(xy).tolist() == [True, True, True, False, False, False, False]
    torch.testing.assert_close(poly.signed_distance(xy[:5]), _xy(-0.5, -0.5, -0.5, 0.5, 1.0))
    assert poly.area == pytest.approx(3.0)


def test_polygon_of_a_rectangle_matches_rect():
    rect = Rect(-1.0, -0.5, 2.0, 1.5)
    poly = Polygon([(-1.0, -0.5), (2.0, -0.5), (2.0, 1.5), (-1.0, 1.5), (-1.0, -0.5)])  # closed ring accepted
    assert poly.vertices.shape == (4, 2)
    xy = torch.randn(2000, 2, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 2.0
    assert torch.equal(poly.contains(xy), rect.contains(xy))
    torch.testing.assert_close(poly.signed_distance(xy), rect.signed_distance(xy))


def test_polygon_containment_matches_matplotlib():
    mpath = pytest.importorskip("matplotlib.path")
    gen = torch.Generator().manual_seed(1)
    k = 24
    angle = torch.arange(k, dtype=torch.float64) * (2 * math.pi / k)
    radius = torch.where(torch.arange(k) % 2 == 0, 2.0, 0.7) + 0.2 * torch.rand(k, generator=gen, dtype=torch.float64)
    star = torch.stack((radius * torch.cos(angle), radius * torch.sin(angle)), dim=1)  # non-convex star
    xy = (torch.rand(5000, 2, generator=gen, dtype=torch.float64) - 0.5) * 5.0
    for poly in (Polygon(star), u_shape((0.3, -0.2), 3.0, 2.0, 0.4, opening="-y")):
        ref = mpath.Path(poly.vertices.numpy()).contains_points(xy.numpy())
        assert poly.contains(xy).tolist() == ref.tolist()
        assert poly.contains(xy.float()).tolist() == ref.tolist()


@pytest.mark.parametrize("opening", ["+x", "-x", "+y", "-y"])
def test_u_shape_pocket_is_free_and_walls_are_occupied(opening):
    # local frame (opening +x): depth 2 along x, width 3 along y, walls 0.25 thick, centred at (5, 1)
    u = u_shape((5.0, 1.0), width=3.0, depth=2.0, thickness=0.25, opening=opening)
    turn = {
        "+x": lambda x, y: (x, y), "+y": lambda x, y: (-y, x), "-x": lambda x, y: (-x, -y), "-y": lambda x, y: (y, -x),
    }
    local = {
        "pocket": (0.0, 0.0), "pocket mouth": (0.9, 0.5), "base wall": (-0.9, 0.0), "side wall": (0.0, 1.4),
        "other side wall": (0.5, -1.4), "outside, behind": (-1.5, 0.0), "outside, beside": (0.0, 2.0),
    }
    xy = _xy(*[(5.0 + turn[opening](*p)[0], 1.0 + turn[opening](*p)[1]) for p in local.values()])
    inside = dict(zip(local, u.contains(xy).tolist()))
    assert inside == {
        "pocket": False, "pocket mouth": False, "base wall": True, "side wall": True,
        "other side wall": True, "outside, behind": False, "outside, beside": False,
    }
    assert u.area == pytest.approx(2.0 * 3.0 - 1.75 * 2.5)


def test_occupancy_grid_cells():
    occ = torch.zeros(3, 4, dtype=torch.bool)
    occ[1, 2] = True  # covers x in [-1 + 2*0.5, -1 + 3*0.5) = [0, 0.5), y in [0.5 + 0.5, 0.5 + 1.0) = [1.0, 1.5)
    grid = OccupancyGrid(occ, origin=(-1.0, 0.5), resolution=0.5)
    xy = _xy((0.25, 1.25), (0.0, 1.0), (0.5, 1.25), (0.25, 1.5), (-0.01, 1.25), (5.0, 1.25), (-2.0, -2.0),
             (float("nan"), 1.25))
    assert grid.contains(xy).tolist() == [True, True, False, False, False, False, False, False]
    i, j, inside = grid.cell_index(_xy((0.25, 1.25), (-0.99, 0.51), (100.0, 0.0)))
    assert i.tolist()[:2] == [1, 0] and j.tolist()[:2] == [2, 0] and inside.tolist() == [True, True, False]
    full = OccupancyGrid(torch.ones(2, 2, dtype=torch.bool), resolution=1.0)
    assert full.contains(_xy((1.999, 1.999), (2.0, 0.5))).tolist() == [True, False]


def test_appear_time_visibility_and_bounds():
    env = Environment([Circle((2.0, 0.0), 0.5), Rect(-1.0, 2.0, 1.0, 3.0, appear_time=1.0)], bounds=(-5, -5, 5, 5))
    xy = _xy((2.0, 0.0), (0.0, 2.5), (0.0, 0.0), (5.0, 5.0), (5.01, 0.0), (0.0, -6.0), (float("nan"), 0.0))
    assert env.in_collision(xy).tolist() == [True, True, False, False, True, True, True]  # truth: all obstacles
    assert env.in_collision(xy, time=0.5).tolist() == [True, False, False, False, True, True, True]
    assert env.in_collision(xy, time=1.0).tolist() == [True, True, False, False, True, True, True]
    assert len(env.visible(0.0)) == 1 and len(env.visible(None)) == 2
    assert Environment([]).in_collision(torch.zeros(3, 7, 2, dtype=torch.float64)).shape == (3, 7)


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: Circle((0, 0), 0.0), "radius"),
        (lambda: Circle((0, 0), -1.0), "radius"),
        (lambda: Circle((0, float("nan")), 1.0), "center"),
        (lambda: Circle((0, 0), 1.0, appear_time=-1.0), "appear_time"),
        (lambda: Rect(1.0, 0.0, 1.0, 2.0), "xmin < xmax"),
        (lambda: Rect(0.0, 2.0, 1.0, 1.0), "ymin < ymax"),
        (lambda: Polygon([(0, 0), (1, 0)]), "at least 3"),
        (lambda: Polygon([(0, 0, 0), (1, 0, 0), (0, 1, 0)]), r"\[V, 2\]"),
        (lambda: Polygon([(0, 0), (1, 1), (1, 0), (0, 1)]), "not simple"),
        (lambda: Polygon([(0, 0), (1, 0), (1, 0), (0, 1)]), "equal"),
        (lambda: Polygon([(0, 0), (1, 0), (2, 0)]), "zero area"),
        (lambda: OccupancyGrid(torch.zeros(2, 2)), "torch.bool"),
        (lambda: OccupancyGrid(torch.zeros(2, dtype=torch.bool)), r"\[H, W\]"),
        (lambda: OccupancyGrid(torch.zeros(2, 2, dtype=torch.bool), resolution=0.0), "resolution"),
        (lambda: u_shape((0, 0), 1.0, 2.0, 0.5), "twice the thickness"),
        (lambda: u_shape((0, 0), 2.0, 0.4, 0.5), "depth"),
        (lambda: u_shape((0, 0), 2.0, 2.0, 0.2, opening="up"), r"\+x, -x, \+y, -y"),
        (lambda: Environment([Circle((0, 0), 1.0)], bounds=(0, 0, -1, 1)), "xmin < xmax"),
        (lambda: Environment([Circle((0, 0), 1.0)], bounds=(0, 0, 1)), "bounds"),
        (lambda: Environment(["wall"]), "contains"),
        (lambda: Circle((0, 0), 1.0).contains(torch.zeros(4, 3)), r"\[\.\.\., 2\]"),
        (lambda: Circle((0, 0), 1.0).contains(torch.zeros(4, 2, dtype=torch.int64)), "floating-point"),
        (lambda: Environment([]).in_collision(torch.zeros(2, 2), time=float("nan")), "time"),
    ],
)
def test_bad_shapes_raise(make, match):
    with pytest.raises(ValueError, match=match):
        make()


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_shapes_agree_on_cpu_and_gpu():
    occ = torch.rand(20, 30, generator=torch.Generator().manual_seed(2)) < 0.3
    env = Environment([Circle((1, 1), 0.5), Rect(-2, -2, -1, 0), Polygon(L_SHAPE), u_shape((3, -2), 2, 2, 0.3),
                       OccupancyGrid(occ, origin=(-3.0, -3.0), resolution=0.2)], bounds=(-4, -4, 4, 4))
    xy = (torch.rand(10000, 2, generator=torch.Generator().manual_seed(3)) - 0.5) * 9.0
    gpu_env = Environment([o.to("cuda") if isinstance(o, OccupancyGrid) else o for o in env.obstacles], env.bounds)
    assert torch.equal(env.in_collision(xy), gpu_env.in_collision(xy.cuda()).cpu())
    with pytest.raises(ValueError, match="grid is on"):
        env.in_collision(xy.cuda())


# ------------------------------------------------------------------------------------------------ cost

def _states(*rollouts, dtype=torch.float32):
    """Rollouts of (x, y) points -> ``[N, T+1, 3]`` states with heading 0."""
    xy = torch.tensor(rollouts, dtype=dtype)  # [N, T+1, 2]
    return torch.cat((xy, torch.zeros(*xy.shape[:2], 1, dtype=dtype)), dim=2)


def test_goal_cost_stops_at_the_goal():
    states = _states(
        [(5, 5), (1, 0), (0.1, 0), (1, 0)],  # reaches the goal at step 2: 1 + 0 + 0 (not + 1)
        [(5, 5), (2, 0), (1, 0), (3, 0)],  # never within 0.2: 4 + 1 + 9
        [(0, 0), (0, 0.1), (3, 0), (3, 0)],  # within the tolerance at step 1: zero throughout
    )
    torch.testing.assert_close(goal_cost(states, (0.0, 0.0), 0.2), torch.tensor([1.0, 14.0, 0.0]))
    torch.testing.assert_close(goal_cost(states, torch.zeros(2), 0.0), torch.tensor([2.01, 14.0, 18.01]))


def test_navigation_cost_collision_penalty_and_time():
    wall = Rect(2.5, -1.0, 3.5, 1.0, appear_time=1.0)
    env = Environment([wall])
    states = _states(
        [(0, 0), (1, 0), (2, 0), (3, 0)],  # drives into the wall at step 3
        [(3, 0), (2, 0), (1, 0), (0, 0)],  # only the start is in the wall: not penalized
    )
    actions = torch.zeros(2, 3, 1)
    cost = NavigationCost(env, goal=(0.0, 0.0), goal_tolerance=0.2, collision_penalty=1e6)
    base = goal_cost(states, (0.0, 0.0), 0.2)
    torch.testing.assert_close(cost(states, actions), base)  # time 0: the wall is not sensed yet
    cost.set_time(1.0)
    torch.testing.assert_close(cost(states, actions), base + torch.tensor([1e6, 0.0]))
    assert collision_mask(states, env, None).tolist() == [True, False]
    assert collision_mask(states, env, 0.99).tolist() == [False, False]
    cost.set_time(None)
    every = cost(states[:1].expand(5, -1, -1), actions[:1].expand(5, -1, -1))
    assert bool(torch.isfinite(every).all())
    assert bool(torch.isfinite(torch.softmax(-every / 1.0, dim=0)).all())  # all rollouts colliding: no NaN weights


@pytest.mark.parametrize("n", [1, 64])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_navigation_cost_batched_shapes(n, dtype):
    env = Environment([Circle((1.0, 0.0), 0.3)], bounds=(-3, -3, 3, 3))
    gen = torch.Generator().manual_seed(4)
    states = torch.randn(n, 11, 3, generator=gen, dtype=dtype)
    cost = NavigationCost(env, goal=(2.0, 0.0))
    out = cost(states, torch.zeros(n, 10, 1, dtype=dtype))
    assert out.shape == (n,) and out.dtype == dtype and bool(torch.isfinite(out).all())
    # a plain loop over rollouts gives the same numbers
    for k in range(n):
        d2 = ((states[k, 1:, :2] - torch.tensor([2.0, 0.0], dtype=dtype)) ** 2).sum(dim=1)
        total = 0.0
        for t in range(10):
            if float(d2[t]) <= 0.2**2:
                break
            total += float(d2[t])
        hit = bool(env.in_collision(states[k, 1:, :2]).any())
        assert float(out[k]) == pytest.approx(total + 1e6 * hit, rel=1e-5)
    assert cost(states[:, :1], torch.zeros(n, 0, 1, dtype=dtype)).tolist() == [0.0] * n  # T = 0


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda c: c(torch.zeros(4, 3), torch.zeros(4, 2, 1)), r"\[N, T\+1, d\]"),
        (lambda c: c(torch.zeros(4, 3, 1), torch.zeros(4, 2, 1)), "d >= 2"),
        (lambda c: c(torch.zeros(4, 3, 3), torch.zeros(4, 3, 1)), r"actions must have shape \[4, 2, q\]"),
        (lambda c: c(torch.zeros(4, 3, 3, dtype=torch.int64), torch.zeros(4, 2, 1)), "floating-point"),
        (lambda c: goal_cost(torch.zeros(4, 3, 3), (0.0, 0.0), -0.1), "goal_tolerance"),
        (lambda c: goal_cost(torch.zeros(4, 3, 3), (0.0,), 0.1), "goal"),
        (lambda c: NavigationCost(c.env, goal=(0, 0), collision_penalty=float("inf")), "collision_penalty"),
        (lambda c: NavigationCost("env", goal=(0, 0)), "Environment"),
        (lambda c: c.set_time(float("nan")), "time"),
    ],
)
def test_bad_cost_input_raises(call, match):
    cost = NavigationCost(Environment([]), goal=(1.0, 1.0))
    with pytest.raises(ValueError, match=match):
        call(cost)


# ------------------------------------------------------------------------------------------------ simulate

class HeadingController:
    """Turn towards the goal: omega = clamp(k * heading error, -pi/4, pi/4)."""

    def __init__(self, goal, gain=2.0):
        self.goal, self.gain, self.resets = goal, gain, 0

    def reset(self):
        self.resets += 1

    def command(self, state):
        desired = math.atan2(self.goal[1] - float(state[1]), self.goal[0] - float(state[0]))
        error = float(wrap_angle(torch.tensor(desired - float(state[2]))))
        omega = max(-math.pi / 4, min(math.pi / 4, self.gain * error))
        return state.new_tensor([omega])


class Straight:
    def command(self, state):
        return state.new_zeros(1)


class TimeRecorder:
    def __init__(self):
        self.times = []

    def set_time(self, t):
        self.times.append(t)


def _sim(**overrides):
    args = dict(system=Dubins(), controller=HeadingController((2.0, 0.0)), x0=torch.zeros(3), env=Environment([]),
                goal=(2.0, 0.0), goal_tolerance=0.2, time_limit=5.0)
    args.update(overrides)
    return simulate(**args)


@pytest.mark.parametrize("goal", [(2.0, 0.0), (2.0, 1.0)])
def test_simulate_reaches_the_goal(goal):
    controller = HeadingController(goal)
    recorder = TimeRecorder()
    res = _sim(controller=controller, goal=goal, cost=recorder)
    assert res.outcome == "goal" and res.success and controller.resets == 1
    S = res.steps
    assert res.path.shape == (S + 1, 3) and res.controls.shape == (S, 1)
    assert math.dist(res.path[-1, :2].tolist(), goal) <= 0.2 < math.dist(res.path[-2, :2].tolist(), goal)
    assert res.time == pytest.approx(S * 0.2)
    assert res.path_length == pytest.approx(S * 0.2, rel=1e-5)  # unit speed, dt 0.2
    assert recorder.times == pytest.approx([0.2 * k for k in range(S)])
    if goal == (2.0, 0.0):
        assert S in (9, 10)  # straight ahead: x = 0.2 k


def test_simulate_collides_with_a_wall_ahead():
    wall = Rect(1.0, -1.0, 1.5, 1.0, appear_time=math.inf)  # never sensed, but physically there
    res = _sim(controller=Straight(), env=Environment([wall]), goal=(3.0, 0.0))
    assert res.outcome == "collision" and not res.success
    assert bool(wall.contains(res.path[-1, :2])) and not bool(wall.contains(res.path[-2, :2]))
    out_of_bounds = _sim(controller=Straight(), env=Environment([], bounds=(-1, -1, 0.5, 1)), goal=(3.0, 0.0))
    assert out_of_bounds.outcome == "collision" and out_of_bounds.steps == 3


def test_simulate_times_out_and_record_false():
    res = _sim(goal=(10.0, 0.0), controller=HeadingController((10.0, 0.0)), time_limit=1.0)
    assert res.outcome == "timeout" and res.steps == 5 and res.time == pytest.approx(1.0)
    assert res.path[-1, 0].item() == pytest.approx(1.0)
    lean = _sim(goal=(10.0, 0.0), controller=HeadingController((10.0, 0.0)), time_limit=1.0, record=False)
    assert lean.outcome == res.outcome and lean.steps == res.steps and lean.path_length == pytest.approx(1.0)
    assert lean.path.shape == (2, 3) and lean.controls.shape == (0, 1)
    torch.testing.assert_close(lean.path[-1], res.path[-1])


def test_simulate_start_at_goal_and_float64():
    res = _sim(x0=torch.tensor([1.9, 0.0, 0.0]))
    assert res.outcome == "goal" and res.steps == 0 and res.path.shape == (1, 3) and res.controls.shape == (0, 1)
    res64 = _sim(x0=torch.zeros(3, dtype=torch.float64))
    assert res64.outcome == "goal" and res64.path.dtype == torch.float64


class BadShape:
    def command(self, state):
        return state.new_zeros(1, 1)


class WrongDtype:
    def command(self, state):
        return torch.zeros(1, dtype=torch.float64)


class NaNControl:
    def command(self, state):
        return state.new_tensor([float("nan")])


@pytest.mark.parametrize(
    "overrides, match",
    [
        (dict(env=Environment([Circle((0.0, 0.0), 0.5)])), "in collision"),
        (dict(env=Environment([], bounds=(1, 1, 2, 2))), "in collision"),
        (dict(x0=torch.tensor([float("nan"), 0.0, 0.0])), "NaN"),
        (dict(x0=torch.zeros(2)), r"shape \[3\]"),
        (dict(x0=torch.zeros(1, 3)), r"shape \[3\]"),
        (dict(x0=torch.zeros(3, dtype=torch.int64)), "floating-point"),
        (dict(time_limit=0.0), "time_limit"),
        (dict(goal_tolerance=-1.0), "goal_tolerance"),
        (dict(goal=(1.0, float("inf"))), "goal"),
        (dict(controller=object()), "command"),
        (dict(controller=BadShape()), r"\[q\] tensor"),
        (dict(controller=WrongDtype()), "torch.float64"),
        (dict(controller=NaNControl()), "non-finite"),
        (dict(cost=object()), "set_time"),
        (dict(env=[Circle((5.0, 5.0), 1.0)]), "Environment"),
    ],
)
def test_bad_simulate_input_raises(overrides, match):
    with pytest.raises(ValueError, match=match):
        _sim(**overrides)


def test_navigation_cost_stop_at_goal_ends_the_collision_term_at_the_goal():
    """Collisions after a rollout's first arrival at the goal are not charged (the run would have ended there);
    collisions before it, and in the arriving state itself, are."""
    env = Environment([Circle((1.5, 0.0), 0.25), Circle((0.5, 1.0), 0.25)])  # behind the goal; on row 2's way
    xs = torch.linspace(0.0, 2.0, 11)  # steps of 0.2 m along +x
    rows = [torch.stack((xs, torch.full((11,), y), torch.zeros(11)), 1) for y in (0.0, 1.0, 3.0)]
    states = torch.stack(rows)  # [3, 11, 3]: through the goal then the circle; a circle, no goal; free
    actions = torch.zeros(3, 10, 1)
    goal = (1.0, 0.0)
    kw = dict(goal_tolerance=0.1, collision_penalty=100.0, per_state=True)
    plain = NavigationCost(env, goal, **kw)(states, actions)
    free = NavigationCost(Environment([]), goal, **kw)(states, actions)
    ends = NavigationCost(env, goal, stop_at_goal=True, **kw)(states, actions)
    assert plain - free == pytest.approx(torch.tensor([200.0, 200.0, 0.0]))  # x = 1.4, 1.6 / x = 0.4, 0.6
    assert ends - free == pytest.approx(torch.tensor([0.0, 200.0, 0.0]))  # row 0 arrives at x = 1.0 first
    assert NavigationCost(env, goal, stop_at_goal=False, **kw)(states, actions) == pytest.approx(plain)
    once = NavigationCost(env, goal, goal_tolerance=0.1, collision_penalty=100.0, stop_at_goal=True)(states, actions)
    assert once - free == pytest.approx(torch.tensor([0.0, 100.0, 0.0]))
    # the arriving state itself still counts: a goal inside an obstacle
    inside = NavigationCost(Environment([Circle((1.0, 0.0), 0.05)]), goal, stop_at_goal=True, **kw)(states, actions)
    assert inside - free == pytest.approx(torch.tensor([100.0, 0.0, 0.0]))
    torch.manual_seed(0)
    rnd = torch.randn(64, 11, 3) * 2  # no arrival within 0.01 m: the two costs agree
    a = torch.zeros(64, 10, 1)
    assert NavigationCost(env, (9.0, 9.0), goal_tolerance=0.01, per_state=True, stop_at_goal=True)(rnd, a) == pytest.approx(
        NavigationCost(env, (9.0, 9.0), goal_tolerance=0.01, per_state=True)(rnd, a))
    with pytest.raises(ValueError):
        NavigationCost(env, goal, stop_at_goal=True)(states, torch.zeros(3, 9, 1))


    with pytest.raises(ValueError, match=r"NavigationCost: stop_at_goal must be a bool, got 1"):
        NavigationCost(env, goal, stop_at_goal=1)
