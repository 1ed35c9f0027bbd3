"""The fast lookup structures of the table policy against slow references.

Shapes: N queries, E keys, R probability rows, A actions, d state dimensions.

* :class:`~cuniform_torch.grid.cells.KeyHash` (one-probe static hash) answers exactly what a sorted-key
  ``searchsorted`` answers, hits and misses alike, for int32 and int64 keys and tiny tables;
* ``TablePolicy`` entries (dense index or hash of the packed (level, cell) key) give the row a dictionary over the table gives,
  the nearest level cell for halo cells, and a miss elsewhere, and count them;
* the per-entry alias tables reproduce every probability row exactly (zero-probability actions get no mass).
"""

from __future__ import annotations

import math

import pytest
import torch

from cuniform_torch import TablePolicy, rollout
from cuniform_torch.grid.cells import CellKeys, CellSet, KeyHash
from cuniform_torch.tables.alias import alias_tables
from cuniform_torch.tables.halo import halo as table_halo

CUDA = torch.cuda.is_available()


def _searchsorted_rows(keys: torch.Tensor, queries: torch.Tensor) -> torch.Tensor:
    """Slow reference: position of each query in ``keys`` (-1 if absent), by sorted search."""
    srt, order = torch.sort(keys)
    pos = torch.searchsorted(srt, queries).clamp(max=keys.numel() - 1)
    return torch.where(srt[pos] == queries, order[pos], -1)


