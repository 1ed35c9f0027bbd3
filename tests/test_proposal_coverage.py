"""The new proposals' open-loop trajectories (issue 36): ``sample_states`` of each time-correlated or mixture method
draws ``[N, T+1, d]`` trajectories from the start whose actions follow its proposal (the low-pass noise's lag-1
autocorrelation, pink and kernel noise's smoothness, the smooth sampler's rate std, the mixture's C-Uniform share),
and the paper's open-loop commands (coverage, uniformity) accept their keys.

The robot is the navigation benchmark's (turn rates in [-1.5, 1.5] rad/s, 7 actions, dt 0.2 s), whose noise levels
these methods are set for, on a short table (8 steps) so that the reachable set enumerates in a second.
"""

from __future__ import annotations

import json
import math

import pytest
import torch

from cuniform_torch import write_table
from cuniform_torch.systems import make_system
from eval.common.methods import METHODS, PAPER, Sources, parse_methods, sample_states
from eval.paper import coverage as coverage_exp
from eval.paper import uniformity as uniformity_exp
from precompute.flow.builder import BuildConfig, build_table

T = 8
N = 2000
DT = 0.2
MAX_OMEGA = 1.5
NEW = ("mppi_pink_1.0", "mppi_lowpass_1.0", "smppi_2.0", "kmppi_1.0", "mix_cu_mppi_0.5")
"""the new proposals' keys; ``mppi_1.0`` is their white-noise peer"""


@pytest.fixture(scope="module")
def table_path(tmp_path_factory):
    system = make_system("dubins", speed=0.5, dt=DT, max_omega=MAX_OMEGA, num_actions=7,
                         cell_size=[0.05, 0.05, 2 * math.pi / 36])
    table, _ = build_table(system, BuildConfig(horizon=T))
    path = tmp_path_factory.mktemp("tables") / "nav8.npz"
    write_table(path, table)
    return path


@pytest.fixture(scope="module")
def sources(table_path, tmp_path_factory):
    return Sources(table=table_path, coverage_table=table_path, policy=tmp_path_factory.mktemp("x") / "none.pt")


def _draw(key: str, sources: Sources, n: int = N, seed: int = 0) -> torch.Tensor:
    return sample_states(METHODS[key], sources, n, T, torch.Generator().manual_seed(seed))


def _turn_rates(states: torch.Tensor) -> torch.Tensor:
    """``[N, T+1, 3]`` Dubins states -> ``[N, T]`` the turn rates that moved them (heading change / dt)."""
    dtheta = states[:, 1:, 2] - states[:, :-1, 2]
    return torch.atan2(torch.sin(dtheta), torch.cos(dtheta)) / DT


def _lag1(actions: torch.Tensor) -> float:
    """The lag-1 autocorrelation of ``[N, T]`` action sequences, pooled over samples and steps."""
    a = actions - actions.mean()
    return float((a[:, 1:] * a[:, :-1]).mean() / a.square().mean())


@pytest.mark.parametrize("key", ("mppi_1.0", *NEW))
def test_each_sampler_draws_trajectories_from_the_start(key, sources):
    states = _draw(key, sources, n=64)
    assert states.shape == (64, T + 1, 3) and states.dtype == torch.float32
    assert bool(torch.isfinite(states).all())
    assert torch.equal(states[:, 0], torch.zeros(64, 3))  # the table's start, (0, 0, 0)
    assert torch.equal(states, _draw(key, sources, n=64))  # a seed is one draw
    assert not torch.equal(states, _draw(key, sources, n=64, seed=1))
    rates = _turn_rates(states)
    assert float(rates.abs().max()) <= MAX_OMEGA + 1e-3  # executed, bounded actions


def test_time_correlated_noise_is_correlated_and_white_noise_is_not(sources):
    lag1 = {k: _lag1(_turn_rates(_draw(k, sources))) for k in ("mppi_1.0", "mppi_pink_1.0", "mppi_lowpass_1.0",
                                                               "kmppi_1.0")}
    assert abs(lag1["mppi_1.0"]) < 0.05, lag1
    # AR(1) with a = 0.8; clipping to +-1.5 (1.5 std) lowers it a little
    assert lag1["mppi_lowpass_1.0"] == pytest.approx(0.8, abs=0.06)
    assert lag1["mppi_pink_1.0"] > 0.3  # 1/f: positively correlated, less than the low-pass at lag 1
    assert lag1["kmppi_1.0"] > 0.6  # an RBF interpolation of 4 points (sigma 1 step) over 8 steps: about 0.7


def test_smooth_sampler_draws_its_rate_noise(sources):
    rates = _turn_rates(_draw("smppi_2.0", sources))  # [N, T]
    jumps = torch.diff(rates, dim=1, prepend=torch.zeros(N, 1))  # from the last command (zero)
    # rate std 2.0 rad/s^2 x dt 0.2 s: each step's change has std 0.4 rad/s (clipping only shrinks it)
    assert float(jumps[:, 0].std()) == pytest.approx(0.4, rel=0.1)
    assert float(jumps.std(dim=0).max()) < 0.44
    white = torch.diff(_turn_rates(_draw("mppi_1.0", sources)), dim=1)
    assert float(white.std()) > 1.0  # white noise of std 1.0 jumps about sqrt(2) std per step


def test_mixture_draws_its_share_of_cuniform_rows(sources):
    rates = _turn_rates(_draw("mix_cu_mppi_0.5", sources))  # [N, T]
    actions = torch.linspace(-MAX_OMEGA, MAX_OMEGA, 7)
    discrete = ((rates.unsqueeze(-1) - actions).abs().amin(dim=-1) < 1e-3).all(dim=1)  # [N] a table row
    # the C-Uniform part is the first K/2 rows (a Gaussian row lands on the 7 rates at all 8 steps with p ~ 1e-7)
    assert discrete[:N // 2].all() and not discrete[N // 2:].any()


def test_the_open_loop_commands_take_the_new_keys(table_path, tmp_path, capsys):
    keys = ["mppi_1.0", *NEW]
    assert [m.key for m in parse_methods(keys, benchmark=PAPER, closed_loop=False)] == keys
    out = tmp_path / "coverage.json"
    assert coverage_exp.main(["--table", str(table_path), "--coverage-table", str(table_path), "--methods", *keys,
                              "cu_table", "--samples", "200", "--seeds", "2", "--json", str(out)]) == 0
    rows = {r["method"]: r for r in json.loads(out.read_text())["results"]}
    assert list(rows) == [*keys, "cu_table"] and all(r["cells_mean"] > 0 for r in rows.values())
    assert "mix_cu_mppi_0.5" in capsys.readouterr().out
    srcs = Sources(table=table_path, coverage_table=table_path)
    result = uniformity_exp.run(uniformity_exp.UniformityConfig(methods=tuple(keys), samples=200, seeds=1), srcs,
                                progress=False)
    assert [r["method"] for r in result["results"]] == keys
    # the paper's default open-loop runs are unchanged: the new keys are opt-in there
    assert not set(keys) & {m.key for m in parse_methods(None, benchmark=PAPER, closed_loop=False)}
