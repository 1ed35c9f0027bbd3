"""``python -m precompute.build maxflow|coverage|set|safe``: each subcommand shows only its own flags, a system's
parameters are ``--param``, ``--print-config`` then ``--config`` rebuilds the same job and the same table bytes,
a config file is strict (an unknown key, a wrong type, a key of another method: one error naming it), and the
old spelling (no subcommand, per-system flags) still builds the same table, with a one-line note."""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

import numpy as np
import pytest
from test_cli_errors import _call, _one_error

import precompute.build as build
from precompute.build_args import CONFIG_KEYS, legacy_argv
from precompute.levels.safe_map import LocalMap, write_map_file

COMMON = {"-h", "--help", "--config", "--print-config", "--system", "--system-module", "--param", "--out",
          "--horizon", "--seed", "--threads", "--quiet"}
REPORT = {"--no-report", "--rollouts", "--device"}
MAXFLOW = {"--points", "--points-per-cell", "--ties", "--resume", "--max-memory"}
COVERAGE = {"--target-samples", "--merge-resolution", "--steps", "--lr", "--state-budget", "--tol"}
FLAGS = {
    "maxflow": COMMON | {"--start"} | REPORT | MAXFLOW,
    "coverage": COMMON | {"--start"} | REPORT | COVERAGE,
    "set": COMMON | {"--starts", "--workers", "--ray", "--no-limit", "--method"} | MAXFLOW | COVERAGE,
    "safe": COMMON | {"--start"} | REPORT | {"--map", "--radius", "--method"} | MAXFLOW | COVERAGE,
}
"""the flags each subcommand's --help shows (and no other)"""


def _help(capsys, argv: list[str]) -> str:
    with pytest.raises(SystemExit) as info:
        build.main(argv)
    assert info.value.code == 0
    return capsys.readouterr().out


@pytest.mark.parametrize("command", sorted(FLAGS))
def test_each_subcommand_shows_only_its_flags(command, capsys):
    text = _help(capsys, [command, "--help"])
    shown = set(re.findall(r"^\s+(-[-\w]+)", text, flags=re.M)) | set(re.findall(r"^\s+-h, (--help)", text, re.M))
    assert shown == FLAGS[command], (shown - FLAGS[command], FLAGS[command] - shown)
    assert "--num-actions" not in text and "--cell-size" not in text  # system parameters are --param


def test_the_top_help_lists_the_subcommands_and_each_ones_flags(capsys):
    """One --help shows every flag there is, each under the subcommands that take it (explained by SUB --help)."""
    text = _help(capsys, ["--help"])
    listing = text.split("flags of each subcommand")[1]
    for name, flags in FLAGS.items():
        block = listing.split(f"  {name}:")[1].split(":")[0]  # up to the next subcommand's name
        assert set(re.findall(r"--[a-z][\w-]*", block)) == flags - {"-h", "--help"}, name


# ------------------------------------------------------------------------------------------ config round trip

def _map(path: Path) -> Path:
    occ = np.zeros((24, 24), np.uint8)
    occ[12, 20] = 1  # 0.4 m ahead of the start
    write_map_file(path, LocalMap(occ, (-0.625, -0.625), 0.05))
    return path


def _cases(tmp: Path) -> dict[str, list[str]]:
    """A tiny build of each subcommand (its output given last, as --out PATH)."""
    return {
        "maxflow": ["maxflow", "--system", "dubins", "--horizon", "3", "--param", "num_actions=3", "--points",
                    "random", "--points-per-cell", "2", "--seed", "4", "--rollouts", "50"],
        "coverage": ["coverage", "--system", "random_walk_1d", "--horizon", "2", "--steps", "3", "--target-samples",
                     "50", "--param", "cell_size=[0.25]", "--no-report"],
        "set": ["set", "--system", "random_walk_1d", "--horizon", "2", "--starts", "0=-1:1:2", "--method", "coverage",
                "--steps", "2"],
        "safe": ["safe", "--system", "dubins", "--horizon", "2", "--param", "num_actions=3", "--map",
                 str(_map(tmp / "m.npz")), "--radius", "0.05", "--no-report"],
    }


def _same_job(a, b) -> None:
    """Two TableJobs are equal (a LocalMap, holding an array, compared by its bytes and frame)."""
    import dataclasses

    maps = [job.build.local_map for job in (a, b)]
    if maps[0] is not None:
        assert maps[1] is not None and maps[0].sha256() == maps[1].sha256()
        assert (maps[0].origin, maps[0].resolution) == (maps[1].origin, maps[1].resolution)
        a, b = (dataclasses.replace(j, build=dataclasses.replace(j.build, local_map=None),
                                    coverage=None if j.coverage is None else
                                    dataclasses.replace(j.coverage, local_map=None)) for j in (a, b))
    assert a == b