def _distinct(n: int, high: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    if high < 2**24:
        return torch.randperm(high, generator=g)[:n]
    keys = torch.unique(torch.randint(0, high, (2 * n,), generator=g))
    return keys[torch.randperm(keys.numel(), generator=g)[:n]]


class TestKeyHash:
    @pytest.mark.parametrize(
        "n, high",
        [(1, 1), (1, 10), (7, 20), (300, 1000), (5000, 2**31 - 1), (20000, 3_000_000), (20000, 2**40), (3000, 2**62)],
    )
    def test_lookup_equals_searchsorted_on_hits_and_misses(self, n, high):
        keys = _distinct(n, high, seed=n)
        table = KeyHash.build(keys)
        assert table.dtype == (torch.int32 if int(keys.max()) < 2**31 else torch.int64)
        assert table.num_slots >= 2 * n and table.num_slots <= 8 * max(n, 4)  # about 2-4x the keys, no dense box
        g = torch.Generator().manual_seed(1)
        misses = torch.randint(0, min(high + 10, 2**63 - 1), (4000,), generator=g)
        edge = torch.tensor([-1, -(2**31), -(2**63), 0, high - 1, high, 2**31 - 1, 2**31, 2**32, 2**62, 2**63 - 1])
        queries = torch.cat((keys, misses, edge, keys.flip(0)))
        assert torch.equal(table.lookup_keys(queries), _searchsorted_rows(keys, queries))

    def test_lookup_keeps_the_query_shape_and_accepts_int32(self):
        keys = _distinct(50, 500, seed=0)
        table = KeyHash.build(keys)
        q = torch.arange(500, dtype=torch.int32).reshape(20, 25)
        assert torch.equal(table.lookup_keys(q), _searchsorted_rows(keys, q.long().reshape(-1)).reshape(20, 25))

    def test_every_query_below_the_key_limit_probes_a_non_empty_slot_only_when_stored(self):
        keys = _distinct(100, 300, seed=2)
        table = KeyHash.build(keys, key_limit=1000)
        q = torch.arange(1000)
        h = table.hash(q.to(table.dtype))
        hit = table.slot_hash[table.slots(h)] == h  # what a kernel checks (no row lookup)
        assert torch.equal(hit, _searchsorted_rows(keys, q) >= 0)
        with pytest.raises(ValueError):
            KeyHash.build(keys, key_limit=int(keys.max()))

    def test_every_key_has_its_own_slot(self):
        keys = _distinct(10000, 10**6, seed=3)
        table = KeyHash.build(keys)
        slots = table.slots(table.hash(keys.to(table.dtype)))
        assert torch.unique(slots).numel() == keys.numel()
        assert torch.equal(table.slot_rows[slots], torch.arange(keys.numel()))

    def test_build_is_deterministic(self):
        keys = _distinct(2000, 10**5, seed=4)
        a, b = KeyHash.build(keys), KeyHash.build(keys)
        assert torch.equal(a.slot_hash, b.slot_hash) and torch.equal(a.disp, b.disp)

    @pytest.mark.parametrize("bad", [torch.tensor([1, 2, 2]), torch.tensor([-1, 3]), torch.tensor([1.0, 2.0])])
    def test_bad_keys_are_value_errors(self, bad):
        with pytest.raises(ValueError):
            KeyHash.build(bad)

    @pytest.mark.gpu
    @pytest.mark.skipif(not CUDA, reason="needs a CUDA device")
    def test_cuda_lookup_equals_cpu(self):
        keys = _distinct(20000, 3_000_000, seed=5)
        table = KeyHash.build(keys)
        q = torch.cat((keys, torch.randint(-10, 3_000_010, (5000,))))
        assert torch.equal(table.to("cuda").lookup_keys(q.cuda()).cpu(), table.lookup_keys(q))


class TestPolicySlots:
    """Random states around every level: the entry lookup against CellSet lookups of the level and its halo."""

    @pytest.mark.parametrize("lookup", ["dense", "hash"])
    @pytest.mark.parametrize("table_name", ["dubins_table", "walk_table"])
    def test_rows_probs_and_counts_match_a_sorted_lookup_with_halo(self, request, table_name, lookup):
        table = request.getfixturevalue(table_name)
        policy = TablePolicy(table, lookup=lookup)
        assert policy.lookup.value == lookup
        grid = policy.grid
        d = grid.dim
        g = torch.Generator().manual_seed(0)
        level_of = torch.repeat_interleave(torch.arange(table.horizon + 1),
                                           torch.from_numpy(table.level_offsets).diff())
        keyed = torch.cat((level_of[:, None], torch.from_numpy(table.cells)), dim=1)  # [C, 1+d]
        halo_cells, halo_rows = table_halo(keyed, grid)
        keys = CellKeys.covering(torch.cat((keyed, halo_cells)))
        own, halo = CellSet.build(keyed, keys), CellSet.build(halo_cells, keys)
        probs = torch.from_numpy(table.action_probs)
        total_hits = total_misses = total = 0
        for t in range(table.horizon + 1):
            lo, hi = int(table.level_offsets[t]), int(table.level_offsets[t + 1])
            # states in level cells, in cells up to 3 cells away (halo and beyond), and far away
            base = torch.from_numpy(table.cells[lo:hi])[torch.randint(0, hi - lo, (3000,), generator=g)]
            cells = base + torch.randint(-3, 4, (3000, d), generator=g) * (torch.rand(3000, 1, generator=g) < 0.7)
            x = grid.centers(cells) + (torch.rand(3000, d, generator=g, dtype=torch.float64) - 0.5) * 0.9 * torch.tensor(
                grid.cell_size, dtype=torch.float64)
            x = torch.cat((x, torch.tensor([[1e6] * d, [-1e6] * d], dtype=torch.float64))).float()
            want = grid.cells(x.double())
            tagged = torch.cat((torch.full((x.shape[0], 1), t), want), dim=1)
            in_level, in_halo = own.lookup(tagged), halo.lookup(tagged)
            expect_row = torch.where(in_level >= 0, in_level, -1)
            assert torch.equal(policy.rows(x, t), expect_row)
            expect_probs = torch.full((x.shape[0], probs.shape[1]), 1.0 / probs.shape[1])
            expect_probs[in_level >= 0] = probs[in_level[in_level >= 0]]
            expect_probs[in_halo >= 0] = probs[halo_rows[in_halo[in_halo >= 0]]]
            torch.testing.assert_close(policy.action_probs(x, t), expect_probs, atol=0, rtol=0)
            total += x.shape[0]
            total_hits += int((in_halo >= 0).sum())
            total_misses += int(((in_level < 0) & (in_halo < 0)).sum())
        assert total_hits > 0 and total_misses > 0
        assert policy.queries == total
        assert int(policy.nearest_hits) == total_hits and int(policy.misses) == total_misses

    @pytest.mark.parametrize("lookup", ["dense", "hash"])
    def test_non_finite_states_are_misses(self, dubins_table, lookup):
        """NaN and +-inf coordinates (any dimension) fall back to uniform rows and count as misses, never a crash."""
        policy = TablePolicy(dubins_table, lookup=lookup)
        bad = []
        for dim in range(3):
            for value in (float("nan"), float("inf"), -float("inf")):
                x = [0.0, 0.0, 0.0]
                x[dim] = value
                bad.append(x)
        x = torch.tensor(bad)
        probs = policy.action_probs(x, 0)
        A = policy.num_actions
        angle_inf = (x[:, 2].isinf()) & (x[:, :2] == 0).all(dim=1)  # an infinite heading clamps to a real angle cell
        assert torch.equal(probs[~angle_inf], torch.full(((~angle_inf).sum(), A), 1.0 / A))
        assert torch.equal(policy.rows(x, 0)[~angle_inf], torch.full(((~angle_inf).sum(),), -1))
        u = policy.sample(x, 3, torch.Generator().manual_seed(0))
        assert u.shape == (x.shape[0], 1) and bool(torch.isfinite(u).all())

    def test_auto_lookup_is_dense_for_small_boxes_and_hash_beyond(self, dubins_table, monkeypatch):
        import cuniform_torch.tables.lookup as lookup_module

        assert TablePolicy(dubins_table).lookup.value == "dense"
        monkeypatch.setattr(lookup_module, "DENSE_MIN_CELLS", 0)
        monkeypatch.setattr(lookup_module, "DENSE_CELLS_PER_ENTRY", 1)
        assert TablePolicy(dubins_table).lookup.value == "hash"
        with pytest.raises(ValueError, match=r"unknown lookup 'sparse'; choose one of: auto, dense, hash"):
            TablePolicy(dubins_table, lookup="sparse")

    @pytest.mark.parametrize("lookup", ["dense", "hash"])
    def test_compiled_kernel_draws_what_the_eager_one_draws(self, dubins_table, lookup):
        """compile=True on one CPU thread (where torch 2.13's inductor once failed to build the kernel's sum)."""
        threads = torch.get_num_threads()
        torch.set_num_threads(1)
        try:
            eager = TablePolicy(dubins_table, lookup=lookup)
            eager.compiled = False  # its steps one by one, as the compiled kernel's (the whole-rollout loop rounds apart)
            compiled = TablePolicy(dubins_table, lookup=lookup, compile=True)
            x0 = torch.tensor([0.3, -0.2, 0.5])
            runs = [rollout(p.system, p, x0, 500, dubins_table.horizon, torch.Generator().manual_seed(3)) for p in
                    (eager, compiled)]
        finally:
            torch.set_num_threads(threads)
        assert torch.equal(runs[0][1], runs[1][1]) and torch.equal(runs[0][0], runs[1][0])
        assert int(eager.nearest_hits) == int(compiled.nearest_hits) and int(eager.misses) == int(compiled.misses)

    @pytest.mark.parametrize("lookup", ["dense", "hash"])
    def test_sample_counts_like_action_probs(self, dubins_table, lookup):
        policy = TablePolicy(dubins_table, lookup=lookup)
        x = policy.grid.centers(torch.tensor([[0, 0, 0], [1, 0, 0], [0, 0, 1], [40, 40, 0]])).float()
        policy.action_probs(x, 0)
        hits, misses = int(policy.nearest_hits), int(policy.misses)
        assert (hits, misses) == (2, 1)
        policy.sample(x, 0, torch.Generator().manual_seed(0))
        assert (int(policy.nearest_hits), int(policy.misses), policy.queries) == (4, 2, 8)

    def test_packed_counter_folds_before_its_low_word_overflows(self, dubins_table):
        policy = TablePolicy(dubins_table)
        x = policy.grid.centers(torch.tensor([[1, 0, 0], [40, 40, 0]])).float()
        policy.counts._packed_queries = 2**31 - 1  # as if 2 billion lookups had been counted
        policy.action_probs(x, 0)  # folds first, then counts
        assert policy.counts._packed_queries == 2
        assert int(policy.nearest_hits) == 1 and int(policy.misses) == 1
        policy.action_probs(x, 0)
        assert int(policy.nearest_hits) == 2 and int(policy.misses) == 2


class TestAlias:
    @pytest.mark.parametrize("A", [1, 2, 5, 9])
    def test_alias_tables_reproduce_every_row(self, A):
        g = torch.Generator().manual_seed(A)
        p = torch.rand(500, A, generator=g, dtype=torch.float64) ** 3
        p[torch.rand(500, A, generator=g) < 0.3] = 0.0  # zero-probability actions
        p[:, 0] += 1e-3  # every row has some mass
        p[0] = 0.0
        p[0, -1] = 1.0  # one certain action
        p /= p.sum(dim=1, keepdim=True)
        thr, alias = alias_tables(p)
        assert bool(((thr >= 0) & (thr <= 1)).all())
        mass = torch.zeros_like(p)
        mass.scatter_add_(1, torch.arange(A).expand(500, A), thr / A)
        mass.scatter_add_(1, alias, (1 - thr) / A)
        torch.testing.assert_close(mass, p, atol=1e-12, rtol=0)
        # a zero-probability column keeps nothing and is nobody's alias with positive weight
        assert bool((thr[p == 0] == 0).all())
        assert bool((p.gather(1, alias)[thr < 1] > 0).all())

    @pytest.mark.parametrize("lookup", ["dense", "hash"])
    @pytest.mark.parametrize("table_name", ["dubins_table", "walk_table"])
    def test_policy_entry_tables_reproduce_the_rows(self, request, table_name, lookup):
        """Every entry's thresholds and outcome pairs give its row (uniform for "not found")."""
        policy = TablePolicy(request.getfixturevalue(table_name), lookup=lookup)
        A = policy.num_actions
        alias_tables = policy.index.alias
        thr = alias_tables.threshold.double().reshape(-1, A) - torch.arange(A)  # [E+1, A] in [0, 1]
        assert bool(((thr >= 0) & (thr <= 1)).all())
        pair = alias_tables.outcome.reshape(-1, A, 2)  # [E+1, A, 2]: alias, j (action values when q == 1)
        values = policy.actions[:, 0].double()
        alias, own = (torch.searchsorted(values, pair[..., i].double()) for i in (0, 1))
        assert torch.equal(own, torch.arange(A).expand_as(own))
        mass = torch.zeros_like(thr)
        mass.scatter_add_(1, own, thr / A)
        mass.scatter_add_(1, alias, (1 - thr) / A)
        want = policy.index.entry_probs.double()  # [E+1, A]: the entries' rows, then uniform for "not found"
        torch.testing.assert_close(mass, want, atol=1e-6, rtol=0)

    def test_sampled_frequencies_follow_a_skewed_row(self, walk_table):
        """A row with zero entries, 400k draws: every frequency within 0.004 of its probability (sd <= 0.0008)."""
        policy = TablePolicy(walk_table)
        lo = int(walk_table.level_offsets[3])
        p = torch.from_numpy(walk_table.action_probs[lo]).double()
        x = policy.grid.centers(torch.from_numpy(walk_table.cells[lo : lo + 1])).float().expand(400_000, 1)
        u = policy.sample(x, 3, torch.Generator().manual_seed(9))
        idx = torch.searchsorted(policy.actions[:, 0].contiguous(), u[:, 0].contiguous())
        freq = torch.bincount(idx, minlength=policy.num_actions).double() / u.shape[0]
        assert float((freq - p).abs().max()) < 0.004
        assert bool((freq[p == 0] == 0).all())


class TestAngles:
    def test_angles_any_number_of_turns_away_get_the_same_row(self, dubins_table):
        policy = TablePolicy(dubins_table)
        t = 3
        lo, hi = int(dubins_table.level_offsets[t]), int(dubins_table.level_offsets[t + 1])
        x = policy.grid.centers(torch.from_numpy(dubins_table.cells[lo:hi]))  # float64 centres
        rows = policy.rows(x.float(), t)
        assert torch.equal(rows, torch.arange(lo, hi))
        for turns in (-1000, -3, -1, 1, 2, 7, 1000):
            shifted = x.clone()
            shifted[:, 2] += 2 * math.pi * turns
            assert torch.equal(policy.rows(shifted.float(), t), rows), turns

    @pytest.mark.parametrize("kernel", ["torch", "numba"])
    def test_huge_and_non_finite_states_are_misses_not_errors(self, dubins_table, kernel):
        """Far (|x| = 1e30), infinite and NaN states are in no cell and no halo: misses, answered uniformly."""
        policy = TablePolicy(dubins_table, kernel=kernel)
        x = torch.tensor([[0.0, 0.0, 1e30], [0.0, 0.0, -1e30], [1e30, -1e30, 0.0], [0.0, 0.0, float("inf")],
                          [0.0, 0.0, float("nan")], [float("nan")] * 3])
        for t in (0, 3):
            assert policy.rows(x, t).tolist() == [-1] * x.shape[0]
            probs = policy.action_probs(x, t)
            torch.testing.assert_close(probs, torch.full_like(probs, 1.0 / policy.num_actions))
        u = policy.sample(x, 0, torch.Generator().manual_seed(0))
        assert bool(torch.isin(u[:, 0], policy.actions[:, 0]).all())
