"""CFU-MPPI (C-Free-Uniform, arXiv 2510.16905): CU-MPPI whose first stage is a map-conditioned policy.

Shapes: K samples, T horizon, d state dimensions, q action dimensions, H x W patch cells.

Per command the controller senses (:meth:`CFUMPPI.sense`, called once with every robot's state before the first
stage's rollout): the robot-frame patch at each robot's pose is cropped from the world grid (:class:`MapSensor`)
and the B patches encoded as one batch, the map policy's explicit input (``set_maps``; the rollout itself senses
nothing); half the budget are rollouts of the
:class:`~cuniform_torch.maps.policy.MapPolicy` for that map, the lowest-cost one becomes the nominal of one
Gaussian (or log-normal) MPPI pass with the other half, and that pass's first control is applied. It is
:class:`~cuniform_torch.controllers.mppi.CUMPPI` with the map policy in place of the table: the MPPI core, the composite
proposal and the split are CUMPPI's, unchanged.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from typing import Any

import torch
from torch import Tensor

from cuniform_torch.controllers.mppi import CUMPPI, CostFn
from cuniform_torch.envs.environment import Environment
from cuniform_torch.envs.occupancy import OccupancyGrid
from cuniform_torch.maps import kernels, sensing
from cuniform_torch.maps.checkpoint import load_map_policy
from cuniform_torch.maps.policy import MapPolicy
from cuniform_torch.maps.sensing import sense_patch
from cuniform_torch.sampling.rollout import same_device

__all__ = ["MapSensor", "CFUMPPI", "check_policy_robot"]


class MapSensor:
    """What CFU-MPPI senses: the robot-frame occupancy patch of a :class:`MapPolicy`'s
    :class:`~cuniform_torch.maps.encoder.PatchSpec` around each robot's pose, cropped from a world grid (or an
    Environment's shapes), within ``max_range`` (m), seeing an Environment's obstacles sensed by :attr:`time`.

    :param policy: the map policy whose patch is sensed (its spec, device and dtype)
    :param world: an OccupancyGrid or an Environment, world frame, not inflated
    :param max_range: how far the patch sees (m; None: the whole patch)
    """

    def __init__(self, policy: MapPolicy, world: OccupancyGrid | Environment, max_range: float | None = None):
        if not isinstance(policy, MapPolicy):
            raise ValueError(f"policy must be a MapPolicy, got {type(policy).__name__}")
        if not policy.system.se2_invariant or len(policy.system.periodic) < 3:
            raise ValueError(f"a map policy needs (x, y, heading, ...) states of an SE(2)-invariant system; "
                             f"{policy.system.name} is not one")
        self.spec, self.device, self.max_range = policy.patch_spec, policy.device, max_range
        self.set_world(world)

        self.time: float | None = None
        """an Environment world's obstacles sensed by this time (s) are seen (None: all); see :meth:`set_time`"""

    def set_world(self, world: OccupancyGrid | Environment) -> None:
        """Sense ``world`` from the next call on (a map that changed: a new obstacle)."""
        if not isinstance(world, (OccupancyGrid, Environment)):
            raise ValueError(f"world must be an OccupancyGrid or an Environment, got {type(world).__name__}")
        self.world = world.to(self.device) if isinstance(world, OccupancyGrid) else world

    def set_time(self, time: float | None) -> None:
        """See an Environment's obstacles sensed by ``time`` (s) from the next call on (None: all)."""
        self.time = time

    def sense(self, states: Tensor) -> Tensor:
        """The patches at the poses ``states[:, :3]`` (``[B, d]``, world frame, one per robot), in one call:
        ``[B, H, W]`` bool, on the policy's device."""
        return sense_patch(self.world, states[:, :3], self.spec, self.max_range, self.time)


def check_policy_robot(policy: MapPolicy, system: Any, horizon: int | None = None) -> None:
    """A clear ValueError naming every difference between the robot ``policy`` was trained for and ``system``
    (its name and parameters) and, when given, the controller ``horizon`` (at most the policy's)."""
    trained, given = policy.system, system
    diff = [f"system: trained {trained.name!r}, given {given.name!r}"] if trained.name != given.name else []
    a, b = trained.params(), given.params()
    for key in sorted(set(a) | set(b)):
        va, vb = a.get(key), b.get(key)
        same = va == vb or (isinstance(va, (list, tuple)) and isinstance(vb, (list, tuple)) and list(va) == list(vb))
        if not same:
            diff.append(f"{key}: trained {va!r}, given {vb!r}")
    if horizon is not None and horizon > policy.horizon:
        diff.append(f"horizon: trained {policy.horizon}, given {horizon}")
    if diff:
        raise ValueError("the map policy was trained for another robot: " + "; ".join(diff))


