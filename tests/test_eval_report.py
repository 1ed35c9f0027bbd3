"""eval: the open-loop experiments' numbers, the graph sampler, and `python -m eval.report --quick` end to end."""

from __future__ import annotations

import json

import matplotlib.image
import numpy as np
import pytest
import torch

from cuniform_torch import make_system, read_table, rollout
from cuniform_torch.metrics import level_uniformity
from cuniform_torch.policies import UniformPolicy
from cuniform_torch.tables import TableError
from eval.common.graph_sampling import GraphSampler
from eval.common.methods import PAPER, Sources, make_controller, methods_of, parse_methods, sample_states
from eval.paper import coverage as coverage_exp
from eval.paper.reachable import reachable


@pytest.fixture(scope="module")
def dubins_table_path(dubins_table, tmp_path_factory):
    from cuniform_torch import write_table

    path = tmp_path_factory.mktemp("tables") / "dubins.npz"
    write_table(path, dubins_table)
    return path


@pytest.fixture(scope="module")
def sources(dubins_table_path, tmp_path_factory):
    return Sources(table=dubins_table_path, coverage_table=dubins_table_path, policy=tmp_path_factory.mktemp("x") / "none.pt")


class TestGraphSampler:
    def test_sequences_follow_arcs_with_flow(self, dubins_table_path):
        table = read_table(dubins_table_path)
        g = GraphSampler(table)
        rows = g.sample_rows(2000, generator=torch.Generator().manual_seed(0))  # [N, T+1]
        assert rows.shape == (2000, table.horizon + 1)
        out_flow = np.bincount(table.arcs[:, 0], weights=table.arc_flow, minlength=len(table.cells))
        # an arc that carries flow, or any arc of a cell whose arcs all carry none
        allowed = {(int(a), int(b)) for (a, b), f in zip(table.arcs, table.arc_flow) if f > 0 or out_flow[a] == 0}
        steps = {(int(a), int(b)) for a, b in zip(rows[:, :-1].reshape(-1), rows[:, 1:].reshape(-1))}
        assert steps <= allowed
        assert any(out_flow[a] > 0 for a, _ in steps)
        for t in range(table.horizon + 1):  # each sequence is at level t at step t
            lo, hi = table.level_offsets[t], table.level_offsets[t + 1]
            assert bool(((rows[:, t] >= lo) & (rows[:, t] < hi)).all())

    def test_first_step_frequencies_match_the_flow(self, dubins_table_path):
        table = read_table(dubins_table_path)
        rows = GraphSampler(table).sample_rows(20000, horizon=1, generator=torch.Generator().manual_seed(1))
        first = table.arcs[:, 0] == 0
        expected = table.arc_flow[first] / table.arc_flow[first].sum()
        seen = np.array([(rows[:, 1] == int(to)).float().mean().item() for to in table.arcs[first, 1]])
        assert np.allclose(seen, expected, atol=0.015)

    def test_a_table_without_arcs_is_refused(self, dubins_table_path):
        table = read_table(dubins_table_path)
        table.arcs = None
        with pytest.raises(TableError, match="flow graph"):
            GraphSampler(table)


def test_uniform_policy_rows_are_uniform():
    system = make_system("dubins")
    p = UniformPolicy(system)
    probs = p.action_probs(torch.zeros(7, 3), 0)
    assert torch.allclose(probs, torch.full((7, 5), 0.2))
    states, actions = rollout(system, p, torch.zeros(3), 4000, 3, torch.Generator().manual_seed(0))
    counts = torch.bincount(torch.round(actions[:, 0, 0] / (torch.pi / 8)).long() + 2, minlength=5).double() / 4000
    assert torch.allclose(counts, torch.full((5,), 0.2, dtype=torch.float64), atol=0.03)


