"""The closed-loop MountainCarContinuous-v0 experiment (``python -m eval.mountain_car``)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from cuniform_torch.systems import make_system
from eval.mountain_car import episode
from eval.mountain_car import run as experiment
from eval.mountain_car.table_set import set_folder, set_spec
from precompute.table_set import parse_starts

pytest.importorskip("gymnasium")

BLIND = ["--seeds", "2", "--budget", "4", "--horizon", "4", "--max-steps", "30", "--quiet"]
"""tiny flags of a run without a table-set method (--set-grid would be refused: it does not apply)"""
TINY = [*BLIND, "--set-grid", "2x2"]


def test_the_cost_is_the_env_reward_plus_distance_until_the_goal():
    # positions after each of 3 model steps: never reaches; reaches at step 1 and rolls back; reaches at step 2
    p = torch.tensor([[-0.5, -0.3, 0.0], [0.5, 0.3, 0.2], [0.0, 0.45, 0.6]], dtype=torch.float64)
    states = torch.stack((p, torch.zeros_like(p)), dim=2)  # [3, 3, 2]
    u = torch.tensor([[1.0, -1.0, 0.5], [0.5, 1.0, 1.0], [-1.0, 0.2, 1.0]], dtype=torch.float64).unsqueeze(2)
    got = episode.trajectory_cost(states, u, repeat=5)
    act = 0.1 * 5  # the env's 0.1 u^2 per env step, over 5 env steps
    want = [act * (1 + 1 + 0.25) + (0.95 + 0.75 + 0.45),
            act * 0.25 - 100.0,  # only the reaching step is paid; the roll-back after it is not
            act * (1 + 0.04) + 0.45 - 100.0]
    torch.testing.assert_close(got, torch.tensor(want, dtype=torch.float64))


def test_the_set_covers_the_env_box_and_its_folder_names_its_parameters(tmp_path):
    spec = set_spec(repeat=5, horizon=30, grid=(13, 9))
    starts = parse_starts(spec["starts"], make_system("mountain_car"))
    assert starts.shape == (117, 2)
    assert starts.min(0).tolist() == [-1.2, -0.07] and starts.max(0).tolist() == [0.6, 0.07]
    folders = {set_folder(tmp_path, set_spec(r, t, g)) for r, t, g in [(5, 30, (13, 9)), (4, 30, (13, 9)),
                                                                        (5, 20, (13, 9)), (5, 30, (13, 8))]}
    assert len(folders) == 4


def test_an_episode_is_seeded_and_follows_the_env():
    a = episode.run_episode("mppi", 3, budget=8, horizon=4, repeat=5, max_steps=23, set_dir=None)
    b = episode.run_episode("mppi", 3, budget=8, horizon=4, repeat=5, max_steps=23, set_dir=None)
    a.pop("command_ms_median"), b.pop("command_ms_median")
    assert a == b  # the env's reset seed and the controller's seed
    assert not a["success"] and a["steps"] == 23 and a["commands"] == 5  # 4 full model steps, then 3 env steps
    assert -0.1 * 23 <= a["return"] < 0  # the env's action cost only, |u| <= 1


def test_the_experiment_runs_end_to_end_and_resumes(tmp_path, capsys):
    argv = [*TINY, "--out", str(tmp_path / "run"), "--cache", str(tmp_path / "sets")]
    assert experiment.main(argv) == 0
    printed = capsys.readouterr().out
    result = json.loads((tmp_path / "run" / "results.json").read_text())
    methods = list(episode.METHODS) if episode.have_pytorch_mppi() else [m for m in episode.METHODS if m != "pytorch_mppi"]
    assert result["methods"] == methods and [r["method"] for r in result["summary"]] == methods
    assert len(result["records"]) == 2 * len(methods)
    assert result["config"]["budget"] == 4 and result["config"]["max_steps"] == 30
    for row in result["summary"]:
        assert row["episodes"] == 2 and 0 <= row["success_ci95"][0] <= row["success_rate"] <= row["success_ci95"][1]
        assert np.isfinite(row["return_mean"]) and row["command_ms_median"] > 0
        assert (row["miss_rate"] is None) == (row["method"] not in episode.SET_METHODS)
        assert row["method"] in printed
    for record in result["records"]:
        assert record["steps"] == 30 or record["success"]
        if record["method"] in episode.SET_METHODS:
            assert 0 <= record["misses"] <= record["queries"] and record["queries"] > 0
    before = (tmp_path / "run" / "results.json").read_text()
    assert experiment.main(argv) == 0  # the same configuration: nothing to run again
    assert "resuming: " + str(2 * len(methods)) in capsys.readouterr().out
    assert json.loads((tmp_path / "run" / "results.json").read_text())["records"] == json.loads(before)["records"]


@pytest.mark.parametrize("flags,message", [(["--methods", "mppi,nope"], "unknown method(s) nope"),
                                           (["--budget", "1"], "--budget: must be an integer in [2, "),
                                           (["--seeds", "0"], "--seeds: must be an integer in [1, "),
                                           (["--set-grid", "1x5"], "--set-grid must be PxV")])
def test_bad_input_is_one_error_line(tmp_path, capsys, flags, message):
    try:
        code = experiment.main([*TINY, "--out", str(tmp_path), *flags])
    except SystemExit as exc:  # a bad count: argparse's exit, as it parses
        code = exc.code
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and message in err[0]
    assert not (tmp_path / "results.json").exists()


def test_missing_extras(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(experiment, "have_gymnasium", lambda: False)
    assert experiment.main([*TINY, "--out", str(tmp_path)]) == 2
    assert capsys.readouterr().err.strip() == f"error: {episode.GYM_MISSING}"
    monkeypatch.setattr(experiment, "have_gymnasium", lambda: True)
    monkeypatch.setattr(experiment, "have_pytorch_mppi", lambda: False)
    assert experiment.main([*BLIND, "--methods", "mppi,pytorch_mppi", "--out", str(tmp_path)]) == 0
    assert "pytorch_mppi is not installed" in capsys.readouterr().out
    assert json.loads((tmp_path / "results.json").read_text())["methods"] == ["mppi"]
    assert experiment.main([*BLIND, "--methods", "pytorch_mppi", "--out", str(tmp_path)]) == 2
