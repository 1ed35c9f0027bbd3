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
    try:  # the parser refuses them (argparse: SystemExit 2 and its one error line)
        code = start_aware.main(["--system", "random_walk_1d", "--starts", "0=-1:1:3", "--cache", str(tmp_path), flag,
                                 value, "--quiet"])
    except SystemExit as exc:
        code = exc.code
    assert code == 2
    err = capsys.readouterr().err
    assert f"{flag}: must be" in err and "Traceback" not in err


# ------------------------------------------------------------------------------------------------ a user's own system

CART_MODULE = '''
import dataclasses, torch
from cuniform_torch.systems import register_system


@dataclasses.dataclass(frozen=True)
class Cart:  # position and speed, pushed: 2-D, not SE(2)-invariant
    dt: float = 0.5
    cell_size: tuple = (0.1, 0.1)
    cell_offset: tuple = (0.0, 0.0)
    name, periodic, se2_invariant = "user_cart", (False, False), False

    def action_set(self, dtype=torch.float32, device=None):
        return torch.tensor([[-0.2], [0.0], [0.2]], dtype=dtype, device=device)

    def step(self, x, u):
        v = x[:, 1] + u[:, 0]
        return torch.stack((x[:, 0] + v * self.dt, v), 1)

    def params(self):
        return dataclasses.asdict(self)


register_system("user_cart", Cart)
'''


@pytest.fixture
def cart_module(tmp_path, monkeypatch):
    """An importable module that registers the user's 2-D system ``user_cart``; forgotten again afterwards."""
    import sys

    from cuniform_torch.systems import _REGISTRY

    name = f"user_cart_{abs(hash(str(tmp_path))) % 10**8}"
    (tmp_path / f"{name}.py").write_text(CART_MODULE)
    monkeypatch.syspath_prepend(str(tmp_path))
    saved = dict(_REGISTRY)
    yield name
    _REGISTRY.clear()
    _REGISTRY.update(saved)
    sys.modules.pop(name, None)


def test_a_set_of_a_user_system_is_measured_with_its_own_system(tmp_path, cart_module, capsys):
    """--set DIR of a user's 2-D system: the system, parameters and horizon are the set's (not ks_speed's)."""
    from precompute.build import main as build

    folder = tmp_path / "cart_set"
    assert build(["--system-module", cart_module, "--system", "user_cart", "--param", "dt=0.4", "--horizon", "3",
                  "--starts", "0=-0.2:0.2:5 1=-0.2:0.2:5", "--out", str(folder), "--quiet"]) == 0
    out = tmp_path / "r.json"
    assert start_aware.main(["--system-module", cart_module, "--set", str(folder), "--random", "3", "--samples",
                             "50", "--json", str(out), "--quiet"]) == 0
    result = json.loads(out.read_text())
    assert result["system"] == "user_cart" and result["params"]["dt"] == 0.4 and result["horizon"] == 3
    assert len(result["rows"]) == 3 and all(len(r["start"]) == 2 for r in result["rows"])
    assert all(-0.2 <= v <= 0.2 for r in result["rows"] for v in r["start"])
    assert "user_cart horizon 3: set of 25 starts" in capsys.readouterr().out
    for extra, message in ((["--system", "ks_speed"], "holds a user_cart set, but --system says ks_speed"),
                           (["--horizon", "5"], "its tables have horizon 3, --horizon says 5"),
                           (["--param", "dt=0.5"], "--param asks for {'dt': 0.5}"),
                           (["--starts", "0=0:1:3"], "not both")):
        code = start_aware.main(["--system-module", cart_module, "--set", str(folder), "--quiet", *extra])
        err = capsys.readouterr().err
        assert code == 2 and message in err and "Traceback" not in err, err


def test_each_start_is_its_own_episode(tmp_path):
    """The warn column is per start: a start whose member already warned for an earlier start warns again."""
    rows = _run(tmp_path, "0=-2:2:2", "--random", "8")["rows"]  # two members 8 cells apart: most starts are off
    off = [r for r in rows if r["set_miss_rate"] > 0]
    assert len(off) >= 3 and all(r["warned"] for r in off)
