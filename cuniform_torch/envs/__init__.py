"""Environments for the navigation experiments: 2-D obstacles, the paper's cost, and a closed-loop simulator."""

from .costs import NavigationCost, TrajectoryCost, collision_mask, goal_cost
from .environment import Environment
from .occupancy import OccupancyGrid
from .scenes import Opening, u_shape
from .shapes import Circle, Obstacle, Polygon, Rect
from .sim import COLLISION, GOAL, TIMEOUT, Controller, SimResult, simulate

__all__ = [
    "Obstacle", "Circle", "Rect", "Polygon", "OccupancyGrid", "Opening", "u_shape", "Environment",
    "TrajectoryCost", "NavigationCost", "goal_cost", "collision_mask",
    "Controller", "SimResult", "simulate", "GOAL", "COLLISION", "TIMEOUT",
]
