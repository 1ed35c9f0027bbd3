"""Lockstep episodes (eval.navigate.lockstep, --lockstep N) give the serial run's records, and the core's trace hook.

Short clutter episodes (a 6-step table, 16 s limits: collisions at different steps and timeouts, so robots
retire mid-batch; obstacles sensed per robot) of each method family, run one at a time and as one batch: the
records are equal, bit for bit, because a robot's arithmetic in the library does not depend on the batch
(tests/test_batch_invariance.py).
"""

from __future__ import annotations

import json
from dataclasses import replace

import pytest
import torch

from cuniform_torch import MPPI, make_system
from eval.navigate.episode import NavContext, run_nav_episode
from eval.navigate.lockstep import LOCKSTEP_CLOCK, lockstep_batches, run_lockstep
from eval.navigate.robot_files import ensure_table
from eval.navigate.run import NavConfig, main, make_jobs, run
from precompute.worlds.robot import NAV_ROBOT
from precompute.worlds.tasks import TIME_LIMITS, make_tasks

ROBOT = replace(NAV_ROBOT, horizon=6)  # a 6-step table builds in about a second
TIMING = ("cycle_hist", "wall_s", "clock", "lockstep")
"""the fields a lockstep record may differ in (timing) or adds"""


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    folder = tmp_path_factory.mktemp("lockstep_cache")
    ensure_table(ROBOT, folder, quiet=True)
    return folder


@pytest.fixture(scope="module")
def ctx(cache, tmp_path_factory):
    return NavContext(table=str(ensure_table(ROBOT, cache, quiet=True)), horizon=6,
                      map_policy=str(_map_policy_file(tmp_path_factory.mktemp("map") / "m.pt")), record_path=True)


def _map_policy_file(path):
    """An untrained, seeded map policy of the robot (the plumbing, not the quality, is under test)."""
    from cuniform_torch.maps import MapPolicy, MapPolicyConfig, map_policy_checkpoint, save_map_policy
    from cuniform_torch.systems import system_to_json

    system = ROBOT.make_system()
    torch.manual_seed(0)
    config = MapPolicyConfig(state_dim=3, num_actions=7, horizon=ROBOT.horizon, periodic=[False, False, True],
                             feature_scale=[1.0, 1.0, 1.0],
                             patch={"shape": [24, 24], "resolution": 0.1, "origin": [-1.2, -1.2]},
                             hidden=16, layers=1, embed=8, channels=4)
    policy = MapPolicy(config, system, system.action_set(dtype=torch.float32))
    save_map_policy(path, map_policy_checkpoint(policy, system_to_json(system, ROBOT.horizon)))
    return path


def _jobs(method: str, count: int = 5, budget: int = 32):
    tasks = make_tasks("clutter", ROBOT.radius, count, seed=0, split="test",
                       time_limits={**TIME_LIMITS, "clutter": 16.0})
    return make_jobs(tasks, [method], [budget], 1, seed=0)


def _without_timing(rec: dict) -> dict:
    return {k: v for k, v in rec.items() if k not in TIMING}


@pytest.mark.parametrize("method", ["mppi_1.0", "cu_table", "cumppi", "cfu_mppi"])
def test_lockstep_records_are_the_serial_records_but_for_timing(ctx, method):
    jobs = _jobs(method)
    serial = [run_nav_episode(job, ctx) for job in jobs]
    batch = run_lockstep(jobs, ctx)
    assert [_without_timing(r) for r in batch] == serial_fields(serial)
    assert len({r["steps"] for r in serial}) > 1, "the robots should retire at different steps"
    for rec in batch:
        assert rec["clock"] == LOCKSTEP_CLOCK and rec["lockstep"] == len(jobs)
        assert sum(rec["cycle_hist"].values()) == rec["cycles"] == rec["steps"]


def serial_fields(records: list[dict]) -> list[dict]:
    return [_without_timing(r) for r in records]


