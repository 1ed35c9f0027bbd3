"""The closed-loop experiments (eval.paper.episodes, eval.common.stats, eval.common.markdown, eval.paper.sudden_obstacle, eval.paper.cluttered) on
tiny sizes, and closed-loop success rates with a stated margin.

Every run here uses the session's horizon-10 Dubins table written to a temporary file, N = 16 samples and
one or two scenarios, so each test takes a second or two.
"""

from __future__ import annotations

import json
import math
from dataclasses import replace

import pytest
import torch

from cuniform_torch.envs import Circle, Environment, NavigationCost
from cuniform_torch.tables.file import write_table
from eval.common.markdown import success_markdown
from eval.common.methods import Sources
from eval.common.stats import aggregate, wilson_interval
from eval.paper import cluttered, sudden_obstacle
from eval.paper.episodes import OUTCOMES, ControllerSettings, Episode, run_episodes, usable_methods

METHODS = ("mppi_high", "cu_table")


@pytest.fixture(scope="module")
def sources(dubins_table, tmp_path_factory):
    path = tmp_path_factory.mktemp("tables") / "dubins10.npz"
    write_table(path, dubins_table)
    missing = path.parent / "missing.npz"
    return Sources(table=path, coverage_table=missing, policy=path.parent / "missing.pt")


def _so(**overrides) -> sudden_obstacle.SuddenObstacleConfig:
    base = sudden_obstacle.SuddenObstacleConfig(positions=2, appear=(0.0, 1.0), samples=(16,), horizon=10,
                                                methods=METHODS, time_limit=6.0)
    return replace(base, **overrides)


def _cl(**overrides) -> cluttered.ClutteredConfig:
    base = cluttered.ClutteredConfig(environments=("u_shape",), starts=1, samples=(16,), horizon=10,
                                     methods=METHODS, time_limit_factor=0.25)
    return replace(base, **overrides)


def _strip(records):
    return [{k: v for k, v in r.items() if k != "wall_s"} for r in records]


DT = 0.2  # the Dubins preset's step


def _check_records(records, env_of, time_limit, tolerance=0.3):
    """Each record's outcome is what its path shows: "goal" ends within the tolerance, "collision" ends in an
    obstacle (the real one, sensed or not), "timeout" ends free and short of the goal at the time limit; success
    is the goal and nothing else; time and length agree with the path."""
    for r in records:
        assert r["outcome"] in OUTCOMES, r["outcome"]
        assert r["success"] == (r["outcome"] == "goal")
        path = torch.tensor(r["path"], dtype=torch.float64)  # [S+1, 2], rounded to the mm
        end, goal = path[-1], torch.tensor(r["goal"], dtype=torch.float64)
        assert r["steps"] == len(path) - 1 and r["time"] == pytest.approx(r["steps"] * DT)
        assert r["path_length"] == pytest.approx(float((path[1:] - path[:-1]).norm(dim=1).sum()), abs=0.01 * len(path))
        near_goal = float((end - goal).norm()) <= tolerance + 2e-3
        hit = bool(env_of(r).in_collision(end.float()))
        if r["outcome"] == "goal":
            assert near_goal and not hit
        elif r["outcome"] == "collision":
            assert hit
        else:
            assert not hit and not near_goal and r["time"] == pytest.approx(time_limit, abs=DT)


# ------------------------------------------------------------------------------------------------ statistics

@pytest.mark.parametrize("k, n, lo, hi", [
    (0, 10, 0.0, 0.2775), (10, 10, 0.7225, 1.0), (5, 10, 0.2366, 0.7634), (19, 20, 0.7639, 0.9911),
    (1, 1, 0.2065, 1.0),
])
def test_wilson_interval_values(k, n, lo, hi):
    got = wilson_interval(k, n)
    assert got == pytest.approx((lo, hi), abs=1e-4)