def _outputs(out: Path) -> dict[str, bytes]:
    """The tables (and a set's index) written at ``out``, by name inside the set (a report names its own path)."""
    if not out.is_dir():
        return {"table": out.read_bytes()}
    return {f.name: f.read_bytes() for f in sorted(out.iterdir())
            if f.suffix in (".npz", ".json") and not f.name.endswith(".report.json")}


@pytest.mark.parametrize("command", ["maxflow", "coverage", "set", "safe"])
def test_print_config_then_config_round_trips(command, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    suffix = "" if command == "set" else ".npz"
    argv = [*_cases(tmp_path)[command], "--quiet", "--out", f"a{suffix}"]
    assert build.main([*argv, "--print-config"]) == 0
    printed = capsys.readouterr().out
    config = json.loads(printed)
    assert set(config) <= set(CONFIG_KEYS) and config["system"]["name"] and not list(tmp_path.glob("a*"))
    (tmp_path / "c.json").write_text(printed)
    job, table_set = build.parse_job(argv)
    again, set_again = build.parse_job([command, "--config", "c.json"])
    _same_job(job, again)
    assert set_again.keys() == table_set.keys()
    for key in table_set:
        assert np.array_equal(table_set[key], set_again[key]) if key == "starts" else table_set[key] == set_again[key]
    assert build.main(argv) == 0
    assert build.main([command, "--config", "c.json", "--out", f"b{suffix}"]) == 0  # a flag beside it wins
    a, b = _outputs(tmp_path / f"a{suffix}"), _outputs(tmp_path / f"b{suffix}")
    assert a and a == b  # identical table bytes (and a set's index)


def test_a_toml_config_and_flags_over_a_config(tmp_path):
    (tmp_path / "c.toml").write_text('out = "t.npz"\n[system]\nname = "dubins"\nnum_actions = 3\n'
                                     '[build]\nhorizon = 3\npoints = "lattice"\n')
    job, _ = build.parse_job(["maxflow", "--config", str(tmp_path / "c.toml")])
    flags, _ = build.parse_job(["maxflow", "--param", "num_actions=3", "--horizon", "3", "--points", "lattice",
                                "--out", "t.npz"])
    assert job == flags
    over, _ = build.parse_job(["maxflow", "--config", str(tmp_path / "c.toml"), "--horizon", "2", "--param",
                               "num_actions=5"])
    assert over.build.horizon == 2 and over.system.num_actions == 5 and over.build.points.value == "lattice"


@pytest.mark.parametrize("command, config, needles", [
    ("maxflow", {"build": {"pointz": "random"}}, ["build.pointz is not a known key", "points"]),
    ("maxflow", {"horizon": 3}, ["horizon is not a known key", "build"]),
    ("maxflow", {"build": {"horizon": "3"}}, ["build.horizon must be an integer", '"3"']),
    ("maxflow", {"build": {"start": [0, 0, "x"]}}, ["build.start[2] must be a number"]),
    ("maxflow", {"build": {"points": "everywhere"}}, ["build.points must be one of", "'lattice'"]),
    ("maxflow", {"coverage": {"steps": 3}}, ["coverage does not apply to maxflow"]),
    ("maxflow", {"map": "m.npz"}, ["map does not apply to maxflow"]),
    ("maxflow", {"report": False, "rollouts": 5}, ["rollouts in", "but report in"]),
    ("maxflow", {"system": {"name": "dubins", "num_actions": 2.5}}, ["system.num_actions must be an integer"]),
    ("maxflow", {"system": {"name": "dubins", "spede": 1.0}}, ["spede", "its parameters"]),
    ("maxflow", {"system": "dubins"}, ["system must be an object"]),
    ("maxflow", {"build": {"points": "centers", "points_per_cell": 4}},
     ["build.points_per_cell in", "--points random only"]),
    ("coverage", {"build": {"points": "random"}}, ["build.points applies to the max-flow method only"]),
    ("coverage", {"coverage": {"horizon": 3}}, ["coverage.horizon comes from the build section"]),
    ("coverage", {"coverage": {"stepz": 3}}, ["coverage.stepz is not a known key", "steps"]),
    ("set", {"set": {"starts": 5}}, ["set.starts must be a string"]),
    ("set", {"build": {"start": [0.0]}, "set": {"starts": "0=-1:1:2"}}, ["build.start does not apply to a table set"]),
    ("set", {"set": {"starts": "0=-1:1:2"}, "coverage": {"steps": 2}, "resume": True}, ["resume does not apply to set"]),
    ("safe", {"map": 5}, ["map must be a path"]),
])
def test_a_bad_config_is_one_error_naming_the_key(command, config, needles, tmp_path, capsys):
    path = tmp_path / "c.json"
    path.write_text(json.dumps(config))
    assert _call(build.main, [command, "--system", "random_walk_1d", "--config", str(path), "--out",
                              str(tmp_path / "t.npz")]) == 2 or "system" in config
    if "system" in config:  # its own system: no --system beside it (that would be a conflict)
        capsys.readouterr()
        assert _call(build.main, [command, "--config", str(path), "--out", str(tmp_path / "t.npz")]) == 2
    _one_error(capsys, str(path) if "spede" not in config.get("system", {}) else "spede", *needles)
    assert not (tmp_path / "t.npz").exists()


@pytest.mark.parametrize("argv, needles", [
    (["--param", "speed=fast"], ["--param speed must be a number", '"fast"']),
    (["--param", "num_actions=2.5"], ["--param num_actions must be an integer"]),
    (["--system", "ks", "--config", "{dir}/c.json"], ["--system ks differs from the config's system.name 'dubins'"]),
    (["--config", "{dir}/nothing.json"], ["nothing.json", "No such file"]),
    (["--config", "{dir}/bad.json"], ["bad.json is not valid JSON", "line 1"]),
])
def test_bad_params_and_config_files(argv, needles, tmp_path, capsys):
    (tmp_path / "c.json").write_text(json.dumps({"system": {"name": "dubins"}}))
    (tmp_path / "bad.json").write_text("{'horizon': 3}")
    argv = ["maxflow", *[a.replace("{dir}", str(tmp_path)) for a in argv], "--out", str(tmp_path / "t.npz")]
    assert _call(build.main, argv) == 2
    _one_error(capsys, *needles)


# ------------------------------------------------------------------------------------------ the old spelling

def test_an_old_per_system_flag_and_its_param_give_the_same_table(tmp_path, capsys, monkeypatch):
    base = ["--system", "dubins", "--horizon", "3", "--quiet", "--no-report"]
    old = [*base, "--num-actions", "3", "--cell-size", "0.1", "0.1", "0.1571", "--out", str(tmp_path / "old.npz")]
    new = ["maxflow", *base, "--param", "num_actions=3", "--param", "cell_size=[0.1, 0.1, 0.1571]", "--out",
           str(tmp_path / "new.npz")]
    monkeypatch.setattr(sys, "argv", ["precompute.build", *old])
    assert build.main() == 0  # the command line: the note names the new spelling, on one line
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "deprecated" in err and "precompute.build maxflow" in err, err
    assert "--param num_actions=3 --param 'cell_size=[0.1, 0.1, 0.1571]'" in err
    assert build.main(new) == 0
    assert (tmp_path / "old.npz").read_bytes() == (tmp_path / "new.npz").read_bytes()
    assert capsys.readouterr().err == ""  # the new spelling: no note


@pytest.mark.parametrize("old, new", [
    (["--method", "coverage", "--steps", "3"], ["coverage", "--steps", "3"]),
    (["--method=maxflow", "--dt", "0.1"], ["maxflow", "--param", "dt=0.1"]),
    (["--starts", "3=0:1:2", "--no-report", "--method", "coverage"], ["set", "--starts", "3=0:1:2", "--method",
                                                                      "coverage"]),
    (["--map", "m.npz", "--radius", "0.1", "--num-actions=7"], ["safe", "--map", "m.npz", "--radius", "0.1",
                                                                "--param", "num_actions=7"]),
    (["maxflow", "--horizon", "3"], ["maxflow", "--horizon", "3"]),
    ([], ["maxflow"]),
    (["flow", "--horizon", "3"], ["flow", "--horizon", "3"]),  # a misspelt subcommand: argparse names the choices
])
def test_the_old_mode_flags_name_the_subcommand(old, new):
    assert legacy_argv(old)[0] == new


def test_a_misspelt_subcommand_lists_the_subcommands(capsys):
    assert _call(build.main, ["flow", "--horizon", "3"]) == 2
    _one_error(capsys, "invalid choice: 'flow'", "maxflow", "coverage", "set", "safe")
