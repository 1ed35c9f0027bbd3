"""The compiled CPU kernel of the table policy (numba) draws exactly what the torch kernel draws.

Shapes: N states, d state dimensions, q action dimensions.

Same generator seed, same uniforms: the two kernels must give the same actions bit for bit, count the same
nearest-cell hits and misses, and drive :func:`~cuniform_torch.sampling.rollout.rollout` to the same states, for states
inside, near and far outside the level sets, NaN and infinite ones, row- and column-major layouts, one and two
action dimensions, dense and hash lookups, the uniform fallback, one and two states. ``kernel="numba"`` names what
rules it out (float64, compile, a key box that needs float64 keys or an int64 hash); ``"auto"`` falls back to
torch there. Making the policy compiles every layout the kernel is later given, and threads sampling one policy
draw what each would draw alone. The whole-rollout loop's own arithmetic (its vectorized cosine and sine, its
fmod-free heading wrap) is checked against numpy.
"""

from __future__ import annotations

import dataclasses
import threading

import numpy as np
import pytest
import torch

from cuniform_torch import TablePolicy, rollout
from cuniform_torch.policies.table import Kernel
from cuniform_torch.systems import make_system
from cuniform_torch.tables.cpu_kernels import available
from precompute.flow.builder import BuildConfig, build_table

pytestmark = pytest.mark.skipif(not available(), reason="numba is not installed")


@pytest.fixture(scope="module")
def ks_speed_table():
    """A small kinematic single-track table with speed: two action dimensions (steer rate, acceleration)."""
    table, _ = build_table(make_system("ks_speed"), BuildConfig(horizon=4))
    return table


