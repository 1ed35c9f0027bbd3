"""The benchmark's cost-to-go (eval.navigate.cost_to_go, navigate --cost-to-go): the geodesic distance is the straight
line in the open and the way round a wall, recomputed only when the sensed obstacles change; the cost uses it;
with it MPPI gets through the offset gaps where the straight-line cost leaves it at the wall."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from test_nav_replay import ROBOT

from cuniform_torch.envs import Environment, NavigationCost, Rect
from eval.navigate.cost_to_go import UNREACHABLE, CostToGo, geodesic_distance
from eval.navigate.episode import NavContext, NavJob, run_nav_episode
from precompute.worlds.tasks import make_tasks

BOX = (0.0, 0.0, 10.0, 10.0)
GOAL = (9.05, 5.05)


def test_in_the_open_it_is_the_straight_line_within_the_grid_metric():
    field = CostToGo(BOX, GOAL, resolution=0.1)
    field.update(Environment([], bounds=BOX))
    pts = torch.tensor([[1.05, 5.05], [1.05, 1.05], [5.05, 9.05]])
    straight = torch.linalg.vector_norm(pts - torch.tensor(GOAL), dim=1)
    got = field(pts)
    assert torch.all(got >= straight - 1e-4) and torch.all(got <= straight * 1.0824 + 0.1)  # octile <= 1.0824 x


def test_a_wall_between_makes_it_the_way_round():
    wall = Rect(4.5, 0.0, 5.5, 8.0)  # a wall from the floor up to y = 8, the gap above it
    field = CostToGo(BOX, GOAL, resolution=0.1)
    field.update(Environment([wall], bounds=BOX))
    start = torch.tensor([[1.05, 5.05]])
    # round the wall's top corners (4.5, 8) and (5.5, 8): at least that polyline
    way_round = math.dist((1.05, 5.05), (4.5, 8.0)) + 1.0 + math.dist((5.5, 8.0), GOAL)
    assert float(field(start)[0]) >= way_round - 0.05
    assert float(field(start)[0]) > math.dist((1.05, 5.05), GOAL) + 2.0
    inside = torch.tensor([[5.0, 4.0]])  # deep in the wall: unreachable
    assert float(field(inside)[0]) == UNREACHABLE
    field.update(Environment([Rect(4.52, 0.0, 5.52, 8.0)], bounds=BOX))  # off the grid by 2 cm
    edge = torch.tensor([[4.51, 5.05]])  # free, in a cell whose centre (4.55) is in the wall: still its distance
    assert float(field(edge)[0]) < float(field(torch.tensor([[4.45, 5.05]]))[0]) + 0.2


def test_unreachable_cells_and_recompute_only_on_change():
    free = np.ones((5, 5), dtype=bool)
    free[:, 2] = False  # a full wall: the left side cannot reach the goal on the right
    dist = geodesic_distance(free, (2, 4), 1.0)
    assert dist[2, 4] == 0 and dist[2, 3] == 1 and dist[2, 0] == UNREACHABLE
    field = CostToGo(BOX, GOAL)
    wall = Rect(4.5, 0.0, 5.5, 8.0)
    env = Environment([wall], bounds=BOX)
    field.update(env)
    field.update(Environment([wall], bounds=BOX))  # the same obstacles: no recompute
    assert field.updates == 1
    field.update(Environment([], bounds=BOX))
    assert field.updates == 2


def test_the_cost_squares_the_cost_to_go_before_arrival():
    env = Environment([], bounds=BOX)
    states = torch.tensor([[[1.0, 5.0, 0.0], [2.0, 5.0, 0.0], [3.0, 5.0, 0.0]]])  # [1, 3, 3]
    actions = torch.zeros(1, 2, 1)
    straight = NavigationCost(env, GOAL, goal_tolerance=0.2)
    same = NavigationCost(env, GOAL, goal_tolerance=0.2,
                          goal_distance=lambda xy: torch.linalg.vector_norm(xy - torch.tensor(GOAL), dim=-1))
    assert float(same(states, actions)) == pytest.approx(float(straight(states, actions)))
    doubled = NavigationCost(env, GOAL, goal_tolerance=0.2,
                             goal_distance=lambda xy: 2 * torch.linalg.vector_norm(xy - torch.tensor(GOAL), dim=-1))
    assert float(doubled(states, actions)) == pytest.approx(4 * float(straight(states, actions)))
    bad = NavigationCost(env, GOAL, goal_distance=lambda xy: xy[..., 0].sum(dim=-1))
    with pytest.raises(ValueError, match="goal_distance must map"):
        bad(states, actions)


def test_with_it_mppi_gets_through_the_offset_gaps(tmp_path):  # 6-step horizon, std 0.3: fails them all without
    from eval.navigate.robot_files import ensure_table

    table = ensure_table(ROBOT, Path(tmp_path), quiet=True)
    offset = [t for t in make_tasks("gaps", ROBOT.radius, count=3) if t.params["offset"] > 0]  # wall on the line
    outcomes = {}
    for to_go in (None, 0.1):
        ctx = NavContext(table=str(table), horizon=ROBOT.horizon, cost_to_go=to_go)
        outcomes[to_go] = [run_nav_episode(NavJob(t, "mppi_0.3", 64, seed=7), ctx)["outcome"] for t in offset]
    assert outcomes[0.1] == ["goal"] * len(offset)
    assert "goal" not in outcomes[None]  # the straight line's minimum at the wall holds it there: it crashes