class CFUMPPI(CUMPPI):
    """CFU-MPPI: ``policy`` (a :class:`MapPolicy`, a checkpoint path or a loaded checkpoint dict) sensing
    ``world`` (an OccupancyGrid or an Environment, world frame, not inflated) seeds one local MPPI pass; see the
    module docstring.

    ``system`` (optional): the robot being controlled; a policy trained for another system (name, speed, turn
    rates, time step, grid) is refused naming what differs. The arguments after ``world`` are :class:`~cuniform_torch.controllers.mppi.CUMPPI`'s (``cuniform_fraction`` of the
    budget are map-policy rollouts); ``max_range`` (m) limits the sensed patch like a costmap. The device is the
    policy's (a checkpoint is loaded onto ``device``, default the CPU). :meth:`set_world` swaps the world map.

    :param policy: a :class:`MapPolicy`, the name of a shipped one (``"unicycle-0.5"``), a checkpoint path or dict
    :param world: an OccupancyGrid or an Environment, sensed around each robot every command
    :param cost_fn: as :class:`~cuniform_torch.controllers.mppi.CUMPPI`'s, and so are ``num_samples``,
        ``cuniform_fraction``, ``lambda_``, ``noise_std``, ``local``, ``horizon``, ``terminal_cost``, ``seed``,
        ``num_robots``, ``debug`` and ``cuda_graph``
    :param max_range: how far the sensed patch sees (m; None: the whole patch)
    :param device: where a checkpoint is loaded
    :param system: the robot being controlled, checked against the one the policy was trained for
    """

    def __init__(self, policy: MapPolicy | dict | str | os.PathLike, world: OccupancyGrid | Environment, cost_fn: CostFn,
                 num_samples: int = 1000, cuniform_fraction: float = 0.5, lambda_: float = 0.567,
                 noise_std: float | Tensor = 0.1, local: str = "mppi", horizon: int | None = None,
                 max_range: float | None = None, terminal_cost: Callable[[Tensor], Tensor] | None = None,
                 device: torch.device | str | None = None, seed: int | Sequence[int] | None = None,
                 system: Any = None, num_robots: int = 1, debug: bool | None = None, cuda_graph: bool = False,
                 **local_kwargs: Any):
        if not isinstance(policy, MapPolicy):
            policy = load_map_policy(policy, device=device if device is not None else "cpu")
        elif device is not None and not same_device(policy.device, device):
            raise ValueError(f"the map policy is on {policy.device} but device={torch.device(device)} was asked "
                             f"for; move it with policy.to(device)")
        if system is not None:
            check_policy_robot(policy, system)
        if kernels.usable(policy.device, policy.dtype):
            kernels.warm_up()  # the compiled rollout's loops, now rather than in the first command
            if isinstance(world, Environment):
                sensing.warm_up()  # and the sensing loop's
        self.sensor = MapSensor(policy, world, max_range)
        """what each command senses around every robot (:meth:`sense`)"""
        self._map_policy = policy
        # the map policy is the first stage's policy itself; its input, the B local maps, is set by :meth:`sense`,
        # which the first stage calls once per command with every robot's state, before its rollout
        super().__init__(policy, cost_fn, num_samples, cuniform_fraction, lambda_, noise_std, local, horizon,
                         terminal_cost=terminal_cost, device=policy.device, seed=seed, num_robots=num_robots,
                         debug=debug, cuda_graph=cuda_graph, condition=self.sense, **local_kwargs)

    @property
    def map_policy(self) -> MapPolicy:
        return self._map_policy

    def sense(self, states: Tensor) -> None:
        """Sense the local map around each robot (``states [B, d]``, world frame) and set them as the map
        policy's input (one encoding of the B maps): its rollouts' row groups ``b`` read map ``b``."""
        self._map_policy.set_maps(self.sensor.sense(states))

    def set_world(self, world: OccupancyGrid | Environment) -> None:
        """Sense ``world`` from the next command on."""
        self.sensor.set_world(world)

    def set_time(self, time: float | None) -> None:
        """Sense an Environment world's obstacles that appeared by ``time`` (s) from the next command on."""
        self.sensor.set_time(time)
