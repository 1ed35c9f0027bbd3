"""Systems and grid: dynamics as specified, robust cell assignment, packed-key lookups."""

from __future__ import annotations

import math

import pytest
import torch

from cuniform_torch.common.checks import wrap_angle
from cuniform_torch.grid.cells import CellKeys, CellSet, Grid
from cuniform_torch.systems import Dubins, RandomWalk1D, make_system, system_from_json, system_to_json


def test_default_dubins_preset_matches_reference_release():
    s = make_system("dubins")
    assert (s.speed, s.dt, s.num_actions) == (1.0, 0.2, 5)
    assert s.cell_size == pytest.approx((0.05, 0.05, 2 * math.pi / 40))
    torch.testing.assert_close(
        s.action_set(torch.float64).squeeze(1), torch.linspace(-math.pi / 4, math.pi / 4, 5, dtype=torch.float64)
    )


def test_dubins_updates_heading_first_then_position():
    s = Dubins()
    x = torch.tensor([[1.0, 2.0, 0.3]], dtype=torch.float64)
    u = torch.tensor([[0.5]], dtype=torch.float64)
    theta = 0.3 + 0.5 * 0.2
    expected = torch.tensor([[1.0 + 0.2 * math.cos(theta), 2.0 + 0.2 * math.sin(theta), theta]], dtype=torch.float64)
    torch.testing.assert_close(s.step(x, u), expected)


def test_dubins_wraps_heading_to_minus_pi_pi():
    s = Dubins()
    x = torch.tensor([[0.0, 0.0, math.pi - 0.01]], dtype=torch.float64)
    out = s.step(x, torch.tensor([[math.pi / 4]], dtype=torch.float64))
    assert -math.pi <= out[0, 2].item() < math.pi
    assert out[0, 2].item() == pytest.approx(math.pi - 0.01 + math.pi / 20 - 2 * math.pi)


def _dubins_reference(s: Dubins, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """The Dubins step written plainly (the formula the in-place step must reproduce bit for bit)."""
    theta = wrap_angle(x[:, 2] + u[:, 0] * s.dt)
    return torch.stack((x[:, 0] + s.speed * torch.cos(theta) * s.dt, x[:, 1] + s.speed * torch.sin(theta) * s.dt,
                        theta), dim=1)


@pytest.mark.parametrize("speed", [1.0, 0.7])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64, torch.bfloat16])
@pytest.mark.parametrize("n", [1, 2, 1000])
@pytest.mark.parametrize("layout", ["rows", "columns", "strided"])
def test_dubins_step_is_the_plain_formula_bit_for_bit(speed, dtype, n, layout):
    s = Dubins(speed=speed)
    g = torch.Generator().manual_seed(n)
    x = (torch.randn(n, 3, generator=g) * 5).to(dtype)
    x = {"rows": x, "columns": x.T.contiguous().T, "strided": torch.cat((x, x), dim=1)[:, ::2]}[layout]
    u = ((torch.rand(n, 1, generator=g) - 0.5) * 1.6).to(dtype)
    out = s.step(x, u)
    expected = _dubins_reference(s, x, u)
    assert out.dtype == dtype and torch.equal(out, expected)
    if layout == "columns" and n > 1:
        assert out.stride(0) == 1  # column-major in, column-major out
    into = torch.empty(3, n, dtype=dtype).T
    assert s.step(x, u, out=into) is into and torch.equal(into, expected)


def test_dubins_step_promotes_mixed_dtypes_and_checks_out():
    s = Dubins()
    x, u = torch.randn(4, 3), torch.rand(4, 1, dtype=torch.float64)
    out = s.step(x, u)
    assert out.dtype == torch.float64 and torch.equal(out, _dubins_reference(s, x, u))
    with pytest.raises(ValueError, match="out must be a"):
        s.step(x, u, out=torch.empty(4, 3))  # float32 for a float64 result


def test_rollout_of_a_dubins_subclass_with_its_own_step():
    """A subclass that overrides ``step`` (no ``out=``) is stepped the plain way."""
    from cuniform_torch import rollout
    from cuniform_torch.policies import UniformPolicy

    class Slow(Dubins):
        def step(self, x, u):
            return super().step(x, u * 0.5)

    system = Slow()
    policy = UniformPolicy(system)
    states, actions = rollout(system, policy, torch.tensor([0.5, -1.0, 0.2]), 50, 6, torch.Generator().manual_seed(0))
    for t in range(6):
        assert torch.equal(states[:, t + 1], Dubins().step(states[:, t], actions[:, t] * 0.5))


