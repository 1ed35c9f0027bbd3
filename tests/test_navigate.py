"""The navigation benchmark (python -m eval.navigate): episodes, executors, resume, bad input."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import torch

from cuniform_torch.envs import Environment
from cuniform_torch.sampling import GaussianSampler
from eval.common.methods import METHODS, NAVIGATE, Method
from eval.navigate.episode import NavContext, NavJob, rasterize, run_nav_episode
from eval.navigate.robot_files import ensure_table
from eval.navigate.run import NavConfig, controller_seed, main, make_jobs, run
from precompute.parallel import ray_available
from precompute.worlds.barn import load_barn, pack_maps, write_barn
from precompute.worlds.geometry import clearance
from precompute.worlds.robot import NAV_ROBOT, preset_dict
from precompute.worlds.suites import SuiteError, forest, gaps
from precompute.worlds.tasks import barn_task, make_tasks

ROBOT = replace(NAV_ROBOT, horizon=6)  # a 6-step table builds in about a second
OUTCOME_FIELDS = ("key", "outcome", "success", "steps", "time", "path_length", "seed")


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    folder = tmp_path_factory.mktemp("nav_cache")
    ensure_table(ROBOT, folder, quiet=True)
    return folder


@pytest.fixture(scope="module")
def ctx(cache):
    return NavContext(table=str(ensure_table(ROBOT, cache, quiet=True)), horizon=6)


def _cfg(**kw) -> NavConfig:
    base = dict(suite="gaps", tasks=5, budgets=(16,), methods=("mppi_1.0", "cu_table"), repeats=1, horizon=6)
    base.update(kw)
    return NavConfig(**base)


def _outcomes(records):
    return sorted(tuple(r[f] for f in OUTCOME_FIELDS) for r in records)


class Straight:
    """A controller that always drives straight (turn rate 0), built the way a noise baseline is."""

    def __init__(self, system, cost_fn, noise_std=None, **kwargs):
        self.zero = torch.zeros(1)

    def command(self, state):
        return self.zero.to(state.dtype)


def test_straight_controller_fails_with_an_obstacle_ahead_and_succeeds_without(monkeypatch, ctx):
    monkeypatch.setitem(METHODS, "straight", Method("straight", "always straight", "mppi", Straight, GaussianSampler,
                                                   0.0, benchmarks=(NAVIGATE,)))
    empty = forest(0, length=12.0, num_discs=(0, 0), robot_radius=0.2, sensing_range=None)
    blocked = gaps(width=0.6, offset=1.5, robot_radius=0.2)  # the wall sits on the straight line
    open_gap = gaps(width=0.6, offset=0.0, robot_radius=0.2)
    got = {name: run_nav_episode(NavJob(task, "straight", 8, seed=0), ctx)
           for name, task in (("empty", empty), ("blocked", blocked), ("open", open_gap))}
    assert got["empty"]["outcome"] == "goal" and got["open"]["outcome"] == "goal"
    assert got["blocked"]["outcome"] == "collision"
    # the collision happens at the wall: 2.5 m of driving minus the robot's radius, in 0.1 m steps
    assert got["blocked"]["path_length"] == pytest.approx(2.5 - 0.2 + 0.1, abs=0.1)


def test_rasterized_cost_map_is_conservative_and_tight():
    task = barn_task(load_barn()[0], robot_radius=0.2)
    raster = rasterize(task.environment, 0.01)
    rng = np.random.default_rng(0)
    xy = torch.from_numpy(rng.uniform((-6, -1.5), (1.5, 15), size=(200_000, 2)))
    exact = task.environment.in_collision(xy)
    grid = raster.in_collision(xy)
    assert bool((grid | ~exact).all())  # every colliding point is marked (conservative)
    marked = raster.obstacles[0].contains(xy).numpy()  # the grid alone (the bounds are exact)
    d = clearance(Environment(task.environment.obstacles), xy.numpy())  # to the nearest inflated cylinder
    assert bool((d[marked] < 0.01 * np.sqrt(2) + 1e-9).all())  # marked points are within one cell diagonal
    assert marked.mean() < (d < 0).mean() * 1.2  # and the grid is tight: not much more than the obstacles


def test_serial_workers_and_ray_give_the_same_episodes(tmp_path, cache):
    cfg = _cfg()
    serial = run(cfg, tmp_path / "serial", ROBOT, cache, progress=False)
    workers = run(replace(cfg, workers=2), tmp_path / "workers", ROBOT, cache, progress=False)
    assert serial["run"]["episodes"] == 10
    assert _outcomes(serial_records(tmp_path / "serial")) == _outcomes(serial_records(tmp_path / "workers"))
    assert {r["outcome"] for r in serial_records(tmp_path / "serial")} != {"goal"}  # not a trivial slice
    assert [r["successes"] for r in serial["summary"]] == [r["successes"] for r in workers["summary"]]
    if not ray_available():
        pytest.skip("ray is not installed (pip install -e '.[ray]')")
    run(cfg, tmp_path / "ray", ROBOT, cache, ray_address="local", progress=False)
    assert _outcomes(serial_records(tmp_path / "serial")) == _outcomes(serial_records(tmp_path / "ray"))
    assert workers["summary"][0]["n"] == 5


def serial_records(folder):
    return [json.loads(line) for line in (folder / "episodes.jsonl").read_text().splitlines() if line]


def test_resume_skips_finished_episodes(tmp_path, cache, monkeypatch):
    out = tmp_path / "run"
    cfg = _cfg(tasks=2)
    run(cfg, out, ROBOT, cache, progress=False)
    first = serial_records(out)
    assert len(first) == 4
    ran = []
    import eval.navigate.execute as nav_exec
    real = nav_exec.run_nav_episode
    monkeypatch.setattr(nav_exec, "run_nav_episode", lambda job, c: ran.append(job.key) or real(job, c))
    again = run(cfg, out, ROBOT, cache, progress=False)
    assert ran == [] and again["run"]["episodes"] == 4 and again["run"]["ran"] == 0
    grown = run(replace(cfg, tasks=3, budgets=(16, 24)), out, ROBOT, cache, progress=False)
    assert len(ran) == 12 - 4 and grown["run"]["episodes"] == 12
    assert serial_records(out)[:4] == first  # finished records are kept as they were
    # a record cut short by a crash is dropped (with a warning) and its episode rerun
    with open(out / "episodes.jsonl", "ab") as f:
        f.write(b'{"key": "gaps/0/mp')
    ran.clear()
    with pytest.warns(UserWarning, match="incomplete last line"):
        run(replace(cfg, tasks=3, budgets=(16, 24)), out, ROBOT, cache, progress=False)
    assert ran == []


def test_resume_with_other_settings_is_refused(tmp_path, cache):
    run(_cfg(tasks=1), tmp_path, ROBOT, cache, progress=False)
    with pytest.raises(ValueError, match="lambda_"):
        run(_cfg(tasks=1, lambda_=1.0), tmp_path, ROBOT, cache, progress=False)


def test_controller_seeds_pair_methods_and_budgets():
    tasks = make_tasks("gaps", 0.2, count=2)
    jobs = make_jobs(tasks, ["mppi_1.0", "cu_table"], [16, 64], repeats=2, seed=3)
    by_task = {}
    for j in jobs:
        by_task.setdefault((j.task.task_id, j.repeat), set()).add(j.seed)
    assert all(len(s) == 1 for s in by_task.values())  # one seed per task and repeat, whatever the method
    assert len({next(iter(s)) for s in by_task.values()}) == 4  # different across tasks and repeats
    assert controller_seed("gaps", 0, 0, 3) != controller_seed("forest", 0, 0, 3)


def exit_code(argv) -> int:
    """main's exit code, whether it returns it or argparse exits with it."""
    try:
        return main(argv)
    except SystemExit as stop:
        return int(stop.code)