def test_every_method_samples_and_every_closed_loop_method_commands(sources):
    paper = methods_of(PAPER)
    for m in parse_methods([k for k in paper if k != "cu_mlp" and paper[k].open_loop], benchmark=PAPER,
                           closed_loop=False):
        states = sample_states(m, sources, 50, 4, torch.Generator().manual_seed(0))
        assert states.shape == (50, 5, 3) and bool(torch.isfinite(states).all())
    cost = lambda s, a: ((s[:, :, :2] - torch.tensor([1.0, 0.0])) ** 2).sum(dim=(1, 2))  # noqa: E731
    for m in parse_methods([k for k in paper if k != "cu_mlp" and paper[k].closed_loop], benchmark=PAPER,
                           closed_loop=True):
        u = make_controller(m, sources, cost, 64, 5, seed=0).command(torch.zeros(3))
        assert u.shape == (1,)
    with pytest.raises(ValueError, match="unknown method"):
        parse_methods(["mppi_huge"], benchmark=PAPER, closed_loop=False)


def test_coverage_experiment_orders_the_methods_as_the_paper_does(sources):
    cfg = coverage_exp.CoverageConfig(methods=["mppi_low", "mppi_high", "uniform", "cu_graph"], samples=[500], seeds=2)
    result = coverage_exp.run(cfg, sources, progress=False)
    cells = {r["method"]: r["cells_mean"] for r in result["results"]}
    assert cells["mppi_low"] < cells["mppi_high"] < cells["uniform"] < cells["cu_graph"]
    reach = result["reachable"]["total"]
    for r in result["results"]:
        assert 0 < r["pct_reachable"] == pytest.approx(100 * r["cells_mean"] / reach)
        assert len(r["per_level_mean"]) == result["horizon"] + 1
    assert result["results"][0]["paper"] == 23  # Table I, N = 500, MPPI low
    assert "| 500 |" in coverage_exp.markdown(result)


def test_reachable_cells_are_what_rollouts_reach(dubins_table_path):
    system = read_table(dubins_table_path).make_system()
    reach = reachable(system, 4)
    from cuniform_torch.grid.cells import Grid

    grid = Grid.of(system)
    states, _ = rollout(system, UniformPolicy(system), torch.zeros(3, dtype=torch.float64), 3000, 4,
                        torch.Generator().manual_seed(0))
    for t in range(5):
        seen = torch.unique(grid.cells(states[:, t]), dim=0)
        ref = {tuple(c) for c in reach.level_cells[t].tolist()}
        assert {tuple(c) for c in seen.tolist()} <= ref  # rollouts never leave the enumerated set
        assert len(seen) >= 0.9 * len(ref) or len(ref) > 3000 // 2


def test_uniformity_stats_of_exact_uniform_draws_and_of_a_point_mass():
    ref = torch.stack([torch.arange(10), torch.zeros(10, dtype=torch.long)], dim=1)  # 10 cells
    uniform = ref.repeat(100, 1)  # every cell exactly 100 times
    s = level_uniformity(uniform, ref, torch.Generator().manual_seed(0))
    assert s["tv"] == pytest.approx(0.0) and s["entropy"] == pytest.approx(1.0) and s["outside"] == 0.0
    point = torch.tensor([[0, 0]] * 500 + [[99, 0]] * 500)  # half in one cell, half outside
    s = level_uniformity(point, ref)
    assert s["outside"] == pytest.approx(0.5)
    expected_tv = 0.5 * (abs(0.5 - 0.1) + 9 * 0.1) + 0.5 * 0.5
    assert s["tv"] == pytest.approx(expected_tv)


