"""The table index (:mod:`cuniform_torch.tables.lookup`) and the pure torch kernel over it, against slow references.

Shapes: N states, d state dimensions, A actions, q action dimensions, E entries.

* every entry of a :class:`~cuniform_torch.tables.lookup.TableIndex` (table cells and halo cells, every level) is found
  from its cell centre, with its row, its probabilities and its fallback code;
* :func:`~cuniform_torch.tables.torch_kernel.lookup_entries` answers what a dictionary over the table and a brute-force
  nearest cell answer, on the dubins, random walk and ks_speed tables and on tables whose key box needs float64
  keys or an int64 hash (paths the numba kernel does not take);
* :func:`~cuniform_torch.tables.torch_kernel.draw` picks the outcome a plain reading of the alias tables picks;
* the index is frozen data that the numba kernel reads in place; :class:`~cuniform_torch.policies.table.UniformPolicy`
  draws exactly what a table draws from its uniform row.
"""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np
import pytest
import torch

from cuniform_torch import TablePolicy, rollout
from cuniform_torch.grid.cells import Grid
from cuniform_torch.policies import UniformPolicy
from cuniform_torch.systems import make_system
from cuniform_torch.tables.cpu_kernels import NumbaKernel, available
from cuniform_torch.tables.halo import halo
from cuniform_torch.tables.lookup import MISS, NEAREST, KeyBox, Lookup, TableIndex, build_index
from cuniform_torch.tables.torch_kernel import draw, lookup_and_draw, lookup_entries
from precompute.flow.builder import BuildConfig, build_table


@pytest.fixture(scope="module")
def ks_speed_table():
    table, _ = build_table(make_system("ks_speed"), BuildConfig(horizon=3))
    return table


def _stretched(table, factor: int):
    """``table`` with its x and y cell indices times ``factor``: a key box of ``factor^2`` times the cells."""
    cells = table.cells.copy()
    cells[:, :2] *= factor
    return dataclasses.replace(table, cells=cells)


def _index(table, lookup="auto", nearest=True, dtype=torch.float32) -> tuple[TableIndex, Grid]:
    grid = Grid.of(table.make_system())
    return build_index(table, grid, nearest=nearest, lookup=Lookup.parse(lookup), dtype=dtype,
                       device=torch.device("cpu")), grid


def _reference(table, grid: Grid, cells: torch.Tensor, t: int, nearest: bool) -> tuple[list[int], list[int]]:
    """Slow reference: the row answering each query cell ``[N, d]`` at level ``t`` (-1: uniform) and its code:
    a dictionary of the level's cells, then the brute-force nearest level cell among the 3^d - 1 neighbours
    (least squared grid distance, ties to the lower row)."""
    lo, hi = int(table.level_offsets[t]), int(table.level_offsets[t + 1])
    members = {tuple(c): lo + i for i, c in enumerate(table.cells[lo:hi].tolist())}
    k = grid.num_angle_cells
    offsets = [o for o in itertools.product((-1, 0, 1), repeat=grid.dim) if any(o)]
    rows, codes = [], []
    for c in cells.tolist():
        if tuple(c) in members:
            rows.append(members[tuple(c)])
            codes.append(0)
            continue
        near = []
        for o in offsets if nearest else []:
            n = tuple((ci + oi) % kk if kk else ci + oi for ci, oi, kk in zip(c, o, k))
            if n in members:
                near.append((sum(oi * oi for oi in o), members[n]))
        rows.append(min(near)[1] if near else -1)
        codes.append(NEAREST if near else MISS)
    return rows, codes


def _states_around(table, grid: Grid, t: int, n: int, seed: int) -> torch.Tensor:
    """``[n + 2, d]`` float32 states within 0.45 cell of the centres of level-t cells moved by -2..2 cells, plus
    two far ones (no state near a cell boundary, where float32 and float64 rounding could disagree)."""
    g = torch.Generator().manual_seed(seed)
    lo, hi = int(table.level_offsets[t]), int(table.level_offsets[t + 1])
    d = grid.dim
    base = torch.from_numpy(table.cells[lo:hi])[torch.randint(0, hi - lo, (n,), generator=g)]
    cells = base + torch.randint(-2, 3, (n, d), generator=g) * (torch.rand(n, 1, generator=g) < 0.6)
    size = torch.tensor(grid.cell_size, dtype=torch.float64)
    x = grid.centers(cells) + (torch.rand(n, d, generator=g, dtype=torch.float64) - 0.5) * 0.9 * size
    return torch.cat((x, torch.tensor([[1e6] * d, [-1e6] * d], dtype=torch.float64))).float()