@pytest.mark.parametrize("argv, message", [
    (["--suite", "maze"], "maze"),
    (["--methods", "mppi_1.0", "magic"], "unknown method"),
    (["--budgets", "1", "64"], "--budgets: must be an integer in [2, "),
    (["--param", "speed=1"], "--param needs --system"),
    (["--starts", "3=0:1:3"], "--starts needs --system"),
    (["--system", "ks_speed", "--starts", "1=0:1:3"], "SE(2)-invariant"),
])
def test_bad_flags_fail_before_any_episode(argv, message, tmp_path, capsys):
    code = exit_code([*argv, "--out", str(tmp_path / "o"), "--cache", str(tmp_path / "c")])
    assert code == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "o" / "episodes.jsonl").exists() and not (tmp_path / "c").exists()


def test_map_file_in_another_format_is_refused(tmp_path, capsys):
    bad = tmp_path / "maps.npz"
    np.savez(bad, centers=np.zeros((3, 2)))
    assert exit_code(["--barn-file", str(bad), "--out", str(tmp_path / "o"), "--cache", str(tmp_path / "c")]) == 2
    err = capsys.readouterr().err
    assert "maps.npz" in err and err.count("\n") == 1


def test_start_in_collision_is_refused_when_the_suite_is_made(tmp_path):
    m = load_barn()[0]
    arrays = pack_maps([m])
    arrays["centers"] = np.concatenate((arrays["centers"], np.array([[-2.25, 3.0]], np.float32)))
    arrays["offsets"] = np.array([0, arrays["centers"].shape[0]])
    path = tmp_path / "blocked.npz"
    write_barn(path, arrays)
    with pytest.raises(SuiteError, match="barn task 0: the start"):
        make_tasks("barn", 0.2, barn_file=path)


