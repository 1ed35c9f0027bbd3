"""One home for the grid's invariants (cuniform_torch.grid.cells.check_grid) and the small argument checks
(cuniform_torch.common.checks): the four places that check a grid agree, on the same borderline values."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from cuniform_torch.common.checks import finite, float_tuple, non_negative, positive, positive_int, wrap_angle
from cuniform_torch.grid.cells import ANGLE_CELL_RTOL, Grid, check_grid
from cuniform_torch.systems import Dubins, check_system
from cuniform_torch.tables.file import TableError, validate_table

K = 40
EXACT = 2 * math.pi / K


class _RawDubins:
    """A user system that keeps its cell sizes as given (nothing normalizes a user's attributes)."""

    name, dt, periodic, se2_invariant, cell_offset = "raw_dubins", 0.2, (False, False, True), True, (0.0, 0.0, 0.01)

    def __init__(self, angle_cell: float):
        self.cell_size = (0.05, 0.05, angle_cell)

    def action_set(self, dtype=torch.float32, device=None):
        return Dubins().action_set(dtype, device)

    def step(self, x, u):
        return Dubins().step(x, u)

    def params(self):
        return {}


def _sites(angle_cell: float, table) -> dict[str, object]:
    """What each of the four places makes of an angle cell size: the normalized size, or the error it raises."""
    out: dict[str, object] = {}
    for site, run in {
        "system": lambda: Dubins(cell_size=(0.05, 0.05, angle_cell)).cell_size[2],
        "check_system": lambda: (check_system(_RawDubins(angle_cell)), Grid.of(_RawDubins(angle_cell)).cell_size[2])[1],
        "Grid": lambda: Grid((0.05, 0.05, angle_cell), (False, False, True), (0.0, 0.0, 0.0)).cell_size[2],
        "table": lambda: validate_table(dataclasses.replace(
            table, cell_size=np.array([0.05, 0.05, angle_cell]))) or EXACT,
    }.items():
        try:
            out[site] = run()
        except (ValueError, TableError) as exc:
            out[site] = exc
    return out


@pytest.mark.parametrize("rel", [1e-4, 0.9 * ANGLE_CELL_RTOL, -0.9 * ANGLE_CELL_RTOL])
def test_all_four_places_accept_a_size_inside_the_tolerance_and_make_it_exact(rel, dubins_table):
    """1e-4 off (a size typed as 0.1571) is accepted everywhere: a place with a 1e-6 tolerance would refuse it."""
    got = _sites(EXACT * (1 + rel), dubins_table)
    assert got == {site: EXACT for site in got}, got


@pytest.mark.parametrize("rel", [1.1 * ANGLE_CELL_RTOL, -1.1 * ANGLE_CELL_RTOL, 0.3])
def test_all_four_places_refuse_a_size_outside_the_tolerance(rel, dubins_table):
    got = _sites(EXACT * (1 + rel), dubins_table)
    assert all(isinstance(v, ValueError) and "must divide 2*pi" in str(v) for v in got.values()), got


def test_check_grid_normalizes_and_names_what_is_wrong():
    sizes, offsets = check_grid(np.array([0.1, 0.1571]), np.array([False, True]), [0.0, 0.01], "crab")
    assert sizes == (0.1, EXACT) and offsets == (0.0, 0.01) and all(type(v) is float for v in sizes + offsets)
    for args, match in [
        (((0.1,), (False, True), (0.0, 0.0)), r"crab: cell_size needs 2 value\(s\)"),
        (((0.1, EXACT), (False, True), (0.0,)), r"crab: cell_offset needs 2 value\(s\)"),
        (((0.1, math.nan), (False, True), (0.0, 0.0)), r"crab: cell_size must be finite"),
        (((0.0, EXACT), (False, True), (0.0, 0.0)), r"crab: cell_size must be positive"),
        (((0.1, EXACT), (False, True), (0.5, 0.0)), r"crab: cell_offset .*\|offset\| < 0\.5"),
        (((0.1, 7.0), (False, True), (0.0, 0.0)), r"crab: the angle cell size must divide 2\*pi.*dimension 1"),
        (((0.1, "x"), (False, True), (0.0, 0.0)), r"crab: cell_size must be a sequence of 2 numbers"),
    ]:
        with pytest.raises(ValueError, match=match):
            check_grid(*args, "crab")


def test_number_checks():
    positive("car", speed=1, dt=0.5)
    non_negative("car", max_omega=0.0)
    finite("car", min_speed=-1.0)
    for check, value, match in [(positive, 0.0, "positive number"), (positive, math.nan, "positive number"),
                                (positive, "1", "positive number, got '1'"), (non_negative, -1e-9, "non-negative"),
                                (finite, math.inf, "finite number")]:
        with pytest.raises(ValueError, match=rf"car: x must be a {match}"):
            check("car", x=value)


def test_positive_int():
    assert positive_int("car", "num_actions", 5, at_most=5) == 5
    assert positive_int("car", "steps", 10**9) == 10**9
    for value in (0, 6, True, 2.0, "3"):
        with pytest.raises(ValueError, match=r"car: num_actions must be a positive integer \(at most 5\), got"):
            positive_int("car", "num_actions", value, at_most=5)
    with pytest.raises(ValueError, match=r"car: steps must be a positive integer, got -1"):
        positive_int("car", "steps", -1)


def test_float_tuple_and_wrap_angle():
    assert float_tuple(np.array([1, 2]), 2, "cell_size", "car") == (1.0, 2.0)
    for dtype in (torch.float32, torch.float64):
        theta = torch.tensor([-math.pi, math.pi, 3 * math.pi + 0.5, -0.25], dtype=dtype)
        out = wrap_angle(theta)
        assert out.dtype == dtype and bool(((out >= -math.pi) & (out < math.pi)).all())
        torch.testing.assert_close(torch.cos(out), torch.cos(theta))
