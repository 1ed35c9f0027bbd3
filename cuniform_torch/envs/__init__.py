"""Environments for the navigation experiments: 2-D obstacles, the paper's cost, and a closed-loop simulator."""

from cuniform_torch.envs.costs import NavigationCost, TrajectoryCost, collision_mask, goal_cost
from cuniform_torch.envs.environment import Environment
from cuniform_torch.envs.moving import MovingDiscs
from cuniform_torch.envs.occupancy import OccupancyGrid
from cuniform_torch.envs.scenes import Opening, u_shape
from cuniform_torch.envs.shapes import Circle, Obstacle, Polygon, Rect
from cuniform_torch.envs.sim import COLLISION, GOAL, TIMEOUT, Controller, SimResult, simulate

__all__ = [
    "Obstacle", "Circle", "Rect", "Polygon", "OccupancyGrid", "Opening", "u_shape", "Environment", "MovingDiscs",
    "TrajectoryCost", "NavigationCost", "goal_cost", "collision_mask",
    "Controller", "SimResult", "simulate", "GOAL", "COLLISION", "TIMEOUT",
]