def test_barn_file_flag_reads_another_file(tmp_path, cache, capsys):
    path = tmp_path / "two.npz"
    write_barn(path, load_barn()[:2])
    code = main(["--barn-file", str(path), "--budgets", "8", "--methods", "mppi_1.0", "--horizon", "6",
                 "--out", str(tmp_path / "o"), "--cache", str(cache), "--quiet",
                 "--table", str(ensure_table(ROBOT, cache, quiet=True))])
    assert code == 0
    result = json.loads((tmp_path / "o" / "results.json").read_text())
    assert result["tasks"]["task_ids"] == [m.map_id for m in load_barn()[:2]]
    assert (tmp_path / "o" / "success.png").read_bytes()[:4] == b"\x89PNG"


def test_barn_worlds_flag_converts_the_sample_world_to_shipped_map_0(tmp_path, cache):
    from pathlib import Path

    world = Path(__file__).parent / "data" / "barn" / "world_0.world"
    code = main(["--barn-worlds", str(world), "--budgets", "8", "--methods", "mppi_1.0", "--horizon", "6",
                 "--out", str(tmp_path / "o"), "--cache", str(cache), "--quiet",
                 "--table", str(ensure_table(ROBOT, cache, quiet=True))])
    assert code == 0
    converted, shipped = load_barn(tmp_path / "o" / "barn.npz"), load_barn()[0]
    assert [m.map_id for m in converted] == [0]
    order = lambda c: c[np.lexsort((c[:, 1], c[:, 0]))]  # noqa: E731
    np.testing.assert_allclose(order(converted[0].centers), order(shipped.centers), atol=1e-5)
    assert json.loads((tmp_path / "o" / "results.json").read_text())["tasks"]["task_ids"] == [0]


def test_opt_in_methods_run_from_given_files(tmp_path, cache):
    """cu_coverage and cu_mlp read the files given (here the max-flow table and a briefly distilled MLP)."""
    from training.distill import main as distill_main

    table = ensure_table(ROBOT, cache, quiet=True)
    policy = tmp_path / "p.pt"
    assert distill_main(["--tables", str(table), "--out", str(policy), "--epochs", "2", "--quiet",
                         "--logdir", str(tmp_path / "runs")]) == 0
    res = run(_cfg(tasks=1, methods=("cu_coverage", "cu_mlp")), tmp_path / "o", ROBOT, cache,
              given={"coverage_table": table, "policy": policy}, progress=False)
    assert [r["method"] for r in res["summary"]] == ["cu_coverage", "cu_mlp"]
    with pytest.raises(FileNotFoundError, match="--policy"):
        run(_cfg(tasks=1, methods=("cu_mlp",)), tmp_path / "o2", ROBOT, cache,
            given={"policy": tmp_path / "missing.pt"}, progress=False)