def test_wilson_interval_edges():
    assert wilson_interval(0, 0) == (0.0, 1.0)
    lo, hi = wilson_interval(3, 7, z=2.576)  # wider at 99%
    lo95, hi95 = wilson_interval(3, 7)
    assert lo < lo95 and hi > hi95
    for bad in [(-1, 3), (4, 3), (1, -1)]:
        with pytest.raises(ValueError):
            wilson_interval(*bad)


def test_aggregate_and_markdown():
    recs = [dict(method="cu_table", num_samples=16, appear=0.0, success=s, outcome="goal" if s else "collision",
                 time=t, path_length=2 * t) for s, t in [(True, 4.0), (True, 6.0), (False, 1.0)]]
    (row,) = aggregate(recs, ("appear", "num_samples", "method"))
    assert (row["n"], row["successes"], row["collisions"], row["timeouts"]) == (3, 2, 1, 0)
    assert row["success_rate"] == pytest.approx(2 / 3)
    assert (row["ci_low"], row["ci_high"]) == pytest.approx(wilson_interval(2, 3))
    assert row["mean_time"] == 5.0 and row["mean_path_length"] == 10.0  # successful runs only
    md = success_markdown([row], ["cu_table"], "appear", [0.0], ["visible"], {0.0: {"cuniform": 1.0}})
    assert "0.67 [" in md and "paper: C-Uniform" in md and "| 1.00 |" in md


def test_per_state_collision_cost():
    env = Environment([Circle((1.0, 0.0), 0.25)])
    xs = torch.linspace(0.0, 2.0, 11)
    states = torch.stack([torch.stack((xs, torch.zeros(11), torch.zeros(11)), 1),
                          torch.stack((xs, torch.full((11,), 1.0), torch.zeros(11)), 1)])  # [2, 11, 3]
    actions = torch.zeros(2, 10, 1)
    once = NavigationCost(env, (5.0, 0.0), collision_penalty=100.0)(states, actions)
    per = NavigationCost(env, (5.0, 0.0), collision_penalty=100.0, per_state=True)(states, actions)
    free = NavigationCost(Environment([]), (5.0, 0.0))(states, actions)
    assert once - free == pytest.approx(torch.tensor([100.0, 0.0]))
    assert per - free == pytest.approx(torch.tensor([300.0, 0.0]))  # x = 0.8, 1.0, 1.2 are inside
    with pytest.raises(ValueError):
        NavigationCost(env, (5.0, 0.0), per_state=1)


def test_missing_sources_are_skipped_with_a_note(sources, capsys):
    kept = [m.key for m in usable_methods(None, sources, requested=False)]
    assert "cu_table" in kept and "cu_coverage" not in kept and "cu_mlp" not in kept
    out = capsys.readouterr().out
    assert "skipping cu_coverage" in out and "leaving out cu_mlp" in out
    usable_methods(None, sources, requested=False, include_slow=True)
    assert "skipping cu_mlp" in capsys.readouterr().out
    with pytest.raises(FileNotFoundError):
        usable_methods(["cu_mlp"], sources, requested=True)


# ------------------------------------------------------------------------------------------------ sudden obstacle

def test_sudden_obstacle_scenario():
    cfg = sudden_obstacle.SuddenObstacleConfig()
    offs = sudden_obstacle.offsets(cfg)
    assert len(offs) == 20 and all(-cfg.radius <= o <= cfg.radius for o in offs)
    assert offs == sudden_obstacle.offsets(cfg) and offs != sudden_obstacle.offsets(replace(cfg, seed=1))
    env = sudden_obstacle.make_env(cfg, 0.1, 0.5)
    (obs,) = env.obstacles
    assert obs.center == (2.0, 0.1) and obs.radius == 0.5 and obs.appear_time == 0.5
    assert len(env.visible(0.4)) == 0 and len(env.visible(0.5)) == 1


