"""eval.navigate.budget: methods judged at equal cycle time. A planted folder (written through EpisodeStore, so its
records are valid) whose right answers are known: which K fits each budget by its p95 (not its median, not the
largest K), the success numbers, a method that fits no K, and the paired test against the best Gaussian baseline
at its own fitting K, over the (task, seed) episodes both ran."""

from __future__ import annotations

import pytest

from eval.common.methods import NAVIGATE, methods_of
from eval.navigate.budget import FAMILIES, family_of, judge, judge_folder, main, pareto_front, render, winners
from eval.navigate.records.cycle_hist import cycle_histogram
from eval.navigate.records.stats import mcnemar_exact_p
from eval.navigate.records.store import EpisodeStore

SUITE = "barn"


def _settings() -> dict:
    """A complete settings record (the shape eval.navigate.run.settings_record writes)."""
    robot = dict(system="dubins", params=dict(speed=0.5, dt=0.2), radius=0.2, horizon=6)
    return dict(suite=SUITE, seed=0, sensing_range=3.0, horizon=6, lambda_=0.5, collision_penalty=1e6,
                cost_resolution=0.01, robot=robot, time_limit=30.0, barn_file=None,
                sources=dict(table="00000000000000aa", coverage_table=None, policy=None))


def _records(method: str, k: int, outcomes: str, ms: float, tail_ms: float | None = None, first_task: int = 0,
             **extra) -> list[dict]:
    """One record per character of ``outcomes`` ("1" goal, "0" collision) on tasks ``first_task``.. (seed 100 +
    task, the same for every method and K: paired), each of 20 commands at ``ms`` (2 of them at ``tail_ms``)."""
    times = [ms / 1e3] * 20 if tail_ms is None else [ms / 1e3] * 18 + [tail_ms / 1e3] * 2
    out = []
    for i, o in enumerate(outcomes):
        t = first_task + i
        out.append(dict(key=f"{SUITE}/{t}/{method}/{k}/0", suite=SUITE, task_id=t, method=method, budget=k,
                        seed=100 + t, repeat=0, outcome="goal" if o == "1" else "collision", success=o == "1",
                        time=3.2, path_length=1.6, steps=20, cycles=20, cycle_hist=cycle_histogram(times),
                        wall_s=0.1, **extra))
    return out


def _planted() -> list[dict]:
    """The planted cells (ms: p95 cycle time; at 5 ms the right picks are in the comments)."""
    return [
        *_records("mppi_0.3", 16, "1010101010", 2), *_records("mppi_0.3", 64, "1111111000", 4),  # 5 ms: K=64, 7/10
        *_records("mppi_0.3", 256, "1111111111", 12),                                            # the best baseline
        *_records("mppi_1.0", 16, "1110000000", 2), *_records("mppi_1.0", 64, "1111000000", 4),  # 5 ms: K=64, 4/10
        # method A: K=64 has a median of 3 ms but a p95 of 30 ms, so at 5 ms only K=16 fits (8/10 on tasks 0-9,
        # plus task 10, which no baseline ran: 9/11)
        *_records("cu_table", 16, "0111111101", 3), *_records("cu_table", 16, "1", 3, first_task=10),
        *_records("cu_table", 64, "1111111111", 3, tail_ms=30),
        # method B: fits 5 ms at K=64; K=256 is more successful but takes 8 ms
        *_records("cumppi", 16, "1100000000", 1), *_records("cumppi", 64, "1111111110", 4),
        *_records("cumppi", 256, "1111111111", 8),
        *_records("uniform", 16, "1111100000", 2), *_records("uniform", 64, "1111100000", 4),  # a tie: the faster K
        *_records("cu_mlp", 16, "1111111111", 50),                                              # fits no budget here
    ]


@pytest.fixture
def folder(tmp_path):
    """The planted records, written through the store's writer (in a shuffled order: pairs go by task, not line)."""
    store = EpisodeStore(tmp_path / "run")
    store.open(_settings())
    recs = _planted()
    for r in recs[::2] + recs[1::2][::-1]:
        store.append(r)
    return tmp_path / "run"


