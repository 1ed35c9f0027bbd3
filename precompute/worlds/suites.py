"""Seeded navigation suites as plain data: a forest corridor with a sensing range, a narrow gap between rooms, and a
corridor of narrow passages at staggered offsets (:func:`narrow`).

Shapes used in this module: M discs, W wall rectangles, P passages.

A suite is a list of :class:`NavTask`; the benchmark (:mod:`eval.navigate.run`) drives a controller through each. Every
task carries both its *raw* geometry (``discs``, ``walls``, ``bounds``: what the robot's body must not touch)
and ``environment``: the same obstacles **already inflated by** ``robot_radius``, so that the robot's centre
(a point) collides with ``environment`` exactly when the disc robot touches the raw geometry. The inflation
is exact (:func:`precompute.worlds.geometry.inflate`).

Everything is checked when the suite is made, not at run time: a start or goal in collision, a goal that is
not reachable, or geometry that cannot hold the robot raises :class:`SuiteError` (a ``ValueError``), so such a
task is never counted as a controller's failure.

Reachability is :func:`precompute.worlds.geometry.reachable`'s certified flood fill; a passage narrower than about
1.4 resolution cells may be missed (the forest then redraws, see :func:`forest`).

Sensing: :class:`~cuniform_torch.envs.Environment` knows obstacles that appear at a *time*, not within a
*range*. :func:`precompute.worlds.geometry.sensed` gives the obstacles within a range of a point; the runner calls it (through
:meth:`NavTask.sensed_environment`) once per control cycle for a task whose ``sensing_range`` is not None,
and gives the result to the cost, while collisions are judged on the full ``environment``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from cuniform_torch.common.options import Option, option_label
from cuniform_torch.envs import Environment, MovingDiscs
from precompute.worlds.geometry import SuiteError, inflate, reachable, sensed

__all__ = ["NavTask", "SuiteError", "Suite", "forest", "gaps", "narrow", "make_suite", "validate_task", "MAX_ATTEMPTS",
           "GAP_WIDTHS", "NARROW_WIDTHS", "NARROW_TURNS"]

MAX_ATTEMPTS = 100
"""a forest seed whose draws 0..MAX_ATTEMPTS-1 are all unreachable raises :class:`SuiteError`"""
GAP_WIDTHS = (0.6, 1.2)
"""``make_suite("gaps", count)`` sweeps ``count`` widths evenly over this range (m), ends included"""
NARROW_WIDTHS = (0.6, 0.8)
"""m: :func:`narrow`'s passage widths by default, uniform in this range: 1.5-2x the 0.4 m body of the fast robot
(:data:`precompute.worlds.robot.FAST_ROBOT`), a free band of 0.2-0.4 m for its centre"""
NARROW_TURNS = (15.0, 35.0)
"""degrees: :func:`narrow`'s default range of the angle between the corridor's axis and the line from one passage's
exit (or the start) to the next passage's entry"""


@option_label("suite")
class Suite(Option):
    """The known suites."""

    FOREST = "forest"
    GAPS = "gaps"
    NARROW = "narrow"