@pytest.mark.parametrize("table_name, factor, lookup", [
    ("dubins_table", 1, "dense"), ("dubins_table", 1, "hash"), ("walk_table", 1, "dense"),
    ("walk_table", 1, "hash"), ("ks_speed_table", 1, "dense"), ("ks_speed_table", 1, "hash"),
    ("dubins_table", 25, "hash"),  # float64 keys, int32 hash
    ("dubins_table", 3000, "hash"),  # float64 keys, int64 hash
])
@pytest.mark.parametrize("nearest", [True, False])
def test_lookup_entries_answer_what_a_dictionary_answers(request, table_name, factor, lookup, nearest):
    table = request.getfixturevalue(table_name)
    table = _stretched(table, factor) if factor > 1 else table
    index, grid = _index(table, lookup, nearest)
    assert index.lookup.value == lookup
    if factor == 25:
        assert index.keys.key_dtype == torch.float64 and index.hash.dtype == torch.int32
    if factor == 3000:
        assert index.keys.key_dtype == torch.float64 and index.hash.dtype == torch.int64
    levels = range(table.horizon + 1) if table.horizon <= 4 else (0, 1, 2, table.horizon // 2, table.horizon)
    for t in levels:
        x = _states_around(table, grid, t, 600, seed=t)
        rows, codes = _reference(table, grid, grid.cells(x.double()), t, nearest)
        entry = lookup_entries(index, x, t).long()
        assert torch.equal(index.entry_code[entry], torch.tensor(codes)), f"level {t}: fallback codes differ"
        found = torch.where(entry < index.num_entries, index.entry_row[entry.clamp(max=index.num_entries - 1)], -1)
        assert torch.equal(found, torch.tensor(rows)), f"level {t}: rows differ"
        A = index.num_actions
        want = torch.full((x.shape[0], A), 1.0 / A)
        want[found >= 0] = torch.from_numpy(table.action_probs)[found[found >= 0]]
        assert torch.equal(index.entry_probs[entry], want)


@pytest.mark.parametrize("table_name", ["dubins_table", "walk_table", "ks_speed_table"])
@pytest.mark.parametrize("lookup", ["dense", "hash"])
def test_every_entry_is_found_from_its_cell_centre(request, table_name, lookup):
    """All E entries, every level: a table cell is its own row (code 0); halo cell i (in :func:`halo`'s order)
    is entry C + i, answered by its nearest cell (code NEAREST); E is "not found" (code MISS, uniform)."""
    table = request.getfixturevalue(table_name)
    index, grid = _index(table, lookup)
    level = torch.from_numpy(np.repeat(np.arange(table.horizon + 1), np.diff(table.level_offsets)))
    cells = torch.from_numpy(table.cells)
    halo_cells, halo_rows = halo(torch.cat((level[:, None], cells), dim=1), grid)  # [H, 1+d], [H]
    C, E = index.num_cells, index.num_entries
    assert E == C + halo_cells.shape[0] and torch.equal(index.entry_row, torch.cat((torch.arange(C), halo_rows)))
    for t in range(table.horizon + 1):
        rows = torch.nonzero(level == t).squeeze(1)
        assert torch.equal(lookup_entries(index, grid.centers(cells[rows]).float(), t).long(), rows), t
        mine = torch.nonzero(halo_cells[:, 0] == t).squeeze(1)
        x = grid.centers(halo_cells[mine, 1:]).float()
        assert torch.equal(lookup_entries(index, x, t).long(), C + mine), t
    assert bool((index.entry_code[:C] == 0).all()) and bool((index.entry_code[C:E] == NEAREST).all())
    assert int(index.entry_code[E]) == MISS
    assert torch.equal(index.entry_probs[:E], torch.from_numpy(table.action_probs)[index.entry_row])
    assert torch.equal(index.entry_probs[E], torch.full((index.num_actions,), 1.0 / index.num_actions))


@pytest.mark.parametrize("table_name", ["dubins_table", "ks_speed_table"])
def test_draw_picks_the_outcome_a_plain_reading_of_the_alias_tables_picks(request, table_name):
    table = request.getfixturevalue(table_name)
    index, _ = _index(table)
    A, E = index.num_actions, index.num_entries
    g = torch.Generator().manual_seed(0)
    entry = torch.randint(0, E + 1, (3000,), generator=g, dtype=torch.int32)
    r = torch.rand(3000, generator=g) * A
    u = draw(index, entry, r)  # [N, q]
    thr, outcome = index.alias.threshold.tolist(), index.alias.outcome.tolist()
    actions = index.actions.tolist()
    for i in range(0, 3000, 7):
        e, ri = int(entry[i]), float(r[i])
        j = int(ri)
        keep = ri < thr[e * A + j]  # r < j + p_keep
        picked = outcome[2 * (e * A + j) + int(keep)]
        want = [picked] if index.alias.outcome_is_value else actions[picked]
        assert u[i].tolist() == want, i
    assert u.shape == (3000, index.actions.shape[1])


def test_lookup_and_draw_is_lookup_then_draw(dubins_table):
    index, grid = _index(dubins_table)
    x = _states_around(dubins_table, grid, 3, 500, seed=1)
    r = torch.rand(x.shape[0], generator=torch.Generator().manual_seed(2)) * index.num_actions
    u, code = lookup_and_draw(index, x, 3, r)
    entry = lookup_entries(index, x, 3)
    assert torch.equal(u, draw(index, entry, r)) and torch.equal(code, index.entry_code[entry])
    u_t, code_t = lookup_and_draw(index, x, torch.tensor(3), r)  # the level as a 0-d tensor (torch.compile)
    assert torch.equal(u_t, u) and torch.equal(code_t, code)


def test_the_index_is_frozen_named_data_built_once(dubins_table):
    policy = TablePolicy(dubins_table)
    index = policy.index
    assert isinstance(index, TableIndex) and isinstance(index.keys, KeyBox)
    with pytest.raises(dataclasses.FrozenInstanceError):
        index.num_cells = 0
    keys = index.keys
    d = policy.grid.dim
    for name in ("scale", "shift", "low", "high", "span", "period", "inv_period", "half"):
        assert getattr(keys, name).shape == (d,), name
    # the per-dimension view the torch kernel reads is the same numbers
    for j, col in enumerate(keys.columns):
        assert (col.scale, col.low, col.high, col.span, col.period, col.inv_period) == tuple(
            float(getattr(keys, n)[j]) for n in ("scale", "low", "high", "span", "period", "inv_period"))
        assert float(col.shift) == float(keys.shift[j]) and float(col.half) == float(keys.half[j])
    k = policy.grid.num_angle_cells
    assert keys.period.tolist() == [float(kk) for kk in k]
    assert torch.equal(keys.scale, torch.tensor([1.0 / c for c in policy.grid.cell_size], dtype=torch.float32))
    assert policy.actions is index.actions and policy.entry_row is index.entry_row


@pytest.mark.skipif(not available(), reason="numba is not installed")
@pytest.mark.parametrize("lookup", ["dense", "hash"])
def test_the_numba_kernel_reads_the_index_in_place(dubins_table, lookup):
    index, _ = _index(dubins_table, lookup)
    kernel = NumbaKernel(index)
    k = index.keys
    for view, tensor in zip(kernel.keys, (k.scale, k.shift, k.low, k.high, k.span, k.period, k.inv_period, k.half)):
        assert np.shares_memory(view, tensor.numpy())
    assert np.shares_memory(kernel.level_base, index.level_base.numpy())
    for view, tensor in zip(kernel.alias, (index.alias.threshold, index.alias.outcome, index.entry_code)):
        assert np.shares_memory(view, tensor.numpy())
    found = index.dense if lookup == "dense" else index.slot_entry
    assert np.shares_memory(kernel.find[-1], found.numpy())
    with pytest.raises(ValueError, match="float64"):
        NumbaKernel(_index(dubins_table, dtype=torch.float64)[0])


@pytest.mark.parametrize("kernel", ["torch", "numba"])
@pytest.mark.parametrize("n", [1, 5000])
def test_uniform_policy_draws_what_a_table_draws_from_its_uniform_row(dubins_table, kernel, n):
    if kernel == "numba" and not available():
        pytest.skip("numba is not installed")
    table = TablePolicy(dubins_table, fallback="uniform", kernel=kernel)
    uniform = UniformPolicy(table.system)
    far = torch.full((n, 3), 1e3)  # in no cell: the table's uniform row
    for t in (0, 4):
        u_table = table.sample(far, t, torch.Generator().manual_seed(t))
        u_uniform = uniform.sample(far, t, torch.Generator().manual_seed(t))
        assert torch.equal(u_uniform, u_table)
    assert int(table.misses) == 2 * n


def test_uniform_policy_samples_in_the_states_dtype_and_rolls_out_uniformly():
    system = make_system("dubins")
    policy = UniformPolicy(system)
    u = policy.sample(torch.zeros(10, 3, dtype=torch.float64), 0, torch.Generator().manual_seed(0))
    assert u.dtype == torch.float64 and u.shape == (10, 1)
    with pytest.raises(TypeError, match="torch.Generator"):
        policy.sample(torch.zeros(2, 3), 0, generator=0)
    _, actions = rollout(system, policy, torch.zeros(3), 20000, 2, torch.Generator().manual_seed(1))
    A = policy.actions.shape[0]
    idx = torch.searchsorted(policy.actions[:, 0].contiguous(), actions[:, :, 0].reshape(-1).contiguous())
    freq = torch.bincount(idx, minlength=A).double() / idx.numel()
    assert float((freq - 1.0 / A).abs().max()) < 0.01  # 40000 draws: sd of each frequency about 0.002
