"""The Triton table rollout (cuniform_torch.tables.gpu_kernels): the numba loop's draws and states, checked on a CPU
through Triton's interpreter (skipped where triton is not installed: CPU builds of torch lack it) and on CUDA."""

import math

import pytest
import torch

from cuniform_torch import TablePolicy, rollout
from cuniform_torch.sampling.rollout import RolloutPlan
from cuniform_torch.systems.models import Dubins
from cuniform_torch.tables import gpu_kernels

pytestmark = pytest.mark.skipif(not gpu_kernels.available(), reason="triton is not installed")


@pytest.fixture(scope="module")
def table(tmp_path_factory):
    """A small Dubins max-flow table (horizon 6) with a fast turn set, so rollouts leave it (fallbacks count)."""
    from precompute.flow.builder import BuildConfig, build_table

    system = Dubins(speed=0.5, dt=0.2, max_omega=1.5, num_actions=7, cell_size=(0.05, 0.05, 2 * math.pi / 40))
    return build_table(system, BuildConfig(horizon=6))[0]


@pytest.fixture
def interpret(monkeypatch):
    monkeypatch.setenv("TRITON_INTERPRET", "1")


def test_the_interpreted_kernel_draws_what_the_numba_loop_draws(table, interpret):
    numba_policy = TablePolicy(table, kernel="numba")
    triton = gpu_kernels.TritonRollout(numba_policy.index)
    uniforms = torch.rand((6, 700), generator=torch.Generator().manual_seed(3))
    states, actions, code = triton(uniforms, 0.2, 0.5)
    ref_states, ref_actions, ref_code = numba_policy._numba.dubins_rollout(uniforms, 0.2, 0.5)
    assert states.shape == (7, 3, 700) and actions.shape == (700, 6, 1)
    assert torch.equal(actions, ref_actions)
    assert int(code) == ref_code and ref_code > 0  # some rollouts left the table: the fallbacks are counted
    assert (states - ref_states).abs().max() < 1e-5


def test_a_triton_policy_rolls_out_as_the_numba_policy(table, interpret):
    fast = TablePolicy(table, kernel="triton")
    ref = TablePolicy(table, kernel="numba")
    system = fast.system
    x0 = torch.tensor([1.0, -2.0, 0.7])
    s1, a1 = rollout(system, fast, x0, 500, 6, torch.Generator().manual_seed(0))
    s2, a2 = rollout(system, ref, x0, 500, 6, torch.Generator().manual_seed(0))
    assert torch.equal(a1, a2)
    assert (s1 - s2).abs().max() < 1e-5
    assert fast.counts.queries == ref.counts.queries == 500 * 6
    assert fast.nearest_rate == ref.nearest_rate and fast.miss_rate == ref.miss_rate


def test_triton_is_refused_by_name_where_it_cannot_run(table):
    with pytest.raises(ValueError, match="kernel='triton' cannot be used: .*not a CUDA device"):
        TablePolicy(table, kernel="triton")  # a CPU without the interpreter
    with pytest.raises(ValueError, match="kernel='triton' cannot be used: .*lookup is a hash"):
        TablePolicy(table, kernel="triton", lookup="hash", device="cuda" if torch.cuda.is_available() else "cpu")


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_on_cuda_the_default_kernel_is_the_fused_one_and_draws_what_the_torch_ops_draw(table):
    fused = TablePolicy(table, device="cuda")
    assert fused.kernel.value == "triton"
    ops = TablePolicy(table, device="cuda", kernel="torch")
    x0 = torch.tensor([1.0, -2.0, 0.7], device="cuda")
    # the same uniforms for both (one [T, N] draw and T draws of [N] are different Philox streams on CUDA)
    uniforms = torch.rand((6, 4000), generator=torch.Generator("cuda").manual_seed(0), device="cuda")
    s1, a1 = RolloutPlan.of(fused.system, fused).run(fused.system, fused, x0, 4000, 6, None, uniforms)
    s2, a2 = RolloutPlan.of(ops.system, ops).run(ops.system, ops, x0, 4000, 6, None, uniforms)
    same = (a1 == a2).all(dim=(1, 2))
    assert same.float().mean() > 0.999  # a state within float rounding of a cell boundary may pick another cell
    assert (s1[same] - s2[same]).abs().max() < 1e-4
    assert abs(fused.miss_rate - ops.miss_rate) < 1e-3


def _broken_compile(index):
    raise RuntimeError("ptxas: no such toolchain")


def test_a_triton_rollout_that_does_not_compile_is_an_error_when_asked_for(table, interpret, monkeypatch):
    monkeypatch.setattr(gpu_kernels, "TritonRollout", _broken_compile)
    with pytest.raises(RuntimeError, match="kernel='triton': the Triton rollout did not compile .*ptxas.*"
                                           "use kernel='torch'"):
        TablePolicy(table, kernel="triton")


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_on_cuda_auto_falls_back_to_the_torch_ops_with_a_warning_when_triton_fails(table, monkeypatch):
    monkeypatch.setattr(gpu_kernels, "TritonRollout", _broken_compile)
    with pytest.warns(RuntimeWarning, match="did not compile .*runs the torch ops"):
        policy = TablePolicy(table, device="cuda")
    assert policy.kernel.value == "torch"
    states, _ = rollout(policy.system, policy, torch.zeros(3, device="cuda"), 100, 6)
    assert states.shape == (100, 7, 3)