def test_batches_are_one_method_and_budget_in_job_order():
    jobs = make_jobs(make_tasks("gaps", 0.2, 3), ["mppi_1.0", "cu_table"], [16, 32], 1, seed=0)
    batches = lockstep_batches(jobs, 2)
    assert all(len({(j.method, j.budget) for j in b}) == 1 and 1 <= len(b) <= 2 for b in batches)
    assert sorted(j.key for b in batches for j in b) == sorted(j.key for j in jobs)
    assert [j.task.task_id for j in batches[0] + batches[1]] == [0, 1, 2]
    with pytest.raises(ValueError, match="at least 1"):
        lockstep_batches(jobs, 0)
    with pytest.raises(ValueError, match="one method at one budget"):
        run_lockstep(jobs[:2], NavContext(table="unused"))


def test_the_benchmark_run_with_lockstep_writes_the_serial_outcomes(cache, tmp_path):
    cfg = NavConfig(suite="gaps", tasks=3, budgets=(16,), methods=("mppi_1.0",), repeats=1, horizon=6)
    serial = run(cfg, tmp_path / "serial", ROBOT, cache, progress=False)
    batched = run(replace(cfg, lockstep=2), tmp_path / "lockstep", ROBOT, cache, progress=False)
    assert batched["summary"][0]["n"] == serial["summary"][0]["n"] == 3

    def records(folder):
        lines = (folder / "episodes.jsonl").read_text().splitlines()
        return sorted((json.loads(line) for line in lines), key=lambda r: r["key"])

    assert [_without_timing(r) for r in records(tmp_path / "lockstep")] == \
        [_without_timing(r) for r in records(tmp_path / "serial")]
    assert {r["clock"] for r in records(tmp_path / "lockstep")} == {LOCKSTEP_CLOCK}
    assert all("clock" not in r for r in records(tmp_path / "serial"))


def test_the_command_with_lockstep_writes_no_equal_compute_view(cache, tmp_path, capsys):
    out = tmp_path / "o"
    assert main(["--suite", "gaps", "--tasks", "2", "--budgets", "16", "--methods", "mppi_1.0", "--horizon", "6",
                 "--lockstep", "2", "--out", str(out), "--cache", str(cache), "--quiet"]) == 0
    assert "no equal-compute view" in capsys.readouterr().out
    assert (out / "results.md").is_file() and not (out / "budget.md").exists()


def test_lockstep_flag_refuses_a_batch_of_none(capsys, tmp_path):
    with pytest.raises(SystemExit) as exc:
        main(["--suite", "gaps", "--lockstep", "0", "--out", str(tmp_path / "o")])
    assert exc.value.code != 0
    assert "--lockstep: must be an integer in [1, 4096], got 0" in capsys.readouterr().err
    with pytest.raises(ValueError, match="--lockstep must be an integer >= 1"):
        run(NavConfig(suite="gaps", lockstep=0), tmp_path / "o2")


# ------------------------------------------------------------------------------------------ the core's trace hook

def _goal_cost(states, actions):
    return (states[..., 1:, :2] - torch.tensor([2.0, 1.0])).square().sum(dim=-1).sum(dim=-1)


@pytest.mark.parametrize("robots", [1, 3])
def test_on_plan_sees_each_commands_result_and_changes_nothing(robots):
    dubins = make_system("dubins")
    make = lambda: MPPI(dubins, _goal_cost, num_samples=32, horizon=6, seed=list(range(robots)),  # noqa: E731
                        num_robots=robots)
    plain, traced = make(), make()
    seen = []
    traced.on_plan = seen.append
    state = torch.zeros(robots, 3) if robots > 1 else torch.zeros(3)
    for step in range(3):
        u = traced.command(state)
        assert torch.equal(u, plain.command(state))
        assert len(seen) == step + 1 and torch.equal(seen[-1].command, u)
        assert seen[-1].costs.shape == ((robots, 32) if robots > 1 else (32,))
    result = traced.command_result(state)
    assert seen[-1] is result
    traced.on_plan = None
    traced.command(state)
    assert len(seen) == 4


def test_on_plan_must_be_callable():
    ctrl = MPPI(make_system("dubins"), _goal_cost, num_samples=8, horizon=4)
    with pytest.raises(TypeError, match="on_plan must be a callable"):
        ctrl.on_plan = 3  # type: ignore[assignment]