def test_random_walk_steps_and_keeps_dtype_device():
    s = RandomWalk1D()
    for dtype in (torch.float32, torch.float64):
        x = torch.zeros(5, 1, dtype=dtype)
        out = s.step(x, s.action_set(dtype))
        assert out.dtype == dtype
        torch.testing.assert_close(out.squeeze(1), torch.tensor([-1, -0.5, 0, 0.5, 1], dtype=dtype))


@pytest.mark.parametrize("name", ["dubins", "random_walk_1d"])
def test_system_json_round_trip(name):
    s = make_system(name, dt=0.5)
    rebuilt, horizon = system_from_json(system_to_json(s, 7))
    assert rebuilt == s and horizon == 7


def test_angle_cell_size_is_normalized_to_2pi_over_k():
    s = make_system("dubins", cell_size=(0.1, 0.1, 0.1571))
    assert s.cell_size[2] == 2 * math.pi / 40


def test_cells_and_centers_round_trip_with_offset():
    grid = Grid.of(Dubins())
    cells = torch.tensor([[0, 0, 0], [3, -7, 39], [-12, 5, 20]])
    back = grid.cells(grid.centers(cells))
    torch.testing.assert_close(back, cells)
    assert grid.cells(torch.zeros(1, 3)).tolist() == [[0, 0, 0]]  # the origin is in cell 0


def test_float32_and_float64_rollouts_land_in_the_same_cells():
    """Default preset: headings move by exact half cells; the 1% angle offset keeps them off the boundaries."""
    system = Dubins()
    grid = Grid.of(system)
    gen = torch.Generator().manual_seed(0)
    idx = torch.randint(0, 5, (20000, 15), generator=gen)
    cells = {}
    for dtype in (torch.float32, torch.float64):
        actions = system.action_set(dtype)
        x = torch.zeros(idx.shape[0], 3, dtype=dtype)
        out = []
        for t in range(idx.shape[1]):
            x = system.step(x, actions[idx[:, t]])
            out.append(grid.cells(x))
        cells[dtype] = torch.stack(out, 1)
    assert torch.equal(cells[torch.float32], cells[torch.float64])


def test_without_offset_float_noise_decides_the_heading_cell():
    """The reason for the offset: with none, float32 and float64 disagree on many headings."""
    system = Dubins(cell_offset=(0.0, 0.0, 0.0))
    grid = Grid.of(system)
    idx = torch.randint(0, 5, (2000, 10), generator=torch.Generator().manual_seed(1))
    res = []
    for dtype in (torch.float32, torch.float64):
        a, x, out = system.action_set(dtype), torch.zeros(2000, 3, dtype=dtype), []
        for t in range(10):
            x = system.step(x, a[idx[:, t]])
            out.append(grid.cells(x))
        res.append(torch.stack(out, 1))
    assert (res[0] != res[1]).any()


def test_angle_index_is_periodic():
    grid = Grid.of(Dubins())
    x = torch.tensor([[0.0, 0.0, -math.pi], [0.0, 0.0, math.pi - 1e-9], [0.0, 0.0, -0.5 * 2 * math.pi / 40]])
    k = grid.cells(x)[:, 2]
    assert ((k >= 0) & (k < 40)).all()
    assert k[0] == k[1] == 20


@pytest.mark.parametrize("n", [1, 7, 1000])
def test_cellset_lookup_matches_a_dictionary(n):
    gen = torch.Generator().manual_seed(n)
    cells = torch.unique(torch.randint(-50, 50, (n, 3), generator=gen), dim=0)
    cells = cells[torch.randperm(len(cells), generator=gen)]
    index = CellSet.build(cells)
    queries = torch.cat((cells, torch.randint(-60, 60, (500, 3), generator=gen)))
    expected = {tuple(c): i for i, c in enumerate(cells.tolist())}
    got = index.lookup(queries).tolist()
    assert got == [expected.get(tuple(q), -1) for q in queries.tolist()]


def test_cellkeys_pack_unpack_and_outside_box():
    cells = torch.tensor([[0, -3, 2], [5, 4, 0], [1, 1, 1]])
    keys = CellKeys.covering(cells)
    torch.testing.assert_close(keys.unpack(keys.pack(cells)), cells)
    assert keys.pack(torch.tensor([[6, 0, 0], [0, -4, 0]])).tolist() == [-1, -1]
