"""python -m eval.start_aware: a table set serving random starts, measured against each exact start's table."""

import json

import numpy as np
import pytest

from cuniform_torch.systems import make_system
from eval import start_aware


def _run(tmp_path, spec, *extra):
    out = tmp_path / "r.json"
    code = start_aware.main(["--system", "random_walk_1d", "--horizon", "4", "--starts", spec, "--random", "6",
                             "--samples", "400", "--cache", str(tmp_path / "cache"), "--json", str(out), "--quiet",
                             *extra])
    assert code == 0
    return json.loads(out.read_text())


def test_a_set_one_cell_apart_serves_every_start_like_its_own_table(tmp_path, capsys):
    result = _run(tmp_path, "0=-2:2:9")  # starts 0.5 m apart: the walk's cell
    s = result["summary"]
    assert s["miss_max"] == 0.0 and s["warned"] == 0
    assert s["ratio_min"] == pytest.approx(1.0) and s["miss_ok"] and s["coverage_ok"]
    assert s["nearest_mean"] == pytest.approx(s["exact_nearest_mean"])
    assert all(-2 <= r["start"][0] <= 2 for r in result["rows"])
    assert "6 starts: set miss rate max 0.000" in capsys.readouterr().out


def test_a_coarse_set_is_reported_as_missing(tmp_path):
    # starts 2 m (4 cells) apart: most random starts lie cells away from the nearest table's start
    s = _run(tmp_path, "0=-2:2:3")["summary"]
    assert s["warned"] > 0 and s["miss_max"] > 0.05 and not s["miss_ok"]


def test_random_starts_stay_in_the_set_box_and_poses_are_drawn_for_se2_systems():
    ks = make_system("ks_speed")
    box = np.zeros((3, 4))
    box[:, 3] = [0.2, 0.5, 0.8]
    starts = start_aware.random_starts(ks, box, 50, seed=1)
    assert ((starts[:, 3] >= 0.2) & (starts[:, 3] <= 0.8)).all()
    assert np.abs(starts[:, :2]).max() > 1 and np.abs(starts[:, 2]).max() <= np.pi
    assert np.ptp(starts[:, :3], axis=0).min() > 0


@pytest.mark.parametrize("flag, value", [("--random", "0"), ("--samples", "1"), ("--horizon", "0")])
def test_bad_counts_are_one_error(tmp_path, capsys, flag, value):
    code = start_aware.main(["--system", "random_walk_1d", "--starts", "0=-1:1:3", "--cache", str(tmp_path), flag,
                             value, "--quiet"])
    assert code == 2
    err = capsys.readouterr().err
    assert f"{flag} must be" in err and "Traceback" not in err
