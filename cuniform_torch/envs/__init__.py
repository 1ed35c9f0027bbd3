"""Environments for the navigation experiments: 2-D obstacles, the paper's cost, and a closed-loop simulator."""

from .costs import NavigationCost, TrajectoryCost, collision_mask, goal_cost
from .shapes import Circle, Environment, Obstacle, OccupancyGrid, Opening, Polygon, Rect, u_shape
from .sim import COLLISION, GOAL, TIMEOUT, Controller, SimResult, simulate

__all__ = [
    "Obstacle", "Circle", "Rect", "Polygon", "OccupancyGrid", "Opening", "u_shape", "Environment",
    "TrajectoryCost", "NavigationCost", "goal_cost", "collision_mask",
    "Controller", "SimResult", "simulate", "GOAL", "COLLISION", "TIMEOUT",
]