def test_sudden_obstacle_oracle(sources):
    cfg = sudden_obstacle.SuddenObstacleConfig()
    system = sources.system
    assert sudden_obstacle.oracle_feasible(cfg, system, 0.0, 0.0)  # visible from the start: easy
    assert not sudden_obstacle.oracle_feasible(cfg, system, 0.0, 1.6)  # sensed 0.1 m before its edge


def test_sudden_obstacle_run_markdown_figures(sources, tmp_path):
    res = sudden_obstacle.run(_so(), sources, progress=False)
    assert res["methods"] == list(METHODS)
    assert len(res["records"]) == 2 * 2 * len(METHODS)
    _check_records(res["records"], lambda r: sudden_obstacle.make_env(_so(), r["offset"], r["appear"]), 6.0)
    assert len(res["summary"]) == 2 * len(METHODS)
    json.loads(json.dumps(res))  # JSON-ready
    md = sudden_obstacle.markdown(res)
    assert "Sudden obstacle" in md and "paper: C-Uniform" in md and "oracle: avoidable" in md and "N = 16" in md
    paths = sudden_obstacle.figures(res, tmp_path)
    assert len(paths) == 2 and all(p.exists() and p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" for p in paths)


def test_sudden_obstacle_is_deterministic(sources):
    cfg = _so(appear=(0.5,), positions=1)
    a = sudden_obstacle.run(cfg, sources, progress=False)
    b = sudden_obstacle.run(cfg, sources, progress=False)
    assert _strip(a["records"]) == _strip(b["records"])


def test_sudden_obstacle_paper_values_shown(sources):
    res = sudden_obstacle.run(_so(samples=(500,), positions=1, appear=(0.5,), methods=("mppi_high",),
                                  time_limit=0.4), sources, progress=False)
    md = sudden_obstacle.markdown(res)
    assert "| **paper: MPPI** | MPPI | 0.55 |" in md and "| **paper: C-Uniform** | C-Uniform | 1.00 |" in md


def test_sudden_obstacle_cli(sources, tmp_path, capsys):
    out = tmp_path / "so.json"
    sudden_obstacle.main(["--quick", "--quiet", "--horizon", "10", "--samples", "16", "--methods", "cu_table",
                          "--table", str(sources.table), "--json", str(out), "--figures", str(tmp_path / "f")])
    assert "Sudden obstacle" in capsys.readouterr().out
    res = json.loads(out.read_text())
    assert res["config"]["horizon"] == 10 and res["methods"] == ["cu_table"]
    assert sorted(p.name for p in (tmp_path / "f").iterdir()) == ["sudden_obstacle_1s_N16.png",
                                                                  "sudden_obstacle_visible_N16.png"]


# ------------------------------------------------------------------------------------------------ cluttered

@pytest.mark.parametrize("name", list(cluttered.ENVIRONMENTS))
def test_cluttered_starts_are_free_and_fixed(name):
    cfg = cluttered.ClutteredConfig()
    starts = cluttered.start_poses(cfg, name)
    assert len(starts) == 10 and starts == cluttered.start_poses(cfg, name)
    assert starts != cluttered.start_poses(replace(cfg, seed=1), name)
    env, spec = cluttered.make_env(name), cluttered.ENVIRONMENTS[name]
    for x, y, th in starts:
        xy = torch.tensor([x, y], dtype=torch.float64)
        assert not bool(env.in_collision(xy))
        assert all(float(o.signed_distance(xy)) >= cfg.clearance - 1e-6 for o in env.obstacles)
        assert math.hypot(x - spec.goal[0], y - spec.goal[1]) >= spec.min_goal_distance
        assert -math.pi <= th <= math.pi
    assert not bool(env.in_collision(torch.tensor(spec.goal, dtype=torch.float64)))


def test_u_shape_goal_is_inside_the_pocket():
    env = cluttered.make_env("u_shape")
    gx, gy = cluttered.ENVIRONMENTS["u_shape"].goal
    walls = [(gx - 1.0, gy), (gx, gy + 2.0), (gx, gy - 2.0)]  # behind and beside the goal: walls in between
    for wx, wy in walls:
        seg = torch.stack((torch.linspace(gx, wx, 200), torch.linspace(gy, wy, 200)), 1).double()
        assert bool(env.in_collision(seg).any())
    ahead = torch.stack((torch.linspace(gx, gx + 3.0, 200), torch.full((200,), gy)), 1).double()
    assert not bool(env.in_collision(ahead).any())  # open towards +x


def test_cluttered_run_markdown_figures_deterministic(sources, tmp_path):
    cfg = _cl(environments=("u_shape", "rectangles"))
    res = cluttered.run(cfg, sources, progress=False)
    assert len(res["records"]) == 2 * len(METHODS)
    assert res["time_limits"] == {"u_shape": 6.0, "rectangles": 5.5}
    json.loads(json.dumps(res))
    md = cluttered.markdown(res)
    assert "U-shape centre" in md and "rectangles (4.0, -3.7, 4.6, -2.3)" in md and "paper: log-MPPI" in md
    paths = cluttered.figures(res, tmp_path)
    assert [p.name for p in paths] == ["cluttered_u_shape_N16.png", "cluttered_rectangles_N16.png"]
    again = cluttered.run(cfg, sources, progress=False)
    assert _strip(res["records"]) == _strip(again["records"])


def test_cluttered_paper_values_shown(sources):
    res = cluttered.run(_cl(samples=(500,), methods=("mppi_high",), time_limit_factor=0.02), sources,
                        progress=False)
    md = cluttered.markdown(res)
    assert "| **paper: C-Uniform** | C-Uniform | 0.80 |" in md


def test_cluttered_cli(sources, tmp_path, capsys):
    out = tmp_path / "cl.json"
    cluttered.main(["--quick", "--quiet", "--horizon", "10", "--samples", "16", "--methods", "mppi_low",
                    "--envs", "rectangles", "--table", str(sources.table), "--json", str(out)])
    assert "Cluttered environments" in capsys.readouterr().out
    res = json.loads(out.read_text())
    assert res["config"]["environments"] == ["rectangles"] and len(res["records"]) == 1


def test_cluttered_seeds_per_start(sources):
    one = cluttered.run(_cl(), sources, progress=False)
    assert all("rep" not in r for r in one["records"])  # the default experiment's records are unchanged
    three = cluttered.run(_cl(seeds_per_start=3), sources, progress=False)
    assert len(three["records"]) == 3 * len(one["records"])
    assert sorted({r["rep"] for r in three["records"]}) == [0, 1, 2]
    assert len({r["seed"] for r in three["records"]}) == 3  # one seed per repeat, shared by every method and N
    first = [{k: v for k, v in r.items() if k != "rep"} for r in three["records"] if r["rep"] == 0]
    assert _strip(first) == _strip(one["records"])  # repeat 0 is the default run
    (row,) = [r for r in three["summary"] if r["method"] == "cu_table"]
    assert row["n"] == 3
    md = cluttered.markdown(three)
    assert "3 controller seeds" in md and "| start 0 |" in md
    assert "| start 0 |" not in cluttered.markdown(one)
    seeds = [cluttered.controller_seed(cluttered.ClutteredConfig(), ei, s, r)
             for ei in range(2) for s in range(1000) for r in range(5)]
    assert len(set(seeds)) == len(seeds)
    with pytest.raises(ValueError):
        cluttered.run(_cl(seeds_per_start=0), sources, progress=False)


def test_cluttered_cli_seeds_per_start(sources, tmp_path, capsys):
    out = tmp_path / "cl.json"
    cluttered.main(["--quick", "--quiet", "--horizon", "10", "--samples", "16", "--methods", "mppi_low",
                    "--envs", "u_shape", "--seeds-per-start", "2", "--table", str(sources.table), "--json", str(out)])
    assert "| start 0 |" in capsys.readouterr().out
    res = json.loads(out.read_text())
    assert res["config"]["seeds_per_start"] == 2 and len(res["records"]) == 2
    with pytest.raises(SystemExit):
        cluttered.main(["--quick", "--seeds-per-start", "0", "--table", str(sources.table)])


def test_collisions_after_goal_flag(sources, tmp_path):
    out = tmp_path / "cl.json"
    base = ["--quick", "--quiet", "--horizon", "10", "--samples", "16", "--methods", "mppi_low", "--envs", "u_shape",
            "--table", str(sources.table), "--json", str(out)]
    cluttered.main(base)
    assert json.loads(out.read_text())["config"]["stop_at_goal"] is True
    cluttered.main(base + ["--collisions-after-goal"])
    assert json.loads(out.read_text())["config"]["stop_at_goal"] is False
    so = sudden_obstacle.run(_so(stop_at_goal=False, positions=1, appear=(0.0,)), sources, progress=False)
    assert so["config"]["stop_at_goal"] is False


# ------------------------------------------------------------------------------------------------ success rates

SEEDS = range(5)
START, GOAL = (0.0, 0.0, 0.0), (3.0, 1.0)


def _success(sources, method, env, penalty=1e6, num_samples=200, time_limit=8.0, goal=GOAL):
    """Records of ``method`` driving from START to ``goal`` in ``env`` under each of SEEDS (horizon 10)."""
    episodes = [Episode(method, num_samples, env, START, goal, 0.3, time_limit, seed=seed, horizon=10)
                for seed in SEEDS]
    records = run_episodes(episodes, sources, ControllerSettings(collision_penalty=penalty), progress=False)
    _check_records(records, lambda r: env, time_limit)
    return records


@pytest.mark.parametrize("method", ["mppi_high", "cu_table"])
def test_open_field_goal_is_reached_in_at_least_4_of_5_seeds(sources, method):
    """An open field, the goal 3.2 m away, 8 s (the straight drive takes 3.2 s): at least 4 of 5 seeds arrive."""
    records = _success(sources, method, Environment([]))
    assert sum(r["success"] for r in records) >= 4, [r["outcome"] for r in records]
    assert all(r["time"] < 6.0 for r in records if r["success"])  # well inside the limit: a direct drive


def test_a_disc_on_the_way_is_avoided_only_when_the_cost_sees_it(sources):
    """A disc of radius 0.4 m right on the straight line: with the paper's collision penalty MPPI goes around it
    in at least 4 of 5 seeds; with a negligible penalty (the cost blind to it) it drives into it in at least 4 of 5."""
    env = Environment([Circle((1.5, 0.5), 0.4)])
    avoided = _success(sources, "mppi_high", env)
    assert sum(r["success"] for r in avoided) >= 4, [r["outcome"] for r in avoided]
    blind = _success(sources, "mppi_high", env, penalty=1e-9)  # > 0 is required; this little is blind
    assert sum(r["outcome"] == "collision" for r in blind) >= 4, [r["outcome"] for r in blind]


def test_an_unreachable_goal_is_never_a_success(sources):
    """The goal 20 m away with 4 s to drive at 1 m/s: every seed must time out (a success here is a bug)."""
    records = _success(sources, "cu_table", Environment([]), time_limit=4.0, goal=(20.0, 0.0))
    assert [r["outcome"] for r in records] == ["timeout"] * len(SEEDS)


def test_workers_give_the_same_records(sources):
    """Episodes in two worker processes: the same records, in the same order, as in this process (wall_s aside)."""
    cfg = _cl(environments=("u_shape", "rectangles"), starts=2)
    alone = cluttered.run(cfg, sources, progress=False)
    pooled = cluttered.run(cfg, sources, progress=False, workers=2)
    assert len(alone["records"]) == 8
    assert _strip(pooled["records"]) == _strip(alone["records"])
