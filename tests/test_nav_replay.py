"""Replaying a stored navigation episode (python -m eval.navigate replay): it reproduces the record, traces every
command, draws it; bad keys and files are one clear error; the trace leaves the benchmark's records unchanged."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from test_cli_errors import _one_error
from test_navigate import Straight  # a controller without plan(): it always drives straight

from cuniform_torch.sampling import GaussianSampler
from eval.common.methods import METHODS, NAVIGATE, Method
from eval.navigate.episode import NavContext, NavJob, run_nav_episode
from eval.navigate.replay import compare_records, main, replay_episode
from eval.navigate.robot_files import ensure_table
from eval.navigate.run import NavConfig, run
from precompute.worlds.robot import NAV_ROBOT
from precompute.worlds.suites import SuiteError
from precompute.worlds.tasks import make_task, make_tasks

ROBOT = replace(NAV_ROBOT, horizon=6)  # a 6-step table builds in about a second
SAME = ("key", "outcome", "success", "time", "path_length", "steps", "cycles", "seed")  # not the wall times


@pytest.fixture(scope="module")
def bench(tmp_path_factory):
    """A tiny benchmark folder: 3 gaps x mppi_1.0 / cu_table at K = 16; (folder, cache, records by key)."""
    root = tmp_path_factory.mktemp("replay")
    cfg = NavConfig(suite="gaps", tasks=3, budgets=(16,), methods=("mppi_1.0", "cu_table"), repeats=1, horizon=6)
    run(cfg, root / "run", ROBOT, root / "cache", progress=False)
    records = [json.loads(line) for line in (root / "run" / "episodes.jsonl").read_text().splitlines() if line]
    return root / "run", root / "cache", {r["key"]: r for r in records}


def _collision_key(records: dict) -> str:
    keys = [k for k, r in records.items() if r["outcome"] == "collision"]
    assert keys, "the tiny run should hold a collision (an offset gap at K = 16)"
    return keys[0]


def test_replay_reproduces_the_stored_episode_traces_each_command_and_draws_it(bench, tmp_path, capsys):
    out, cache, records = bench
    key = _collision_key(records)
    png, js = tmp_path / "replay.png", tmp_path / "replay.json"
    assert main(["--out", str(out), "--key", key, "--cache", str(cache), "--png", str(png), "--json", str(js)]) == 0
    printed = capsys.readouterr().out
    assert "reproduced" in printed and "warning" not in printed
    assert "collision-free proposal was" in printed or "no command ever had" in printed
    assert png.is_file() and png.stat().st_size > 10_000
    got = json.loads(js.read_text())
    stored = records[key]
    assert {k: got["replayed"][k] for k in SAME} == {k: stored[k] for k in SAME}
    assert len(got["trace"]) == stored["steps"] == len(got["replayed"]["path"]) - 1
    shares = [e["free_share"] for e in got["trace"]]
    assert all(0.0 <= s <= 1.0 for s in shares) and shares[0] > 0  # the start is in free space
    assert [e["t"] for e in got["trace"]] == pytest.approx([0.2 * k for k in range(stored["steps"])])
    s = got["summary"]
    assert s["outcome"] == "collision" and s["commands"] == stored["steps"]
    assert s["no_free_share"] == pytest.approx(sum(x == 0 for x in shares) / len(shares))
    last = max(k for k, x in enumerate(shares) if x > 0)
    assert s["last_free_s"] == pytest.approx(stored["time"] - 0.2 * last)


def test_default_png_goes_under_the_folder_and_a_goal_reproduces(bench):
    out, cache, records = bench
    key = next(k for k, r in records.items() if r["outcome"] == "goal")
    got = replay_episode(out, key, cache=cache)
    assert compare_records(got["stored"], got["replayed"]) == []
    assert main(["--out", str(out), "--key", key, "--cache", str(cache)]) == 0
    assert (out / "replay" / (key.replace("/", "_") + ".png")).is_file()


def test_a_changed_record_is_reported_as_not_reproduced(bench):
    out, cache, records = bench
    got = replay_episode(out, _collision_key(records), cache=cache)
    differ = compare_records({**got["stored"], "steps": got["stored"]["steps"] + 1}, got["replayed"])
    assert len(differ) == 1 and differ[0].startswith("steps")
    assert compare_records(got["stored"], {**got["replayed"], "path_length": got["replayed"]["path_length"] + 1e-3})


def test_an_unknown_key_or_a_wrong_source_file_is_one_clear_error(bench, tmp_path, capsys):
    out, cache, records = bench
    key = next(iter(records))
    assert main(["--out", str(out), "--key", "gaps/7/cu_table/16/0", "--cache", str(cache)]) == 2
    _one_error(capsys, "no episode 'gaps/7/cu_table/16/0'", "6 episodes", "gaps/")
    other = tmp_path / "other.npz"
    other.write_bytes(ensure_table(ROBOT, cache, quiet=True).read_bytes() + b"\0")
    assert main(["--out", str(out), "--key", key, "--cache", str(cache), "--table", str(other)]) == 2
    _one_error(capsys, f"--table {other}", "not the file the run used")
    assert main(["--out", str(tmp_path), "--key", key, "--cache", str(cache)]) == 2
    _one_error(capsys, "no settings.json")
    assert main(["--out", str(out), "--key", key, "--cache", str(cache), "--barn-file", str(other)]) == 0  # not barn
    capsys.readouterr()


def test_the_trace_leaves_every_record_unchanged(bench, monkeypatch):
    _, cache, _ = bench
    monkeypatch.setitem(METHODS, "straight", Method("straight", "always straight", "mppi", Straight, GaussianSampler,
                                                   0.0, benchmarks=(NAVIGATE,)))
    ctx = NavContext(table=str(ensure_table(ROBOT, cache, quiet=True)), horizon=6)
    task = make_task("gaps", 1, ROBOT.radius, count=3, time_limits={"gaps": 8.0})
    for method in ("mppi_1.0", "cu_table", "cumppi", "straight"):
        job = NavJob(task, method, 16, seed=3)
        trace: list = []
        plain, traced = run_nav_episode(job, ctx), run_nav_episode(job, ctx, trace=trace)
        assert {k: plain[k] for k in SAME} == {k: traced[k] for k in SAME}, method
        assert len(trace) == (0 if method == "straight" else plain["steps"]), method


def test_make_task_is_the_task_make_tasks_makes():
    for suite, count, seed in (("gaps", 4, 0), ("forest", 1, 3), ("barn", 1, 0)):
        for task in make_tasks(suite, 0.2, count, seed=seed):
            one = make_task(suite, task.task_id, 0.2, seed=seed, count=count)
            assert (one.suite, one.start, one.goal, one.bounds, one.time_limit, one.sensing_range) == \
                (task.suite, task.start, task.goal, task.bounds, task.time_limit, task.sensing_range)
            assert np.array_equal(one.discs, task.discs) and np.array_equal(one.walls, task.walls)
    with pytest.raises(SuiteError, match="no map 12345"):
        make_task("barn", 12345, 0.2)
    with pytest.raises(SuiteError, match="not in a sweep of 9"):
        make_task("gaps", 9, 0.2)


def test_a_map_policy_or_barn_file_other_than_the_runs_is_one_clear_error(bench, tmp_path):
    _, cache, records = bench
    from eval.navigate.replay import _barn_file, _checked_sources

    policy = tmp_path / "other.map_policy.pt"
    policy.write_bytes(b"not the run's policy")
    table = str(ensure_table(ROBOT, cache, quiet=True))
    settings = dict(suite="clutter", horizon=6, sources=dict(table=None, map_policy="0123456789abcdef"))
    record = dict(records[next(iter(records))], method="cfu_mppi")
    with pytest.raises(ValueError, match=f"--map-policy {policy} is not the file the run used"):
        _checked_sources(settings, record, ROBOT, cache, {"table": table, "map_policy": policy})
    with pytest.raises(ValueError, match="cfu_mppi needs a map policy for this robot"):
        _checked_sources(settings, record, ROBOT, cache, {"table": table})
    barn = dict(suite="barn", barn_file=None)  # the shipped file
    assert _barn_file(tmp_path, barn, None) is None
    with pytest.raises(ValueError, match="the run used the shipped BARN file, not --barn-file"):
        _barn_file(tmp_path, barn, policy)
    with pytest.raises(ValueError, match="another BARN file .* not the shipped BARN file"):
        _barn_file(tmp_path, dict(barn, barn_file="0123456789abcdef"), None)