def test_a_robot_with_a_speed_drives_from_a_table_set(tmp_path):
    """--system ks_speed --starts SPEC: the robot's tables are a set over the speed, built once into the cache and
    recorded in the settings (a one-table robot's records keep no starts key)."""
    argv = ["--suite", "gaps", "--tasks", "1", "--repeats", "1", "--budgets", "8", "--methods", "cu_table",
            "--system", "ks_speed", "--starts", "3=0:1:3", "--horizon", "3", "--out", str(tmp_path / "o"),
            "--cache", str(tmp_path / "c"), "--quiet"]
    assert main(argv) == 0
    [folder] = [p for p in (tmp_path / "c").iterdir() if p.is_dir()]
    index = json.loads((folder / "tables.json").read_text())
    assert [t["start"][3] for t in index["tables"]] == [0.0, 0.5, 1.0]
    settings = json.loads((tmp_path / "o" / "settings.json").read_text())
    assert settings["robot"]["starts"] == "3=0:1:3" and settings["sources"]["table"]
    assert "starts" not in preset_dict(ROBOT)


def test_success_pivot_marks_methods_against_the_best_baseline():
    from eval.navigate.run import success_pivot

    def row(method, budget, rate):
        return dict(suite="barn", method=method, budget=budget, success_rate=rate, success_rate_low=rate - 0.1,
                    success_rate_high=min(1.0, rate + 0.1))

    summary = [row("mppi_1.0", 64, 0.9), row("cu_table", 64, 0.5), row("uniform", 64, 0.95)]
    comparisons = [dict(suite="barn", budget=64, method="cu_table", baseline="mppi_1.0", verdict="worse"),
                   dict(suite="barn", budget=64, method="uniform", baseline="mppi_1.0", verdict="tie")]
    lines = success_pivot(summary, comparisons).splitlines()
    assert "| mppi_1.0 | 0.90 [0.80, 1.00] (best) |" in lines
    assert "| cu_table | 0.50 [0.40, 0.60] - |" in lines
    assert "| uniform | 0.95 [0.85, 1.00] |" in lines


def test_store_merges_new_source_files_and_refuses_changed_ones(tmp_path):
    from test_bench_records import bench_settings

    from eval.navigate.records.store import EpisodeStore, StoreError

    aa, bb, cc, dd = (f"{c * 2:0>16}" for c in "abcd")  # digests as the run writes them: 16 hex digits
    base = bench_settings("barn", lambda_=0.5, sources=dict(table=aa, policy=None))
    EpisodeStore(tmp_path).open(base)
    EpisodeStore(tmp_path).open({**base, "sources": dict(table=aa, policy=bb)})  # the MLP joins
    assert json.loads((tmp_path / "settings.json").read_text())["sources"] == dict(table=aa, policy=bb)
    EpisodeStore(tmp_path).open(base)  # a later run without the MLP still fits
    with pytest.raises(StoreError, match="sources.policy"):
        EpisodeStore(tmp_path).open({**base, "sources": dict(table=aa, policy=cc)})
    with pytest.raises(StoreError, match="sources.table"):
        EpisodeStore(tmp_path).open({**base, "sources": dict(table=dd, policy=None)})


def _map_policy_file(path, system, horizon):
    """An untrained map policy of the robot's system (the plumbing, not the quality, is under test)."""
    from cuniform_torch.maps import MapPolicy, MapPolicyConfig, map_policy_checkpoint, save_map_policy
    from cuniform_torch.systems import system_to_json

    config = MapPolicyConfig(state_dim=3, num_actions=7, horizon=horizon, periodic=[False, False, True],
                             feature_scale=[1.0, 1.0, 1.0],
                             patch={"shape": [24, 24], "resolution": 0.1, "origin": [-1.2, -1.2]},
                             hidden=16, layers=1, embed=8, channels=4)
    policy = MapPolicy(config, system, system.action_set(dtype=torch.float32))
    save_map_policy(path, map_policy_checkpoint(policy, system_to_json(system, horizon)))
    return path