def _row(res: dict, budget: float, method: str) -> dict:
    (row,) = [r for r in res["budgets"] if r["budget_ms"] == budget and r["method"] == method]
    return row


def test_each_method_at_the_best_k_whose_p95_fits(folder):
    res = judge_folder(folder, [5, 10])
    picks = {r["method"]: (r["cell"] or {}).get("budget") for r in res["budgets"] if r["budget_ms"] == 5}
    assert picks == {"mppi_0.3": 64, "mppi_1.0": 64, "cu_table": 16, "cumppi": 64, "uniform": 16, "cu_mlp": None}
    a = _row(res, 5, "cu_table")
    assert a["fits"] == [16]  # K=64's median (3 ms) fits, its p95 (30 ms) does not
    assert (a["cell"]["n"], a["cell"]["successes"]) == (11, 9)
    assert a["cell"]["success_rate_low"] < 9 / 11 < a["cell"]["success_rate_high"]
    assert _row(res, 5, "cumppi")["fits"] == [16, 64]
    assert _row(res, 10, "cumppi")["cell"]["budget"] == 256  # 8 ms fits 10 ms: the most successful
    assert _row(res, 10, "mppi_0.3")["cell"]["budget"] == 64  # K=256 takes 12 ms


def test_a_method_that_fits_no_k_says_so(folder):
    res = judge_folder(folder, [5])
    row = _row(res, 5, "cu_mlp")
    assert row["cell"] is None and row["fits"] == [] and row["comparison"] is None
    assert row["fastest"]["budget"] == 16 and 45 < row["fastest"]["cycle_ms_p95"] < 55
    line = next(ln for ln in render(res).splitlines() if "| cu_mlp |" in ln and "5 ms" in ln)
    assert "no K fits (fastest: p95 48.7 ms at K = 16)" in line  # 50 ms, read from its histogram bin


def test_paired_against_the_best_baseline_at_its_own_k_over_the_same_tasks(folder):
    res = judge_folder(folder, [5, 1.5])
    assert _row(res, 5, "mppi_0.3")["is_baseline"] and _row(res, 5, "mppi_0.3")["baseline_k"] == 64
    c = _row(res, 5, "cu_table")["comparison"]
    # cu_table@16 "0111111101" vs mppi_0.3@64 "1111111000" on tasks 0-9; task 10 has no baseline episode
    assert (c["baseline"], c["n"], c["wins"], c["losses"]) == ("mppi_0.3@64", 10, 2, 1)
    assert (c["method_successes"], c["baseline_successes"]) == (8, 7)
    assert c["p_value"] == pytest.approx(mcnemar_exact_p(2, 1)) and c["verdict"] == "tie"
    b = _row(res, 5, "cumppi")["comparison"]  # "1111111110" vs "1111111000": 2 wins, no loss
    assert (b["method"], b["n"], b["wins"], b["losses"]) == ("cumppi@64", 10, 2, 0)
    assert b["p_value"] == pytest.approx(0.5)
    assert _row(res, 5, "mppi_1.0")["comparison"]["losses"] == 3
    # at 1.5 ms only cumppi@16 fits (1 ms): no baseline to pair with, said so
    assert _row(res, 1.5, "cumppi")["pairs_note"] == "no Gaussian baseline fits"
    assert _row(res, 1.5, "mppi_0.3")["pairs_note"] == "no K fits"


def test_without_gaussian_baselines_and_threads_notes(folder):
    settings, by_key = EpisodeStore(folder).load()
    res = judge(settings, list(by_key.values()), [5], baselines=())
    assert _row(res, 5, "cumppi")["pairs_note"] == "no Gaussian baseline in the folder"
    assert res["threads"].startswith("unknown")
    recs = [dict(r, threads=1) for r in by_key.values()]
    assert judge(settings, recs, [5])["threads"] == "1 (from the records)"


