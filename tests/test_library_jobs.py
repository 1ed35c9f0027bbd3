"""The library owns its jobs (issue 35 item 1): building a table or a set, distilling and training a map policy
are typed functions of ``precompute`` and ``training``, and the commands call them, so a table built from Python
is byte for byte the command's file; the old ``python -m eval.bench.NAME`` spelling is refused naming the new."""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import precompute.build as build_command
from cuniform_torch import write_table
from cuniform_torch.systems import make_system
from precompute import BuildConfig, CoverageConfig, SetConfig, build_table, build_table_set

ROOT = Path(__file__).resolve().parents[1]


def _sha(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


# ------------------------------------------------------------------------------------------ precompute

@pytest.mark.parametrize("method", ["maxflow", "coverage"])
def test_build_table_from_python_is_the_commands_file(tmp_path, method):
    """The same settings from Python and from the command: the same table bytes (and the returned table is the
    one written)."""
    system = make_system("dubins")
    config = BuildConfig(horizon=4, seed=3)
    coverage = CoverageConfig(horizon=4, target_samples=200, steps=5) if method == "coverage" else None
    table = build_table(system, config, coverage=coverage, out=tmp_path / "lib.npz")
    flags = ["--target-samples", "200", "--steps", "5"] if method == "coverage" else []
    assert build_command.main([method, "--system", "dubins", "--horizon", "4", "--seed", "3", "--no-report",
                               "--quiet", "--out", str(tmp_path / "cli.npz"), *flags]) == 0
    assert _sha(tmp_path / "lib.npz") == _sha(tmp_path / "cli.npz")
    write_table(tmp_path / "returned.npz", table)
    assert _sha(tmp_path / "returned.npz") == _sha(tmp_path / "lib.npz")
    assert (tmp_path / "lib.report.json").is_file()
    assert (table.method or "maxflow") == method


def test_build_table_in_memory_writes_nothing_and_prints_nothing(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    table = build_table(make_system("dubins"), BuildConfig(horizon=3))
    assert table.horizon == 3 and len(table.level_sizes) == 4
    assert list(tmp_path.iterdir()) == []
    captured = capsys.readouterr()
    assert captured.out == "" and captured.err == ""  # progress bars are off by default in library calls


@pytest.mark.parametrize("call, field", [
    (lambda s: build_table(s, CoverageConfig(horizon=3)), "config must be a BuildConfig"),
    (lambda s: build_table(s, BuildConfig(horizon=3), coverage=CoverageConfig(horizon=4)), "horizon"),
    (lambda s: build_table(s, BuildConfig(horizon=3), report=True), "need out=FILE"),
    (lambda s: SetConfig(starts="3=0:1:2", workers=0), "SetConfig.workers"),
    (lambda s: build_table_set(s, SetConfig(starts=[[0.0, 1.0]]), out="x"), "SetConfig.starts"),
    (lambda s: build_table(s, BuildConfig(horizon=3), out=Path("/proc/nope/t.npz")), "--out"),
    (lambda s: build_table("ks_speed", BuildConfig(horizon=3)), "system must be a System object"),
    (lambda s: build_table(object(), BuildConfig(horizon=3)), "lacks name"),
])
def test_bad_settings_are_one_value_error_naming_the_field(call, field):
    with pytest.raises(ValueError, match=field.replace("(", r"\(")):
        call(make_system("ks_speed"))


def test_build_table_set_returns_the_set_and_equals_the_commands(tmp_path):
    system = make_system("ks_speed")
    config = BuildConfig(horizon=3)
    policy = build_table_set(system, SetConfig(starts="3=0:1:2"), config, out=tmp_path / "lib")
    assert policy.starts.shape == (2, 4) and policy.starts[:, 3].tolist() == [0.0, 1.0]
    assert build_command.main(["set", "--system", "ks_speed", "--horizon", "3", "--starts", "3=0:1:2", "--quiet",
                               "--out", str(tmp_path / "cli")]) == 0
    for name in ("start_0000.npz", "start_0001.npz"):
        assert _sha(tmp_path / "lib" / name) == _sha(tmp_path / "cli" / name)
    starts = np.array([[0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]])  # the same starts as an array
    again = build_table_set(system, SetConfig(starts=starts), config, out=tmp_path / "lib")  # complete: kept
    assert again.starts.tolist() == policy.starts.tolist()


# ------------------------------------------------------------------------------------------ training

def test_distill_policy_from_python_is_the_commands_checkpoint(tmp_path, monkeypatch, capsys):
    """The same DistillConfig from Python and from the command: the same weights; the policy comes back."""
    import torch

    from training import DistillConfig, distill_policy
    from training.distill import main as distill_main

    write_table(tmp_path / "t.npz", build_table(make_system("dubins"), BuildConfig(horizon=3)))
    flags = dict(epochs=3, eval_samples=[50], eval_every=3, logdir=str(tmp_path / "runs"))
    capsys.readouterr()
    policy = distill_policy(DistillConfig(tables=[str(tmp_path / "t.npz")], out=str(tmp_path / "lib.pt"), **flags))
    assert capsys.readouterr().err == ""  # no progress bar from a library call
    assert distill_main(["--tables", str(tmp_path / "t.npz"), "--out", str(tmp_path / "cli.pt"), "--epochs", "3",
                         "--eval-samples", "50", "--eval-every", "3", "--logdir", str(tmp_path / "runs"),
                         "--quiet"]) == 0
    a, b = (torch.load(tmp_path / f"{n}.pt", weights_only=True)["state_dict"] for n in ("lib", "cli"))
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert policy.horizon == 3 and policy.system.name == "dubins"
    with pytest.raises(ValueError, match="--lr"):
        distill_policy(DistillConfig(tables=[str(tmp_path / "t.npz")], lr=-1.0))
    with pytest.raises(ValueError, match="DistillConfig.tables"):
        distill_policy(DistillConfig())


def test_train_map_policy_from_python(tmp_path):
    from test_distill_maps import MAPS, SYSTEM, T, write_dataset

    from training import MapDistillConfig, train_map_policy

    data = write_dataset(tmp_path / "walls", build_table(SYSTEM, BuildConfig(horizon=T)), MAPS)
    config = MapDistillConfig(maps=[str(data)], out=str(tmp_path / "p.pt"), epochs=2, hidden=16, embed=8,
                              channels=4, logdir=str(tmp_path / "runs"), skip_deep_checks=True)  # as that file trains
    policy = train_map_policy(config)
    assert (tmp_path / "p.pt").is_file() and policy.horizon == T
    with pytest.raises(ValueError, match="--hidden"):
        train_map_policy(MapDistillConfig(maps=[str(data)], hidden=0))
    with pytest.raises(ValueError, match="--maps"):
        train_map_policy(MapDistillConfig(maps=[str(tmp_path)]))


# ------------------------------------------------------------------------------------------ eval.bench subcommands

def test_the_old_eval_bench_spelling_is_refused_naming_the_new(tmp_path):
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.run([sys.executable, "-m", "eval.bench.soak_bank", "--commands", "10"], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2 and proc.stdout == ""
    assert proc.stderr.splitlines() == [
        "error: python -m eval.bench.soak_bank is now a subcommand: python -m eval.bench soak_bank --commands 10"]
    assert list(tmp_path.iterdir()) == []  # nothing ran


def test_eval_bench_dispatches_its_subcommands(monkeypatch, capsys):
    import eval.bench.cli as bench
    import eval.bench.family as family

    seen = []
    monkeypatch.setattr(family, "main", lambda argv: seen.append(argv) or 0)
    assert bench.main(["family", "--repeats", "3"]) == 0 and seen == [["--repeats", "3"]]
    assert bench.main(["nope"]) == 2
    assert "'nope' is not a subcommand" in capsys.readouterr().err
    parser = bench.make_parser()  # every subcommand's own flags, for --help and the entry-point tests
    subs = next(a for a in parser._actions if a.choices and "family" in a.choices).choices
    assert set(subs) == set(bench.COMMANDS) and any("--robots" in a.option_strings for a in subs["family"]._actions)