@dataclass(frozen=True, eq=False)
class NavTask:
    """One navigation task: raw geometry, the inflated environment, start, goal and limits."""

    suite: str
    """``"forest"``, ``"gaps"``, ``"clutter"``, ``"barn"``, ``"moving"``, ``"sudden"`` or ``"narrow"``"""
    task_id: int
    """forest, moving, narrow: the seed; gaps: the index in its sweep; sudden: position x appearance times + appearance"""
    discs: np.ndarray
    """float64 ``[M, 3]``: (x, y, radius) of each raw disc (m); ``[0, 3]`` for none"""
    walls: np.ndarray
    """float64 ``[W, 4]``: (xmin, ymin, xmax, ymax) of each raw wall rectangle (m)"""
    bounds: tuple[float, float, float, float]
    """(xmin, ymin, xmax, ymax) of the raw workspace: the robot's body must stay inside"""
    robot_radius: float
    """m; ``environment`` is inflated by it"""
    environment: Environment
    """the obstacles inflated by ``robot_radius`` (see the module docstring); check the robot's centre on it"""
    start: tuple[float, float, float]
    """(x, y, heading) in m and rad"""
    goal: tuple[float, float]
    """(x, y) in m"""
    goal_tolerance: float
    """m: reached when the centre is within it of ``goal``"""
    time_limit: float
    """s"""
    sensing_range: float | None = None
    """forest: the robot senses the raw obstacles whose surface is within this distance of its centre (m);
    None: everything is known from the start"""
    attempt: int = 0
    """forest: which draw of the seed was kept (0 unless earlier draws were unreachable); gaps: 0"""
    params: dict = field(default_factory=dict)
    """the generator's keyword arguments, for the record"""
    moving: MovingDiscs | None = None
    """the raw discs that move (:func:`precompute.worlds.dynamic.moving`), not inflated; ``environment``
    holds them inflated by ``robot_radius`` in its ``moving``; None: nothing moves"""

    def sensed_environment(self, xy: torch.Tensor) -> Environment:
        """``xy [2]`` -> the inflated obstacles the robot senses at ``xy``: those whose *raw* surface is within
        ``sensing_range`` (an inflated obstacle is ``robot_radius`` closer, so :func:`sensed` is called with
        ``sensing_range - robot_radius``). All of ``environment`` when ``sensing_range`` is None."""
        if self.sensing_range is None:
            return self.environment
        return sensed(self.environment, xy, self.sensing_range - self.robot_radius)


# ------------------------------------------------------------------------------------------------ checks

def _num(value: Any, what: str, who: str, positive: bool = True) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise SuiteError(f"{who}: {what} must be a finite number, got {value!r}")
    if value < 0 or (positive and value == 0):
        raise SuiteError(f"{who}: {what} must be {'> 0' if positive else '>= 0'}, got {value!r}")
    return float(value)