def test_each_method_against_the_best_of_the_other_families(folder):
    res = judge_folder(folder, [5])
    # at 5 ms: cumppi@64 9/10, cu_table@16 9/11, mppi_0.3@64 7/10, uniform@16 5/10, mppi_1.0@64 4/10
    (win,) = winners(res)
    assert (win["method"], win["cell"]["budget"], win["rival"], win["rival_k"]) == ("cumppi", 64, "cu_table", 16)
    a = _row(res, 5, "cu_table")  # C-Uniform table: its rival is CU-MPPI, another family
    assert (a["family"], a["rival"], a["rival_family"]) == ("C-Uniform table", "cumppi", "CU-MPPI")
    c = a["rival_comparison"]  # "0111111101" vs "1111111110" on tasks 0-9
    assert (c["baseline"], c["n"], c["wins"], c["losses"]) == ("cumppi@64", 10, 1, 2)
    assert _row(res, 5, "mppi_0.3")["rival"] == "cumppi"
    assert _row(res, 5, "cu_mlp")["rival_note"] == "no K fits" and _row(res, 5, "cu_mlp")["rival_comparison"] is None
    text = render(res)
    assert "## Against the best of the other families" in text and "5 ms: **cumppi** @ K = 64" in text
    line = next(ln for ln in text.split("## Against")[1].splitlines() if ln.startswith("| 5 ms | cu_table |"))
    assert "| C-Uniform table | 16 |" in line and "cumppi@64" in line and "1 / 2" in line
    # a rival is never of the method's own family: with only Gaussians fitting, they have none
    settings, by_key = EpisodeStore(folder).load()
    gauss = [r for r in by_key.values() if r["method"].startswith("mppi_")]
    row = next(r for r in judge(settings, gauss, [5])["budgets"] if r["method"] == "mppi_1.0")
    assert row["rival"] is None and row["rival_note"] == "no method of another family fits"


def test_every_method_of_the_registry_has_a_family():
    keys = [k for ks in FAMILIES.values() for k in ks]
    assert sorted(methods_of(NAVIGATE)) == sorted(keys)  # a new method must be given its family
    assert family_of("someone_elses") == "someone_elses" and family_of("cumppi_pipe") == "CU-MPPI"


def test_pareto_front():
    assert pareto_front([(1.0, 0.2), (2.0, 0.5), (3.0, 0.4), (4.0, 0.9), (4.0, 0.8)]) == [True, True, False, True,
                                                                                        False]


def test_command_writes_the_tables_and_the_figure(folder, tmp_path, capsys):
    md, png = tmp_path / "b.md", tmp_path / "b.png"
    assert main([str(folder), "--budgets-ms", "5", "10", "--out", str(md), "--figure", str(png)]) == 0
    text = md.read_text()
    assert "## Per method and K" in text and "## Time budgets" in text
    line = next(ln for ln in text.splitlines() if ln.startswith("| 5 ms | cu_table |"))
    assert "| 16 | 16 | 0.82 [" in line and "mppi_0.3@64" in line
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "wrote" in capsys.readouterr().out


@pytest.mark.parametrize("args, match", [
    (["--budgets-ms", "0"], "must be a finite number > 0"),
    (["--budgets-ms", "nan"], "must be a finite number"),
])
def test_bad_budgets_one_error(folder, capsys, args, match):
    with pytest.raises(SystemExit):
        main([str(folder), *args])
    err = capsys.readouterr().err
    assert match in err and len(err.strip().splitlines()) == 1


def test_bad_folders_one_error(tmp_path, capsys):
    assert main([str(tmp_path)]) == 2
    assert "no settings.json" in capsys.readouterr().err
    EpisodeStore(tmp_path / "empty").open(_settings())
    assert main([str(tmp_path / "empty")]) == 2
    err = capsys.readouterr().err
    assert "holds no episode" in err and len(err.strip().splitlines()) == 1


def test_lockstep_records_are_refused_their_cycles_are_a_batch_share():
    """A --lockstep run's cycle times are a batched command's share per robot: judging them as control cycles
    would credit batching to the method, so the view refuses them, naming why."""
    recs = _records("mppi_1.0", 64, "1111", 4) + _records("cu_table", 64, "1110", 4, clock="lockstep", lockstep=4)
    with pytest.raises(ValueError, match="--lockstep"):
        judge(_settings(), recs)
    judge(_settings(), _records("mppi_1.0", 64, "1111", 4))  # the serial records alone are judged
