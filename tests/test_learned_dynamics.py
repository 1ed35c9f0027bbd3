"""The costly-dynamics mode (issue 36): LearnedDubins and ``python -m eval.navigate --dynamics learned``."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import pytest
import torch

from cuniform_torch.systems import Dubins, check_system, se2_invariance_gap
from cuniform_torch.systems.learned import LearnedDubins, train_weights
from eval.navigate import episode as nav_episode
from eval.navigate.robot_files import ensure_table
from eval.navigate.run import NavConfig, main, run
from precompute.worlds.robot import NAV_ROBOT

ROBOT = replace(NAV_ROBOT, horizon=6)  # a 6-step table builds in about a second


@pytest.fixture(scope="module")
def robot() -> Dubins:
    return NAV_ROBOT.make_system()


@pytest.fixture(scope="module")
def model(robot) -> LearnedDubins:
    return LearnedDubins.of(robot)


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    folder = tmp_path_factory.mktemp("nav_cache")
    ensure_table(ROBOT, folder, quiet=True)
    return folder


def _held_out(n: int, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """States anywhere in a 20 m square, any heading, and turn rates in the robot's range (not the training draws:
    another seed, and every state, not only the origin)."""
    gen = torch.Generator().manual_seed(12345)
    x = (torch.rand(n, 3, generator=gen, dtype=torch.float64) * 2 - 1) * torch.tensor([10.0, 10.0, math.pi])
    u = (torch.rand(n, 1, generator=gen, dtype=torch.float64) * 2 - 1) * 1.5
    return x.to(dtype), u.to(dtype)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_one_step_error_against_dubins(robot, model, dtype):
    """Below 2 mm (4% of a 5 cm cell) and 0.01 rad (6% of a 10-degree cell) on held-out states and rates, and on
    the action set: the robot's tables look up the same cells."""
    x, u = _held_out(4096, dtype)
    u = torch.cat([u, robot.action_set(dtype).repeat(len(u) // 7 + 1, 1)[: len(u)]])  # + the 7 actions
    x = torch.cat([x, x])
    got, want = model.step(x, u), robot.step(x, u)  # [N, 3]
    assert got.dtype == dtype
    pos = (got[:, :2] - want[:, :2]).norm(dim=1).max().item()
    head = (torch.remainder(got[:, 2] - want[:, 2] + math.pi, 2 * math.pi) - math.pi).abs().max().item()
    assert pos < 2e-3 and head < 1e-2, (pos, head)
    assert bool((got[:, 2] >= -math.pi).all() and (got[:, 2] < math.pi).all())  # wrapped


def test_a_system_with_the_robots_grid(robot, model):
    check_system(model)
    assert model.cell_size == robot.cell_size and model.cell_offset == robot.cell_offset
    assert torch.equal(model.action_set(), robot.action_set())
    assert se2_invariance_gap(model) < 1e-9  # declared se2_invariant: the body-frame step makes it exact
    assert not hasattr(model, "scan")  # the point: rollouts run the step loop


def test_training_is_reproducible_from_a_seed(robot):
    args = (robot.speed, robot.dt, robot.max_omega, 16, 3, 64, 50)  # small: seconds
    first = train_weights(*args)
    train_weights.cache_clear()  # retrain, not the per-process copy
    again = train_weights(*args)
    assert all(torch.equal(a, b) for a, b in zip(first, again))
    other = train_weights(*args[:4], 4, *args[5:])
    assert not torch.equal(first[0], other[0])


def test_bad_parameters_are_one_clear_error(robot):
    with pytest.raises(ValueError, match="hidden"):
        LearnedDubins.of(robot, hidden=0)
    with pytest.raises(ValueError, match="seed"):
        LearnedDubins.of(robot, seed=-1)
    with pytest.raises(ValueError, match="'dubins' system"):
        LearnedDubins.of(model_free := object())  # noqa: F841


@pytest.mark.parametrize("dynamics", ["learned", "true"])
def test_the_flag_reaches_every_controller_and_not_the_simulator(cache, tmp_path, monkeypatch, dynamics):
    """With ``--dynamics learned`` each method's rollouts step LearnedDubins and the simulator the true Dubins;
    without it, no learned step runs."""
    calls: dict[str, int] = {"learned": 0}
    sim_systems: list[type] = []
    step = LearnedDubins.step

    def counted(self, x, u):
        calls["learned"] += 1
        return step(self, x, u)

    def simulate(system, *args, **kwargs):
        sim_systems.append(type(system))
        return real_simulate(system, *args, **kwargs)

    real_simulate = nav_episode.simulate
    monkeypatch.setattr(LearnedDubins, "step", counted)
    monkeypatch.setattr(nav_episode, "simulate", simulate)
    nav_episode._CACHE.clear()
    for method in ("mppi_1.0", "cu_table", "cumppi"):
        before = calls["learned"]
        cfg = NavConfig(suite="gaps", tasks=1, budgets=(16,), methods=(method,), repeats=1, horizon=6,
                        dynamics=dynamics)
        run(cfg, tmp_path / method, ROBOT, cache, progress=False)
        assert (calls["learned"] > before) == (dynamics == "learned"), method
        settings = json.loads((tmp_path / method / "settings.json").read_text())
        assert settings.get("dynamics", "true") == dynamics
    assert sim_systems and all(t is Dubins for t in sim_systems)


def test_a_robot_it_cannot_model_is_refused(tmp_path, capsys):
    code = main(["--suite", "gaps", "--tasks", "1", "--dynamics", "learned", "--system", "ks", "--out",
                 str(tmp_path / "o"), "--cache", str(tmp_path / "c"), "--quiet"])
    assert code != 0
    assert "models the Dubins robot only" in capsys.readouterr().err
