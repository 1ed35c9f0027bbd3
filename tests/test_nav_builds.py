"""No hidden builds (issue 37): the navigation robot's files are announced, with their expected time, before they
are built, once."""

from __future__ import annotations

from dataclasses import replace

import torch

from eval.navigate import robot_files
from eval.navigate.robot_files import BUILD_SECONDS, ensure_table, expected_time
from precompute.worlds.robot import NAV_ROBOT

ROBOT = replace(NAV_ROBOT, horizon=6)  # a 6-step table builds in well under a second


def test_a_build_is_announced_with_its_time_before_it_starts_and_once(tmp_path, capsys, monkeypatch):
    import precompute.one_table as one_table

    built = one_table.build_table_file
    seen: dict[str, object] = {}

    def spy(job):  # what was printed when the build started, and the torch threads it ran with
        seen["printed"] = capsys.readouterr().out
        seen["threads"] = torch.get_num_threads()
        return built(job)

    monkeypatch.setattr(one_table, "build_table_file", spy)
    threads = torch.get_num_threads()
    path = ensure_table(ROBOT, tmp_path, quiet=True)
    assert path.is_file()
    lines = str(seen["printed"]).splitlines()
    assert lines == [f"building the maxflow table of the navigation robot (about a second; once, cached in {path})"]
    assert seen["threads"] == 1 and torch.get_num_threads() == threads  # the command's one thread, restored after
    assert ensure_table(ROBOT, tmp_path, quiet=True) == path
    assert capsys.readouterr().out == ""  # cached: nothing said, nothing built


def test_expected_times_name_seconds_for_the_measured_robots():
    assert expected_time(NAV_ROBOT) == f"about {BUILD_SECONDS[('maxflow', 15)]:.0f} s on a 2-core CPU"
    assert expected_time(NAV_ROBOT, "coverage") == f"about {BUILD_SECONDS[('coverage', 15)]:.0f} s on a 2-core CPU"
    assert expected_time(NAV_ROBOT, "policy") == "about 4 minutes on a 2-core CPU"
    other = expected_time(replace(NAV_ROBOT, horizon=7), "coverage")
    assert "not measured" in other and f"about {BUILD_SECONDS[('coverage', 15)]:.0f} s" in other
    assert "not measured" in expected_time(replace(NAV_ROBOT, params={**NAV_ROBOT.params, "speed": 0.7}))


def test_the_announcement_names_the_file_and_the_time(tmp_path, capsys):
    robot_files.announce(NAV_ROBOT, "coverage", "building X", tmp_path / "t.npz")
    out = capsys.readouterr().out
    seconds = BUILD_SECONDS[("coverage", 15)]
    assert out == f"building X (about {seconds:.0f} s on a 2-core CPU; once, cached in {tmp_path / 't.npz'})\n"