def _int(value: Any, what: str, who: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise SuiteError(f"{who}: {what} must be an integer, got {value!r}")
    return int(value)


def disc_count_range(num_discs: Any, who: str) -> tuple[int, int]:
    """``num_discs`` checked as a pair ``(min, max)`` of integers with ``0 <= min <= max``; SuiteError naming it."""
    try:
        lo, hi = (_int(v, "num_discs", who) for v in num_discs)
    except TypeError:
        raise SuiteError(f"{who}: num_discs must be a pair (min, max), got {num_discs!r}") from None
    if not 0 <= lo <= hi:
        raise SuiteError(f"{who}: num_discs must satisfy 0 <= min <= max, got {num_discs!r}")
    return lo, hi


def validate_task(task: NavTask, resolution: float = 0.1, check_reachable: bool = True) -> None:
    """Raise :class:`SuiteError` if the start or goal is in collision on ``task.environment`` (obstacles or
    bounds; moving discs where they are at t = 0) or, with ``check_reachable``, if :func:`reachable` fails on the
    environment as it is at t = 0."""
    who = f"{task.suite} task {task.task_id}"
    pts = torch.tensor([task.start[:2], task.goal], dtype=torch.float64)  # [2, 2]
    hit = task.environment.in_collision(pts, at=0.0).tolist()  # moving discs where they are at the start
    for name, p, bad in zip(("start", "goal"), (task.start, task.goal), hit):
        if bad:
            raise SuiteError(f"{who}: the {name} {tuple(p)} is in collision (inflated by robot_radius "
                             f"{task.robot_radius}) or outside the bounds")
    if check_reachable and not reachable(task.environment.snapshot(0.0), task.start[:2], task.goal, resolution):
        raise SuiteError(f"{who}: the goal {task.goal} is not reachable from the start {task.start[:2]} "
                         f"(flood fill at {resolution} m)")


# ------------------------------------------------------------------------------------------------ suites

def forest(seed: int, length: float = 35.0, width: float = 10.0, num_discs: tuple[int, int] = (10, 30),
           disc_radius: float = 1.0, sensing_range: float | None = 3.0, robot_radius: float = 0.25,
           start_clearance: float = 0.5, goal_tolerance: float = 0.5, time_limit: float = 60.0,
           resolution: float = 0.1) -> NavTask:
    """A corridor ``[0, length] x [-width/2, width/2]`` with a wall rectangle (0.2 m thick) along each long
    side and ``n`` discs of ``disc_radius``, ``n`` uniform in ``num_discs`` (ends included), centres uniform in
    the corridor; the corridor's ends are the bounds. Start ``(1, 0, 0)`` (heading +x), goal ``(length - 1, 0)``.

    No inflated disc comes within ``start_clearance`` of the start or goal (candidates that would are redrawn),
    so neither is in collision by construction; :func:`validate_task` checks it. Draw ``k`` uses
    ``numpy.random.default_rng([seed, k])``; draw 0 is kept unless its goal is unreachable, then 1, 2, ...
    (``NavTask.attempt`` says which), so a seed gives the same map every time. Raises :class:`SuiteError`
    after :data:`MAX_ATTEMPTS` unreachable draws or for bad parameters."""
    who = "forest"
    seed = _int(seed, "seed", who)
    if seed < 0:
        raise SuiteError(f"{who}: seed must be >= 0, got {seed}")
    L, Wd = _num(length, "length", who), _num(width, "width", who)
    R, r = _num(disc_radius, "disc_radius", who), _num(robot_radius, "robot_radius", who, positive=False)
    clear = _num(start_clearance, "start_clearance", who)
    lo, hi = disc_count_range(num_discs, who)
    if sensing_range is not None:
        sensing_range = _num(sensing_range, "sensing_range", who)
        if sensing_range <= r:
            raise SuiteError(f"{who}: sensing_range ({sensing_range}) must exceed robot_radius ({r})")
    if not L > 2.0 + 2 * r:
        raise SuiteError(f"{who}: length ({L}) must exceed 2 + 2 x robot_radius ({2 + 2 * r}) to hold start and goal")
    if not Wd > 2 * r:
        raise SuiteError(f"{who}: width ({Wd}) must exceed 2 x robot_radius ({2 * r})")
    start, goal = (1.0, 0.0, 0.0), (L - 1.0, 0.0)
    t = 0.2
    walls = np.array([[0.0, Wd / 2, L, Wd / 2 + t], [0.0, -Wd / 2 - t, L, -Wd / 2]])  # [2, 4]
    bounds = (0.0, -Wd / 2, L, Wd / 2)
    keep_out = R + r + clear  # centre-to-start distance below which a disc is redrawn
    anchors = np.array([start[:2], goal])  # [2, 2]
    params = dict(length=L, width=Wd, num_discs=(lo, hi), disc_radius=R, sensing_range=sensing_range,
                  robot_radius=r, start_clearance=clear, goal_tolerance=goal_tolerance, time_limit=time_limit,
                  resolution=resolution)
    for attempt in range(MAX_ATTEMPTS):
        rng = np.random.default_rng([seed, attempt])
        n = int(rng.integers(lo, hi, endpoint=True))
        centres = np.empty((0, 2))
        while centres.shape[0] < n:
            cand = rng.uniform((0.0, -Wd / 2), (L, Wd / 2), size=(2 * n, 2))  # [2n, 2]
            far = np.linalg.norm(cand[:, None] - anchors[None], axis=-1).min(axis=1) > keep_out  # [2n]
            centres = np.concatenate((centres, cand[far]))[:n]
        discs = np.concatenate((centres, np.full((n, 1), R)), axis=1)  # [n, 3]
        task = NavTask(
            suite=Suite.FOREST.value, task_id=seed, discs=discs, walls=walls, bounds=bounds, robot_radius=r,
            environment=inflate(discs, walls, bounds, r), start=start, goal=goal,
            goal_tolerance=_num(goal_tolerance, "goal_tolerance", who, positive=False),
            time_limit=_num(time_limit, "time_limit", who), sensing_range=sensing_range, attempt=attempt,
            params=params,
        )
        validate_task(task, check_reachable=False)  # never fails by construction; a clear error if it does
        if reachable(task.environment, start[:2], goal, resolution):
            return task
    raise SuiteError(f"{who}: seed {seed}: no reachable map in {MAX_ATTEMPTS} draws (num_discs {num_discs}, "
                     f"width {Wd}, disc_radius {R}, robot_radius {r})")


def gaps(width: float = 0.8, length: float = 1.0, room: float = 5.0, robot_radius: float = 0.25,
         goal_tolerance: float = 0.5, time_limit: float = 30.0, task_id: int = 0, offset: float = 0.0) -> NavTask:
    """Two ``room`` x ``room`` rooms, ``[0, room]`` and ``[room + length, 2 room + length]`` in x, both
    ``[-room/2, room/2]`` in y, joined through a wall ``length`` thick by a gap ``|y - offset| < width / 2``.
    Start at room 1's centre heading +x, goal at room 2's centre. With ``offset = 0`` the straight line ``y = 0``
    runs through the gap with clearance ``width / 2 - robot_radius``, so the goal is reachable by construction;
    with an offset the straight line meets the wall (the distance-to-goal cost has a local minimum there, the
    case that tells samplers apart) and the goal is checked by the flood fill (:func:`reachable`).
    Refuses ``width <= 2 robot_radius`` (the inflated gap would be closed) and a gap that leaves the wall."""
    who = "gaps"
    w, L = _num(width, "width", who), _num(length, "length", who)
    S, r = _num(room, "room", who), _num(robot_radius, "robot_radius", who, positive=False)
    o = _num(offset, "offset", who, positive=False) if offset >= 0 else -_num(-offset, "offset", who, positive=False)
    if not w > 2 * r:
        raise SuiteError(f"{who}: the gap width {w} m is not wider than the robot (2 x robot_radius = {2 * r} m)")
    if not w < S:
        raise SuiteError(f"{who}: the gap width {w} m must be smaller than the room ({S} m)")
    if not S > 2 * r:
        raise SuiteError(f"{who}: room ({S}) must exceed 2 x robot_radius ({2 * r})")
    if not abs(o) + w / 2 < S / 2:
        raise SuiteError(f"{who}: a gap of width {w} m at offset {o} m leaves the wall (room half width {S / 2} m)")
    walls = np.array([[S, -S / 2, S + L, o - w / 2], [S, o + w / 2, S + L, S / 2]])  # [2, 4]
    bounds = (0.0, -S / 2, 2 * S + L, S / 2)
    task = NavTask(
        suite=Suite.GAPS.value, task_id=_int(task_id, "task_id", who), discs=np.zeros((0, 3)), walls=walls,
        bounds=bounds, robot_radius=r, environment=inflate(np.zeros((0, 3)), walls, bounds, r),
        start=(S / 2, 0.0, 0.0), goal=(1.5 * S + L, 0.0),
        goal_tolerance=_num(goal_tolerance, "goal_tolerance", who, positive=False),
        time_limit=_num(time_limit, "time_limit", who), sensing_range=None,
        params=dict(width=w, length=L, room=S, robot_radius=r, goal_tolerance=goal_tolerance, time_limit=time_limit,
                    offset=o),
    )
    validate_task(task, resolution=0.02, check_reachable=o != 0)
    return task


def narrow(seed: int, num_passages: int = 4, spacing: float = 2.5, thickness: float = 0.4,
           widths: tuple[float, float] = NARROW_WIDTHS, turns: tuple[float, float] = NARROW_TURNS,
           corridor: float = 5.0, robot_radius: float = 0.2, goal_tolerance: float = 0.5, time_limit: float = 30.0,
           resolution: float = 0.05) -> NavTask:
    """A corridor ``corridor`` m wide (walls and bounds as :func:`forest`'s) crossed by ``num_passages`` walls
    ``thickness`` m thick, each pierced by one passage: wall ``k`` spans x in ``[1 + (k + 1) spacing, 1 + (k + 1)
    spacing + thickness]``; start ``(1, 0, 0)`` (heading +x), goal ``(1 + (num_passages + 1) spacing, 0)``.

    Passage ``k``: width uniform in ``widths`` (m); its centre ``y_k`` is ``y_{k-1} +- d_k tan(a_k)``, ``a_k``
    uniform in ``turns`` (degrees), ``d_k`` the free run before the wall (``spacing`` for the first, from the start's
    ``y = 0``; ``spacing - thickness`` after a passage), the side at even odds, flipped when the passage would come
    within 0.25 m of the corridor's side walls. So each passage sits off the line through the last one and the
    robot must turn into it, then straighten within the wall's ``thickness + 2 robot_radius`` m of inflated slot.

    ``numpy.random.default_rng(seed)``, one draw: the free space is connected by construction (every passage is
    wider than the robot, every free run longer than it), and the certified flood fill at ``resolution`` checks it
    (:func:`validate_task`). ``params["passages"]`` holds ``[P, 3]`` rows (x of the wall's front face, y of the
    passage's centre, width) and ``params["turn_angles"]`` the drawn ``a_k`` (signed, degrees). Raises
    :class:`SuiteError` for bad parameters: a width range not wider than the robot, turns outside [0, 80) degrees,
    a free run not longer than the robot, or a corridor too narrow for the largest offset."""
    who = "narrow"
    seed = _int(seed, "seed", who)
    if seed < 0:
        raise SuiteError(f"{who}: seed must be >= 0, got {seed}")
    n = _int(num_passages, "num_passages", who)
    if n < 1:
        raise SuiteError(f"{who}: num_passages must be >= 1, got {n}")
    S, t, Wd = _num(spacing, "spacing", who), _num(thickness, "thickness", who), _num(corridor, "corridor", who)
    r = _num(robot_radius, "robot_radius", who, positive=False)
    w_lo, w_hi = _range(widths, "widths", who)
    a_lo, a_hi = _range(turns, "turns", who, positive=False)
    if not w_lo > 2 * r:
        raise SuiteError(f"{who}: the narrowest passage ({w_lo} m) must be wider than the robot (2 x robot_radius = "
                         f"{2 * r} m)")
    if not a_hi < 80.0:
        raise SuiteError(f"{who}: turns must stay below 80 degrees, got {turns!r}")
    if not S - t > 2 * r:
        raise SuiteError(f"{who}: the free run between walls (spacing - thickness = {S - t} m) must be longer than "
                         f"the robot ({2 * r} m)")
    y_lim = Wd / 2 - w_hi / 2 - 0.25  # a passage's centre stays within this of the axis
    shift = S * math.tan(math.radians(a_hi))  # the largest offset between two passages
    if not shift <= y_lim:
        raise SuiteError(f"{who}: a corridor {Wd} m wide cannot hold an offset of {shift:.2f} m (spacing {S} m at "
                         f"{a_hi} degrees) on one side of the axis: widen it to {2 * (shift + w_hi / 2 + 0.25):.2f} m "
                         "or lower the turns")
    rng = np.random.default_rng(seed)
    width = rng.uniform(w_lo, w_hi, n)  # [P]
    angle = rng.uniform(a_lo, a_hi, n)  # [P] degrees
    side = np.where(rng.random(n) < 0.5, -1.0, 1.0)  # [P]
    run = np.full(n, S - t)
    run[0] = S  # the first passage is reached from the start
    step = run * np.tan(np.radians(angle))  # [P] lateral offsets, each <= y_lim
    # the side flips where the passage would leave the corridor: a short sequential walk over P <= a few walls
    centre = np.empty(n)
    y = 0.0
    for k in range(n):
        if abs(y + side[k] * step[k]) > y_lim:
            side[k] = -side[k]
        y = centre[k] = y + side[k] * step[k]
    front = 1.0 + S * np.arange(1, n + 1)  # [P] x of each wall's front face
    lo, hi = centre - width / 2, centre + width / 2  # [P] the passage's edges
    below = np.stack((front, np.full(n, -Wd / 2), front + t, lo), axis=1)  # [P, 4]
    above = np.stack((front, hi, front + t, np.full(n, Wd / 2)), axis=1)  # [P, 4]
    goal_x = 1.0 + (n + 1) * S
    L = goal_x + 1.0
    sides = np.array([[0.0, Wd / 2, L, Wd / 2 + 0.2], [0.0, -Wd / 2 - 0.2, L, -Wd / 2]])  # [2, 4], forest's
    walls = np.concatenate((sides, below, above))  # [2 + 2P, 4]
    bounds = (0.0, -Wd / 2, L, Wd / 2)
    params = dict(num_passages=n, spacing=S, thickness=t, widths=(w_lo, w_hi), turns=(a_lo, a_hi), corridor=Wd,
                  robot_radius=r, goal_tolerance=goal_tolerance, time_limit=time_limit, resolution=resolution,
                  passages=np.stack((front, centre, width), axis=1).tolist(),
                  turn_angles=(side * angle).tolist())
    task = NavTask(
        suite=Suite.NARROW.value, task_id=seed, discs=np.zeros((0, 3)), walls=walls, bounds=bounds, robot_radius=r,
        environment=inflate(np.zeros((0, 3)), walls, bounds, r), start=(1.0, 0.0, 0.0), goal=(goal_x, 0.0),
        goal_tolerance=_num(goal_tolerance, "goal_tolerance", who, positive=False),
        time_limit=_num(time_limit, "time_limit", who), sensing_range=None, params=params,
    )
    validate_task(task, resolution=_num(resolution, "resolution", who))
    return task


def _range(value: Any, what: str, who: str, positive: bool = True) -> tuple[float, float]:
    """A (low, high) pair of numbers with ``low <= high``; SuiteError naming ``what`` otherwise."""
    try:
        lo, hi = value
    except (TypeError, ValueError):
        raise SuiteError(f"{who}: {what} must be a pair (min, max), got {value!r}") from None
    lo, hi = _num(lo, what, who, positive), _num(hi, what, who, positive)
    if lo > hi:
        raise SuiteError(f"{who}: {what} must satisfy min <= max, got {value!r}")
    return lo, hi


def make_suite(name: str, count: int, seed: int = 0, offsets: tuple[float, ...] = (0.0,),
               **params: Any) -> list[NavTask]:
    """``count`` tasks of suite ``name``: forest and narrow seeds ``seed, seed + 1, ..., seed + count - 1``; gaps: the
    first ``count`` of every (width, offset) pair, widths ``numpy.linspace(*GAP_WIDTHS, ceil(count /
    len(offsets)))`` (0.6 for one width) outermost, ``offsets`` (m, gaps only) innermost; ``seed`` unused.
    ``params`` go to :func:`forest`, :func:`narrow` or :func:`gaps` (not ``seed`` / ``width`` / ``offset``, which the
    suite sets)."""
    try:
        suite = Suite.parse(name)
    except ValueError as err:
        raise SuiteError(str(err)) from None
    count = _int(count, "count", "make_suite")
    if count < 1:
        raise SuiteError(f"make_suite: count must be >= 1, got {count}")
    seed = _int(seed, "seed", "make_suite")
    if suite is Suite.FOREST:
        return [forest(seed + k, **params) for k in range(count)]
    if suite is Suite.NARROW:
        return [narrow(seed + k, **params) for k in range(count)]
    if "width" in params or "offset" in params:
        raise SuiteError("make_suite: the gaps suite sets width and offset itself (a sweep over GAP_WIDTHS and "
                         "offsets); call gaps() for one")
    if not offsets:
        raise SuiteError("make_suite: give at least one gap offset")
    n_widths = math.ceil(count / len(offsets))
    widths = np.round(np.linspace(*GAP_WIDTHS, n_widths), 12)  # rounded: 0.8, not 0.7999999999999999
    pairs = [(float(w), float(o)) for w in widths for o in offsets][:count]
    return [gaps(width=w, offset=o, task_id=k, **params) for k, (w, o) in enumerate(pairs)]
