"""eval.bench.profile_split: a cProfile of controller commands split into sampling, cost and the rest."""

from __future__ import annotations

import cProfile
import time

import pytest
import torch

from cuniform_torch.controllers.mppi import MPPI
from cuniform_torch.systems import make_system
from eval.bench.profile_split import split
from precompute.cli import CLIError


def simulate(controller, commands: int) -> None:  # named as the simulator loop the split looks for
    x = torch.zeros(3)
    for _ in range(commands):
        controller.command(x)
    time.sleep(0.05)  # the harness's own time: 50 ms in all


def test_the_split_finds_a_slow_cost_and_the_harness(tmp_path):
    def cost(states, actions):  # 4 ms a command: the cost dominates
        time.sleep(0.004)
        return states[:, 1:, 0].neg().sum(dim=1)

    controller = MPPI(make_system("dubins"), cost, num_samples=32, horizon=5, seed=0)
    profiler = cProfile.Profile()
    profiler.runcall(simulate, controller, 10)
    profiler.dump_stats(tmp_path / "p.prof")
    row = split(tmp_path / "p.prof")
    assert row["commands"] == 10
    assert 4.0 <= row["cost"] < 20 and row["sampling"] < row["cost"], row
    assert row["sampling"] > 0 and row["rest of plan"] >= 0
    assert row["sampling"] + row["cost"] + row["rest of plan"] <= row["command"] + 1e-6
    assert 4.0 <= row["episode harness"] < 8.5, row  # 50 ms over 10 commands, beyond the commands (>= 4 ms each)


def test_a_file_that_is_not_a_profile_is_one_error(tmp_path):
    (tmp_path / "x.prof").write_text("not a profile")
    with pytest.raises(CLIError, match="not a readable cProfile output"):
        split(tmp_path / "x.prof")
    profiler = cProfile.Profile()
    profiler.runcall(sum, [1, 2])
    profiler.dump_stats(tmp_path / "y.prof")
    with pytest.raises(CLIError, match="no controller command"):
        split(tmp_path / "y.prof")
