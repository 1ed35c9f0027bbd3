"""Sorting the benchmark's failures (python -m eval.navigate failures): a timeout is lost, a collision whose last
command had free proposals is missed, one preceded by commands with none is trapped only when the C-Uniform
probe finds no free trajectory at that state either; the CLI counts every failure of the folder once."""

from __future__ import annotations

import json

import pytest
from test_nav_replay import ROBOT, bench  # noqa: F401  (the tiny benchmark folder fixture)

from eval.navigate.episode import NavContext
from eval.navigate.failures import classify, main, probe_free_share
from eval.navigate.robot_files import ensure_table
from precompute.worlds.tasks import make_task


@pytest.fixture(scope="module")
def gap(tmp_path_factory):
    """A gap task (walls across the room) and a context on the 6-step table."""
    cache = tmp_path_factory.mktemp("failures")
    table = ensure_table(ROBOT, cache, quiet=True)
    task = make_task("gaps", 0, ROBOT.radius, count=3)
    return task, NavContext(table=str(table), horizon=ROBOT.horizon)


def _facing_wall(task) -> list[float]:
    """A pose 6 cm from the inflated dividing wall, heading into it, half a metre above the wall's lower end."""
    xmin, ymin = task.walls[0][:2]  # the wall below the gap
    return [float(xmin) - ROBOT.radius - 0.06, float(ymin) + 0.5, 0.0]


def _trace(shares: list[float], state: list[float]) -> list[dict]:
    return [dict(t=0.2 * k, free_share=s, min_cost=0.0 if s else 1e6, state=state) for k, s in enumerate(shares)]


def test_probe_sees_no_way_out_when_the_robot_is_on_a_wall_and_plenty_in_the_open(gap):
    task, ctx = gap
    facing_wall = _facing_wall(task)
    in_the_open = [task.start[0], task.start[1], 0.0]
    assert probe_free_share(task, facing_wall, ctx, samples=512) == 0.0
    assert probe_free_share(task, in_the_open, ctx, samples=512) > 0.5


def test_classify_sorts_each_outcome(gap):
    task, ctx = gap
    facing_wall = _facing_wall(task)
    in_the_open = [task.start[0], task.start[1], 0.0]
    lost = classify(dict(key="g/0/m/16/0", outcome="timeout", time=30.0), [], task, ctx)
    assert lost.kind == "lost" and lost.trapped_s is None
    rec = dict(key="g/0/m/16/0", outcome="collision", time=1.0, path_length=0.5, cycles=5)
    missed = classify(rec, _trace([1, 1, 1, 0.5, 0.2], facing_wall), task, ctx)  # free at its last command
    assert missed.kind == "missed" and missed.probe_free_share is None
    trapped = classify(rec, _trace([1, 1, 0, 0, 0], facing_wall), task, ctx, samples=512)
    assert trapped.kind == "trapped" and trapped.probe_free_share == 0.0
    assert trapped.trapped_s == pytest.approx(1.0 - 0.4)  # the first all-colliding command was at t = 0.4 s
    blind = classify(rec, _trace([1, 1, 0, 0, 0], in_the_open), task, ctx, samples=512)
    assert blind.kind == "missed" and blind.probe_free_share > 0  # a free trajectory the controller missed
    with pytest.raises(ValueError, match="did not fail"):
        classify(dict(rec, outcome="goal"), _trace([1], in_the_open), task, ctx)


def test_cli_counts_every_failure_of_the_folder_once(bench, tmp_path, capsys):  # noqa: F811
    out, cache, records = bench
    js = tmp_path / "failures.json"
    assert main(["--out", str(out), "--cache", str(cache), "--probe-samples", "256", "--json", str(js)]) == 0
    printed = capsys.readouterr().out
    failed = sorted(k for k, r in records.items() if not r["success"])
    got = json.loads(js.read_text())
    assert sorted(f["key"] for f in got["failures"]) == failed and not got["not_reproduced"]
    assert all(f["kind"] in ("trapped", "missed", "lost") for f in got["failures"])
    for method in ("mppi_1.0", "cu_table"):
        n_failed = sum(1 for k in failed if records[k]["method"] == method)
        row = next(line for line in printed.splitlines() if line.startswith(f"| {method} | 16 |"))
        cells = [c.strip() for c in row.strip("|").split("|")]
        assert int(cells[2]) == 3 and int(cells[3]) == n_failed
        assert int(cells[4]) + int(cells[5]) + int(cells[6]) == n_failed


def test_cli_errors_are_one_line(bench, capsys):  # noqa: F811
    out, cache, _ = bench
    assert main(["--out", str(out), "--cache", str(cache), "--methods", "nope"]) == 2
    err = capsys.readouterr().err
    assert "no episode" in err and len(err.strip().splitlines()) == 1
    with pytest.raises(SystemExit, match="2"):  # refused as it parses
        main(["--out", str(out), "--probe-samples", "0"])
    assert "--probe-samples: must be an integer in [1, " in capsys.readouterr().err