def test_cfu_mppi_runs_from_a_given_map_policy_and_needs_one(tmp_path, cache):
    table = ensure_table(ROBOT, cache, quiet=True)
    policy = _map_policy_file(tmp_path / "m.pt", ROBOT.make_system(), ROBOT.horizon)
    res = run(_cfg(tasks=1, methods=("cfu_mppi",)), tmp_path / "o", ROBOT, cache,
              given={"table": table, "map_policy": policy}, progress=False)
    [row] = res["summary"]
    assert row["method"] == "cfu_mppi" and row["n"] == 1
    settings = json.loads((tmp_path / "o" / "settings.json").read_text())
    assert settings["sources"]["map_policy"]
    with pytest.raises(ValueError, match="--map-policy"):
        run(_cfg(tasks=1, methods=("cfu_mppi",)), tmp_path / "o2", ROBOT, cache, given={"table": table},
            progress=False)


def test_cfu_mppi_senses_the_raw_obstacles_not_the_inflated_ones(monkeypatch, tmp_path, cache):
    """The farm's patches are raw occupancy (its tables inflate by the radius): a policy fed the inflated world
    would see every obstacle 0.2 m too large, a map unlike any it was trained on."""
    from eval.navigate import episode as nav_episode
    from precompute.worlds.tasks import make_tasks

    task = make_tasks("forest", ROBOT.radius, 1)[0]
    seen = {}

    class Stop(Exception):
        pass

    def capture(method, sources, cost, *args, world=None, max_range=None, **kw):
        seen.update(world=world, max_range=max_range)
        raise Stop

    monkeypatch.setattr(nav_episode, "make_controller", capture)
    table = ensure_table(ROBOT, cache, quiet=True)
    ctx = nav_episode.NavContext(table=str(table), map_policy=str(_map_policy_file(tmp_path / "m.pt", ROBOT.make_system(),
                                                                                    ROBOT.horizon)))
    with pytest.raises(Stop):
        nav_episode.run_nav_episode(nav_episode.NavJob(task, "cfu_mppi", 16, 0), ctx)
    raw = [float(r) for r in task.discs[:, 2]]
    assert [o.radius for o in seen["world"].obstacles[:len(raw)]] == pytest.approx(raw)
    assert [o.radius for o in task.environment.obstacles[:len(raw)]] == pytest.approx([r + ROBOT.radius for r in raw])
    assert seen["world"].bounds == pytest.approx(task.bounds) and seen["max_range"] == task.sensing_range


def test_a_gap_sweep_of_other_widths_is_refused_since_its_task_ids_mean_other_gaps(tmp_path):
    from eval.navigate.records.store import EpisodeStore, StoreError
    from eval.navigate.run import settings_record
    from precompute.worlds.tasks import make_tasks

    sweep = {n: make_tasks("gaps", 0.2, count=n) for n in (2, 3, 4, 7)}
    assert sweep[4][3].params["width"] != sweep[7][3].params["width"]  # why: the same key, another gap
    (tmp_path / "t.npz").write_bytes(b"a table")
    sources = dict(table=str(tmp_path / "t.npz"), coverage_table=None, policy=None)

    def record(n: int, **kw) -> dict:
        return settings_record(_cfg(tasks=n, **kw), ROBOT, None, sources, sweep[n])

    assert record(4)["gap_widths"] == [0.6, 1.2] and "gap_widths" not in settings_record(
        _cfg(suite="forest"), ROBOT, None, sources)
    store = EpisodeStore(tmp_path / "run")
    store.open(record(4))
    store.open(record(4, methods=("uniform",)))  # another method fits
    with pytest.raises(StoreError, match=r"gap_widths: \[0.6, 1.2\] there, \[0.6, 0.9, 1.2\] now"):
        store.open(record(7))
    other = EpisodeStore(tmp_path / "short")
    other.open(record(2))
    other.open(record(3))  # one width either way: the same gaps, one more task