def test_report_quick_runs_end_to_end(tmp_path, capsys):
    from eval.report import main

    assert main(["--quick", "--out", str(tmp_path / "out"), "--runs", str(tmp_path / "runs")]) == 0
    root = tmp_path / "out" / "quick"
    text = (root / "report.md").read_text()
    for heading in ("## Coverage", "## Uniformity", "## Figures", "Machine:", "# Navigation benchmark: barn"):
        assert heading in text
    figures = sorted((root / "figures").glob("*.png"))
    assert {"coverage_vs_n.png", "trajectory_fans.png", "uniformity_per_level.png"} <= {f.name for f in figures}
    for f in figures:
        image = matplotlib.image.imread(f)
        assert image.ndim == 3 and image.shape[0] > 100
    for name in ("coverage", "uniformity"):
        json.loads((root / "eval" / f"{name}.json").read_text())
    events = list((tmp_path / "runs" / "quick").rglob("events.out.tfevents.*"))
    assert {p.parent.name for p in events} >= {"cu_table", "mppi_high", "figures"}
    # a second run reuses every table, the policy and every experiment's result: nothing is rewritten
    outputs = sorted([*root.glob("*.npz"), *root.glob("*.pt"), *(root / "eval").glob("*.json")])
    assert {p.name for p in outputs} >= {"dubins.npz", "dubins_cov.npz", "dubins.policy.pt", "coverage.json",
                                         "uniformity.json", "sudden_obstacle.json", "cluttered.json"}
    before = {p: p.stat().st_mtime_ns for p in outputs}
    first = capsys.readouterr().out  # what cost what: the stage table ends the run, each build's command below
    table = first[first.index("\nstage "):]
    for row in ("tables and policy", "  precompute.build dubins.npz", "  precompute.build dubins_cov.npz",
                "  training.distill dubins.policy.pt", "coverage", "navigation (short)", "total"):
        assert f"\n{row} " in table
    assert "Stage times (what cost what):" in text and "  precompute.build dubins.npz" in text
    assert main(["--quick", "--out", str(tmp_path / "out"), "--runs", str(tmp_path / "runs")]) == 0
    out = capsys.readouterr().out
    assert {p: p.stat().st_mtime_ns for p in outputs} == before
    reused = {line.removeprefix("reusing ") for line in out.splitlines() if line.startswith("reusing ")}
    assert reused == {str(p) for p in outputs if p.suffix != ".pt" or p.name == "dubins.policy.pt"}
    n = len(reused)
    assert f"reused {n} of {n} outputs of earlier runs" in out and "$ python -m" not in out  # no build, no distill
    assert f"Reused from an earlier run ({n} of {n} outputs" in (root / "report.md").read_text()


def test_the_stage_table_says_what_cost_what():
    from eval.report import Stages

    stages = Stages()
    stages.stage("tables", lambda: stages.run_step("precompute.build", ["--out", "x/t.npz"], lambda argv: None))
    stages.stage("coverage", lambda: None)
    stages.timings.update(tables=3.0, coverage=1.0, total=4.0)
    stages.steps["tables"] = [("precompute.build t.npz", 2.5)]
    lines = stages.table().splitlines()
    assert lines[0].split() == ["stage", "seconds", "share"]
    assert [line.split() for line in lines[1:]] == [["tables", "3.0", "75.0%"], ["precompute.build", "t.npz", "2.5",
                                                    "62.5%"], ["coverage", "1.0", "25.0%"], ["total", "4.0", "100.0%"]]
    assert lines[2].startswith("  precompute.build t.npz")


def test_the_report_builds_its_tables_on_the_commands_one_thread(tmp_path, monkeypatch):
    import precompute.api
    import training.distill
    from eval.common.paths import OutputPaths
    from eval.report import Stages, build_inputs

    seen = []

    def build(system, config, *, coverage, out, **kwargs):  # the threads it ran with; an empty file: the table
        seen.append((out.name, torch.get_num_threads(), config.horizon, coverage is not None))
        out.write_bytes(b"")

    monkeypatch.setattr(precompute.api, "build_table", build)  # the library function eval.report calls
    monkeypatch.setattr(training.distill, "distill", lambda cfg: None)
    threads = torch.get_num_threads()
    stages = Stages()
    stages.stage("tables and policy", lambda: build_inputs(OutputPaths(tmp_path, quick=True), tmp_path / "runs",
                                                           stages))
    assert seen == [("dubins.npz", 1, 10, False), ("dubins_cov.npz", 1, 10, True)]  # as the command (--threads 1)
    assert torch.get_num_threads() == threads
    assert [step for step, _ in stages.steps["tables and policy"]] == [
        "precompute.build dubins.npz", "precompute.build dubins_cov.npz", "training.distill dubins.policy.pt"]