def _states(policy: TablePolicy, n: int, seed: int) -> torch.Tensor:
    """``[n, d]`` states: on table cells (jittered), spread wide, and a few NaN, infinite and huge ones."""
    g = torch.Generator().manual_seed(seed)
    d = policy.grid.dim
    cells = torch.from_numpy(policy.table.cells)[torch.randint(0, policy.num_cells, (n // 2,), generator=g)]
    size = torch.tensor(policy.grid.cell_size, dtype=torch.float64)
    offset = torch.tensor(policy.grid.offset, dtype=torch.float64)
    near = ((cells - offset + 1.2 * (torch.rand(cells.shape, generator=g, dtype=torch.float64) - 0.5)) * size)
    wide = torch.randn((n - n // 2, d), generator=g, dtype=torch.float64) * 3.0
    x = torch.cat((near, wide)).float()
    x[::97] = float("nan")
    x[5::89, 0] = float("inf")
    x[7::83, -1] = -float("inf")
    x[11::79, 0] = 1e30
    return x


@pytest.mark.parametrize("table_name", ["dubins_table", "walk_table", "ks_speed_table"])
@pytest.mark.parametrize("lookup", ["dense", "hash"])
@pytest.mark.parametrize("column_major", [False, True])
def test_numba_draws_what_torch_draws(request, table_name, lookup, column_major):
    table = request.getfixturevalue(table_name)
    eager, fast = TablePolicy(table, kernel="torch", lookup=lookup), TablePolicy(table, lookup=lookup)
    assert eager.kernel is Kernel.TORCH and fast.kernel is Kernel.NUMBA
    x = _states(fast, 20000, seed=3)
    if column_major:
        x = x.T.contiguous().T
    for t in range(fast.horizon + 1):
        u_eager = eager.sample(x, t, torch.Generator().manual_seed(t))
        u_fast = fast.sample(x, t, torch.Generator().manual_seed(t))
        assert u_fast.shape == u_eager.shape == (x.shape[0], table.actions.shape[1])
        assert torch.equal(u_fast, u_eager), f"level {t}: {int((u_fast != u_eager).any(1).sum())} states differ"
    assert int(fast.misses) == int(eager.misses) > 0
    assert int(fast.nearest_hits) == int(eager.nearest_hits) > 0
    assert fast.queries == eager.queries


@pytest.mark.parametrize("table_name", ["dubins_table", "walk_table", "ks_speed_table"])
@pytest.mark.parametrize("n", [1, 2, 777])
def test_numba_draws_what_torch_draws_with_the_uniform_fallback_and_few_states(request, table_name, n):
    table = request.getfixturevalue(table_name)
    eager = TablePolicy(table, kernel="torch", fallback="uniform")
    fast = TablePolicy(table, kernel="numba", fallback="uniform")
    assert fast.num_halo == 0
    x = _states(fast, 800, seed=n)[torch.randperm(800, generator=torch.Generator().manual_seed(n))[:n]]
    for t in range(fast.horizon + 1):
        u_eager = eager.sample(x, t, torch.Generator().manual_seed(t))
        u_fast = fast.sample(x, t, torch.Generator().manual_seed(t))
        assert torch.equal(u_fast, u_eager), f"level {t}"
    assert int(fast.misses) == int(eager.misses) and int(fast.nearest_hits) == int(eager.nearest_hits) == 0


def test_the_first_control_cycle_compiles_nothing(dubins_table, monkeypatch):
    """Making the policy compiles every layout numba is then given (one state or d = 1: C; else column-major: F).

    Recorded per call (numba's dispatcher is shared by every policy of the process, so its signatures are not)."""
    import numba

    from cuniform_torch.tables.cpu_kernels import NumbaKernel

    layouts = []
    call = NumbaKernel.__call__

    def spy(self, x, *args):
        layouts.append(numba.typeof(x if x.flags.f_contiguous else np.asfortranarray(x)).layout)
        return call(self, x, *args)

    monkeypatch.setattr(NumbaKernel, "__call__", spy)
    fast = TablePolicy(dubins_table, kernel="numba")
    warmed = set(layouts)
    layouts.clear()
    rollout(fast.system, fast, torch.zeros(3), 100, 3, torch.Generator().manual_seed(0))
    fast.sample(torch.zeros(1, 3), 0)
    fast.sample(torch.zeros(50, 3), 0)  # row-major: made column-major first
    fast.sample(torch.zeros(50, 6)[:, ::2], 0)  # strided
    assert set(layouts) <= warmed == {"C", "F"}


def test_threads_sampling_one_policy_draw_what_each_would_draw_alone(dubins_table):
    """A bank's worker thread and the control loop may sample the same policy: the kernel's reused uniforms are
    per thread. Two sizes, so the threads would also fight over the buffer's size if they shared one."""
    fast = TablePolicy(dubins_table, kernel="numba")
    x = _states(fast, 20000, seed=4)
    jobs = [(x[:20000], 1), (x[:13000], 2)]
    alone = [[fast.sample(xs, t % 5, g) for t in range(40)] for xs, g in
             ((xs, torch.Generator().manual_seed(seed)) for xs, seed in jobs)]
    together: list[list[torch.Tensor]] = [[], []]

    def work(i):
        xs, seed = jobs[i]
        g = torch.Generator().manual_seed(seed)
        together[i].extend(fast.sample(xs, t % 5, g) for t in range(40))

    threads = [threading.Thread(target=work, args=(i,)) for i in range(2)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    for i in range(2):
        assert all(torch.equal(a, b) for a, b in zip(alone[i], together[i], strict=True)), f"thread {i}"


def test_rollouts_are_the_same_with_either_kernel(dubins_table):
    eager, fast = TablePolicy(dubins_table, kernel="torch"), TablePolicy(dubins_table, kernel="numba")
    fast.compiled = False  # step by step here; the whole-rollout loop is tested below
    for x0 in (torch.zeros(3), torch.tensor([1.0, -2.0, 0.7])):
        s_eager, a_eager = rollout(eager.system, eager, x0, 3000, 10, torch.Generator().manual_seed(5))
        s_fast, a_fast = rollout(fast.system, fast, x0, 3000, 10, torch.Generator().manual_seed(5))
        assert torch.equal(s_fast, s_eager) and torch.equal(a_fast, a_eager)
    assert fast.miss_rate == eager.miss_rate and fast.nearest_rate == eager.nearest_rate


@pytest.mark.parametrize("lookup", ["dense", "hash"])
def test_the_whole_rollout_loop_draws_the_step_by_step_actions(dubins_table, lookup):
    """The compiled Dubins rollout (one numba call for all T steps) takes the step-by-step path's actions from the
    same stream, its states equal to float rounding, and counts the same lookups; batched starts too."""
    step, fused = TablePolicy(dubins_table, lookup=lookup), TablePolicy(dubins_table, lookup=lookup)
    step.compiled = False
    starts = (torch.zeros(3), torch.tensor([1.0, -2.0, 0.7]), torch.randn(500, 3, generator=torch.Generator().manual_seed(2)))
    for x0 in starts:
        n = 500
        s_step, a_step = rollout(step.system, step, x0, n, 10, torch.Generator().manual_seed(5))
        s_fused, a_fused = rollout(fused.system, fused, x0, n, 10, torch.Generator().manual_seed(5))
        assert torch.equal(a_fused, a_step)
        torch.testing.assert_close(s_fused, s_step, atol=1e-5, rtol=0)
    assert fused.queries == step.queries and int(fused.misses) == int(step.misses)
    assert int(fused.nearest_hits) == int(step.nearest_hits)


@pytest.mark.parametrize("kwargs, reason", [
    (dict(dtype=torch.float64), "float64"),
    (dict(compile=True), "compile"),
])
def test_numba_names_what_rules_it_out_and_auto_falls_back(dubins_table, kwargs, reason):
    with pytest.raises(ValueError, match=reason):
        TablePolicy(dubins_table, kernel="numba", **kwargs)
    assert TablePolicy(dubins_table, **kwargs).kernel is Kernel.TORCH
    with pytest.raises(ValueError, match="unknown kernel 'fortran'"):
        TablePolicy(dubins_table, kernel="fortran")


@pytest.mark.parametrize("factor, reason", [(25, "float64 keys"), (3000, "int64 hash")])
def test_numba_names_a_key_box_it_cannot_serve(dubins_table, factor, reason):
    """x and y cell indices times ``factor``: a key box beyond 2^24 cells per level (float64 keys), and beyond
    2^31 in all (an int64 hash); both stay with the torch kernel."""
    cells = dubins_table.cells.copy()
    cells[:, :2] *= factor
    table = dataclasses.replace(dubins_table, cells=cells)
    with pytest.raises(ValueError, match=reason):
        TablePolicy(table, kernel="numba", lookup="hash")
    assert TablePolicy(table, lookup="hash").kernel is Kernel.TORCH


def test_the_rollout_loops_sincos_is_within_an_ulp_of_cosine_and_sine():
    """The whole-rollout loop's cosine and sine (a vectorized polynomial, not libm) rounded to float32 are within
    one float32 ulp of the exact values, over every quadrant and the headings a 0.1 rad lattice reaches."""
    from cuniform_torch.tables.lookup_loops import sincos

    rng = np.random.default_rng(0)
    x = np.concatenate((rng.uniform(-np.pi, np.pi, 200_000), rng.uniform(-40.0, 40.0, 20_000),
                        np.arange(-45, 46) * 0.1, [0.0, -0.0, 1e-30, np.pi / 2, -np.pi / 2, np.pi, -np.pi]))
    x = x.astype(np.float32)
    got = np.array([sincos(np.float64(v)) for v in x], dtype=np.float64).astype(np.float32)  # [n, 2]
    exact = np.stack((np.cos(x.astype(np.float64)), np.sin(x.astype(np.float64))), axis=1)  # [n, 2]
    ulp = np.spacing(np.abs(exact).astype(np.float32)).astype(np.float64)
    worst = (np.abs(got - exact) / ulp).max(axis=0)
    assert (worst <= 1.0).all(), f"cos, sin off by up to {worst} ulp"


def test_the_rollout_loops_dubins_step_wraps_headings_as_fmod_does():
    """The step's fmod-free heading wrap equals ``wrap(theta + rate dt)`` with fmod bit for bit, for headings
    all round the circle and turn rates small and large (sums below -2 pi and above 4 pi take the fmod branch);
    positions move by ``speed dt (cos, sin)`` of the new heading."""
    from cuniform_torch.tables.lookup_loops import dubins_step

    pi, two_pi, dt, speed = np.float32(np.pi), np.float32(2 * np.pi), np.float32(0.2), np.float32(0.5)
    heads = np.linspace(-np.pi, np.pi, 4001, dtype=np.float32)[:-1]
    rates = np.float32([-50.0, -1.5, -0.5, 0.0, 0.5, 1.5, 50.0])
    head, rate = (a.ravel() for a in np.meshgrid(heads, rates))
    n = head.shape[0]
    states = np.zeros((2, 3, n), dtype=np.float32)
    states[0, 0] = np.linspace(-1, 1, n, dtype=np.float32)
    states[0, 2] = head
    dubins_step(0, rate, True, rate, states, dt, speed, pi, two_pi)
    a = rate * dt + head + pi  # float32, as the loop rounds it
    m = np.fmod(a, two_pi)
    want = np.where(m < 0, m + two_pi, m) - pi
    assert (np.abs(a) > 4 * np.pi).any() and (a < 0).any()
    np.testing.assert_array_equal(states[1, 2], want)
    th = states[1, 2].astype(np.float64)
    np.testing.assert_allclose(states[1, 0], states[0, 0] + 0.1 * np.cos(th), atol=2e-7, rtol=0)
    np.testing.assert_allclose(states[1, 1], 0.1 * np.sin(th), atol=2e-7, rtol=0)
