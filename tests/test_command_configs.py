"""``--config FILE`` / ``--print-config`` on every command whose settings are one dataclass (issue 35): what
``--print-config`` writes, ``--config`` reads back to the same settings; a flag beside it wins over its key; a
key that is no setting, a value of the wrong type and a missing required setting are one error naming it."""

from __future__ import annotations

import json

import pytest

import eval.navigate.run as navigate
import training.distill as distill
import training.maps.distill as map_distill

COMMANDS = {  # the command's main, and flags that set a few settings away from their defaults
    "eval.navigate": (navigate.main, ["--suite", "clutter", "--tasks", "3", "--budgets", "16", "64", "--methods",
                                      "mppi_1.0", "cu_table", "--lockstep", "4"]),
    "training.distill": (distill.main, ["--tables", "a.npz", "b.npz", "--epochs", "3", "--hidden", "16"]),
    "training.maps.distill": (map_distill.main, ["--maps", "data", "--epochs", "2", "--lr", "0.01"]),
}


def _printed(capsys, main, argv) -> dict:
    assert main([*argv, "--print-config"]) == 0
    return json.loads(capsys.readouterr().out)


@pytest.mark.parametrize("name", COMMANDS)
def test_print_config_then_config_is_the_same_settings(name, capsys, tmp_path):
    main, argv = COMMANDS[name]
    first = _printed(capsys, main, argv)
    path = tmp_path / "c.json"
    path.write_text(json.dumps(first))
    assert _printed(capsys, main, ["--config", str(path)]) == first
    defaults = _printed(capsys, main, argv[:2])  # the required setting alone: the others at their defaults
    assert first != defaults


@pytest.mark.parametrize("name", COMMANDS)
def test_a_flag_beside_config_wins_over_its_key(name, capsys, tmp_path):
    main, argv = COMMANDS[name]
    first = _printed(capsys, main, argv)
    path = tmp_path / "c.json"
    path.write_text(json.dumps(first))
    again = _printed(capsys, main, ["--config", str(path), "--seed", "7"])
    assert again["seed"] == 7 and {k: v for k, v in again.items() if k != "seed"} == \
        {k: v for k, v in first.items() if k != "seed"}


@pytest.mark.parametrize("name", COMMANDS)
@pytest.mark.parametrize("edit, words", [({"no_such_setting": 1}, ["no_such_setting", "not a known key"]),
                                         ({"seed": "5"}, ["seed", "must be an integer"])])
def test_a_bad_key_is_one_error_naming_it(name, edit, words, capsys, tmp_path):
    main, argv = COMMANDS[name]
    data = _printed(capsys, main, argv)
    path = tmp_path / "c.json"
    path.write_text(json.dumps({**data, **edit}))
    assert main(["--config", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and all(w in err[0] for w in words), err


@pytest.mark.parametrize("name, flag", [("training.distill", "--tables"), ("training.maps.distill", "--maps")])
def test_a_required_setting_comes_from_a_flag_or_a_key(name, flag, capsys, tmp_path):
    main, argv = COMMANDS[name]
    assert main(["--epochs", "1"]) == 2
    assert f"{flag} is required" in capsys.readouterr().err
    path = tmp_path / "c.json"
    path.write_text(json.dumps(_printed(capsys, main, argv)))
    assert _printed(capsys, main, ["--config", str(path)])[flag[2:]] == _printed(capsys, main, argv)[flag[2:]]
