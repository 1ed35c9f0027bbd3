"""Systems: batched torch dynamics with a finite action set and a grid, plus a registry.

A *system* is anything that satisfies the :class:`System` protocol. One definition serves the offline table
builder (float64 on the CPU) and the runtime (float32 on any device): ``step`` only uses torch ops and keeps
the dtype and device of its inputs. Where each thing lives:

* :mod:`.protocol`: :class:`System`, :func:`check_system` (says what a user system lacks),
  :func:`check_dynamics` (probes a user ``step`` once: no in-place update, its input's dtype, ``[N, d]``),
  :func:`se2_invariance_gap` (checks a claimed SE(2) invariance numerically), the limits ``MAX_ACTIONS``,
  ``MAX_HORIZON`` and ``DEFAULT_HORIZON``.
* :mod:`.models`: the built-in ``random_walk_1d`` (:class:`RandomWalk1D`) and ``dubins`` (:class:`Dubins`), and the
  helpers the built-ins share; :mod:`.single_track`: ``ks`` (:class:`KinematicSingleTrack`) and ``ks_speed``
  (:class:`KinematicSingleTrackSpeed`).
* :mod:`.classic`: the built-in ``double_integrator`` (:class:`DoubleIntegrator`) and ``mountain_car``
  (:class:`MountainCar`, gymnasium's MountainCarContinuous-v0), which are not SE(2)-invariant.
* :mod:`.registry`: :func:`register_system`, :func:`make_system`, :func:`resolve_system`, factories by
  ``"module:qualname"`` path, and the system JSON of table and checkpoint files (:func:`system_to_json`,
  :func:`system_from_json`).

The grid invariants are :func:`cuniform_torch.grid.cells.check_grid`; :func:`wrap_angle` and the small argument
checks are :mod:`cuniform_torch.common.checks`.

Your own robot: write a class (a frozen dataclass is simplest) with the attributes and methods of
:class:`System`, then ``register_system("my_robot", MyRobot)``. Tables record the factory as an importable
``"module:qualname"`` path in their system JSON (key ``factory``), but reading a table or checkpoint never
imports or calls it: :func:`system_from_json` rebuilds a system from the registry, or from a ``trust_factory``
the caller names (the file's string is only compared with it). In a fresh process, import the module that
registers the system first, or pass ``trust_factory="my_robots:MyRobot"``.
"""

from cuniform_torch.common.checks import wrap_angle
from cuniform_torch.systems.classic import DoubleIntegrator, MountainCar
from cuniform_torch.systems.models import Dubins, RandomWalk1D
from cuniform_torch.systems.protocol import (
    DEFAULT_HORIZON,
    MAX_ACTIONS,
    MAX_HORIZON,
    System,
    check_dynamics,
    check_system,
    se2_invariance_gap,
    system_horizon,
)
from cuniform_torch.systems.registry import (
    _REGISTRY,
    UnknownSystemError,
    factory_path,
    import_system_modules,
    is_builtin,
    known_systems,
    load_factory,
    make_system,
    register_system,
    resolve_system,
    system_from_json,
    system_to_json,
)
from cuniform_torch.systems.single_track import KinematicSingleTrack, KinematicSingleTrackSpeed

__all__ = [
    "System",
    "RandomWalk1D",
    "Dubins",
    "KinematicSingleTrack",
    "KinematicSingleTrackSpeed",
    "DoubleIntegrator",
    "MountainCar",
    "UnknownSystemError",
    "register_system",
    "make_system",
    "known_systems",
    "is_builtin",
    "system_to_json",
    "system_from_json",
    "wrap_angle",
    "check_dynamics",
    "check_system",
    "se2_invariance_gap",
    "resolve_system",
    "import_system_modules",
    "factory_path",
    "load_factory",
    "system_horizon",
    "DEFAULT_HORIZON",
    "MAX_ACTIONS",
    "MAX_HORIZON",
]
