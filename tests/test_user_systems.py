"""Your own robot: user systems through the registry and table files, the kinematic single-track presets, q > 1
and d = 4 through tables, rollouts, distillation and controllers, and the build's size guidance."""

from __future__ import annotations

import json
import math
import re
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from cuniform_torch import CUMPPI, CUniformMPPI, TablePolicy, load_policy, read_table, rollout, write_table
from cuniform_torch.envs import Circle, Environment, NavigationCost, simulate
from cuniform_torch.grid.cells import Grid
from cuniform_torch.systems import (
    _REGISTRY,
    Dubins,
    KinematicSingleTrack,
    KinematicSingleTrackSpeed,
    UnknownSystemError,
    check_system,
    import_system_modules,
    make_system,
    register_system,
    resolve_system,
    se2_invariance_gap,
    system_from_json,
    system_to_json,
)
from cuniform_torch.tables.file import TableError
from precompute import build as build_cli
from precompute.flow.builder import BuildConfig, SizeGuide, build_table, estimate_build_bytes, project_level_sizes
from precompute.report import uniformity_report
from training import distill

README = Path(__file__).resolve().parents[1] / "README.md"

# small presets: seconds, not minutes
KS_SMALL = dict(cell_size=(0.1, 0.1, 2 * math.pi / 30), num_actions=7)
KS_SPEED_SMALL = dict(cell_size=(0.2, 0.2, 2 * math.pi / 18, 0.2), num_steer=3)
# plain features (--frequencies 0), as this plumbing test was written: with the encoding, 3 or 10 epochs of this
# network reached the goal of the ks closed loop below 2 times in 4 (the table itself: 6 in 8, seeds 0-7)
TINY = ["--hidden", "32", "--layers", "2", "--jitter", "1", "--batch-size", "512", "--lr", "1e-2", "--epochs", "3",
        "--frequencies", "0", "--eval-samples", "64", "--eval-every", "1000", "--quiet"]


@pytest.fixture(autouse=True)
def clean_registry():
    """Every test sees (and leaves) the built-in registry; imported user modules are forgotten again."""
    saved = dict(_REGISTRY)
    modules = set(sys.modules)
    threads = torch.get_num_threads()
    yield
    _REGISTRY.clear()
    _REGISTRY.update(saved)
    for name in set(sys.modules) - modules:
        if name.startswith("user_robot"):
            del sys.modules[name]
    torch.set_num_threads(threads)


USER_MODULE = '''
import dataclasses, math, torch
from cuniform_torch.systems import register_system, wrap_angle


@dataclasses.dataclass(frozen=True)
class SlowCar:
    speed: float = 0.5
    dt: float = 0.2
    cell_size: tuple = (0.05, 0.05, 2 * math.pi / 36)
    cell_offset: tuple = (0.0, 0.0, 0.01)
    name, periodic, se2_invariant = "slow_car", (False, False, True), True

    def action_set(self, dtype=torch.float32, device=None):
        return torch.linspace(-1.0, 1.0, 3, dtype=dtype, device=device).unsqueeze(1)

    def step(self, x, u):
        th = wrap_angle(x[:, 2] + u[:, 0] * self.dt)
        return torch.stack((x[:, 0] + self.speed * self.dt * th.cos(), x[:, 1] + self.speed * self.dt * th.sin(), th), 1)

    def params(self):
        return dataclasses.asdict(self)


def make_crab(step_size=0.1):  # a function factory: moves sideways, not SE(2)-invariant
    return Crab(step_size)


@dataclasses.dataclass(frozen=True)
class Crab:
    step_size: float = 0.1
    dt: float = 1.0
    cell_size: tuple = (0.1,)
    cell_offset: tuple = (0.0,)
    name, periodic, se2_invariant = "crab", (False,), False

    def action_set(self, dtype=torch.float32, device=None):
        return torch.tensor([[-1.0], [0.0], [1.0]], dtype=dtype, device=device)

    def step(self, x, u):
        return x + u * self.step_size

    def params(self):
        return {"step_size": self.step_size}


register_system("slow_car", SlowCar)  # --system-module imports this module; make_crab is registered by path
'''


@pytest.fixture
def user_module(tmp_path, monkeypatch):
    """An importable module ``user_robot_<n>`` that registers SlowCar when imported and defines a crab factory."""
    name = f"user_robot_{abs(hash(str(tmp_path))) % 10**8}"
    (tmp_path / f"{name}.py").write_text(USER_MODULE)
    monkeypatch.syspath_prepend(str(tmp_path))
    return name


def _forget(module: str, *systems: str) -> None:
    """As a fresh process: neither the module nor its systems are known."""
    sys.modules.pop(module, None)
    for s in systems:
        _REGISTRY.pop(s, None)


# ------------------------------------------------------------------------------------------- registry

def test_user_table_names_its_factory_but_a_fresh_process_must_trust_it(user_module, tmp_path):
    resolve_system(f"{user_module}:SlowCar")  # imports and registers under the system's own name
    system = make_system("slow_car", speed=0.4)
    spec = json.loads(system_to_json(system, 3))
    assert spec["factory"] == f"{user_module}:SlowCar" and spec["name"] == "slow_car"
    table, _ = build_table(system, BuildConfig(horizon=3))
    write_table(tmp_path / "slow.npz", table)
    _forget(user_module, "slow_car")
    with pytest.raises(TableError, match=rf"unknown system 'slow_car'.*the file names factory '{user_module}:SlowCar'"
                                         rf".*trust_factory='{user_module}:SlowCar'.*--system-module {user_module}"):
        read_table(tmp_path / "slow.npz")
    assert user_module not in sys.modules and "slow_car" not in _REGISTRY  # reading imported nothing
    back = read_table(tmp_path / "slow.npz", trust_factory=f"{user_module}:SlowCar")
    assert back.make_system().speed == 0.4 and "slow_car" in _REGISTRY


def test_importing_the_users_module_is_enough(user_module, tmp_path):
    resolve_system(f"{user_module}:SlowCar")
    table, _ = build_table(make_system("slow_car", speed=0.4), BuildConfig(horizon=2))
    write_table(tmp_path / "slow.npz", table)
    _forget(user_module, "slow_car")
    import_system_modules([user_module])  # what --system-module does
    assert read_table(tmp_path / "slow.npz").make_system().speed == 0.4


def test_trusted_factory_that_cannot_be_imported_names_it(user_module, tmp_path):
    resolve_system(f"{user_module}:SlowCar")
    table, _ = build_table(make_system("slow_car"), BuildConfig(horizon=2))
    write_table(tmp_path / "slow.npz", table)
    _forget(user_module, "slow_car")
    (tmp_path / f"{user_module}.py").unlink()
    with pytest.raises(TableError, match=r"system cannot be rebuilt: cannot import module"):
        read_table(tmp_path / "slow.npz", trust_factory=f"{user_module}:SlowCar")


def test_system_defined_in_a_script_has_no_factory_and_a_clear_error(tmp_path):
    namespace: dict = {}
    exec(compile(USER_MODULE, "script", "exec"), namespace)  # like a class defined in __main__
    register_system("slow_car", namespace["SlowCar"])
    text = system_to_json(make_system("slow_car"), 2)
    assert "factory" not in json.loads(text)
    _REGISTRY.pop("slow_car")
    with pytest.raises(UnknownSystemError, match=r"unknown system 'slow_car' \(known: .*\)\. Reading a file never "
                                                 r"imports code it names.*register_system\('slow_car', factory\)"):
        system_from_json(text)


def test_function_factory_and_parameters(user_module):
    name = resolve_system(f"{user_module}:make_crab")
    assert name == "crab"
    crab = make_system("crab", step_size=0.2)
    assert crab.step(torch.zeros(1, 1), torch.ones(1, 1)).item() == pytest.approx(0.2)
    with pytest.raises(ValueError, match=r"system 'crab': its factory does not accept \['wheels'\]"):
        make_system("crab", wheels=3)
    assert system_from_json(system_to_json(crab, 4))[0] == crab


@pytest.mark.parametrize("spec, match", [
    ("no_such_module_xyz:Car", r"cannot import module 'no_such_module_xyz'"),
    ("cuniform_torch.systems:NoSuchCar", r"module 'cuniform_torch.systems' has no 'NoSuchCar'"),
    ("cuniform_torch.systems:DEFAULT_HORIZON", r"is not callable"),
    ("hovercraft", r"unknown system 'hovercraft'.*--system-module"),
])
def test_resolve_system_errors(spec, match):
    with pytest.raises(ValueError, match=match):
        resolve_system(spec)


class _Broken:
    name, dt, cell_size, cell_offset, periodic, se2_invariant = "broken", 0.1, (0.1, 0.1), (0.0, 0.0), (False, False), False

    def action_set(self, dtype=torch.float32, device=None):
        return torch.zeros(2, 1, dtype=dtype)

    def step(self, x, u):
        return x.clone()

    def params(self):
        return {}


@pytest.mark.parametrize("change, match", [
    (dict(step=None), r"lacks step of the System protocol"),
    (dict(cell_size=(0.1,)), r"cell_size needs 2 value"),
    (dict(se2_invariant=True), r"SE\(2\)-invariant system needs the state \(x, y, theta, \.\.\.\)"),
    (dict(periodic=(False, True), cell_size=(0.1, 0.3)), r"bad grid: the angle cell size .*must be 2\*pi/K"),
    (dict(step=lambda x, u: x[:, :1]), r"step\(x, u\) .*\[2, 2\] tensor of torch.float64.* must return \[2, 2\]"),
    (dict(step=lambda x, u: x), r"returned x itself"),
    (dict(step=lambda x, u: x.add_(1)), r"changed its input x in place"),
    (dict(step=lambda x, u: (x + 1).long()), r"torch.int64.*nothing is cast silently"),
    (dict(action_set=lambda dtype=None, device=None: torch.zeros(0, 1, dtype=dtype)), r"non-empty \[A, q\]"),
    (dict(params=lambda: {"f": object()}), r"params\(\) must be JSON-serializable"),
    (dict(cell_offset=(0.5, 0.0)), r"bad grid"),
])
def test_check_system_names_what_is_wrong(change, match):
    system = _Broken()
    for key, value in change.items():
        setattr(system, key, value)
    with pytest.raises(ValueError, match=match):
        check_system(system)


def test_se2_invariance_gap_tells_invariant_from_not():
    assert se2_invariance_gap(Dubins()) < 1e-12
    assert se2_invariance_gap(KinematicSingleTrack()) < 1e-12
    speeds = torch.zeros(64, 4, dtype=torch.float64)
    speeds[:, 3] = torch.linspace(0, 1, 64)
    speeds[:, 2] = torch.linspace(-3, 3, 64)
    assert se2_invariance_gap(KinematicSingleTrackSpeed(), speeds) < 1e-12

    class Windy(KinematicSingleTrack):  # a drift along the world's x axis: not invariant
        def step(self, x, u):
            out = super().step(x, u)
            return torch.cat((out[:, :1] + 0.1, out[:, 1:]), 1)

    assert se2_invariance_gap(Windy()) > 0.05


# ------------------------------------------------------------------------------------- the ks presets

def test_ks_preset_and_dynamics():
    s = make_system("ks")
    assert (s.wheelbase, s.speed, s.dt, s.num_actions, s.default_horizon) == (0.324, 1.0, 0.2, 13, 15)
    assert s.cell_size == pytest.approx((0.03, 0.03, math.radians(6)))
    torch.testing.assert_close(s.action_set(torch.float64)[:, 0],
                               torch.linspace(-math.pi / 6, math.pi / 6, 13, dtype=torch.float64))
    x = torch.tensor([[1.0, 2.0, 0.3]], dtype=torch.float64)
    delta = 0.2
    theta = 0.3 + 1.0 * math.tan(delta) / 0.324 * 0.2
    expected = torch.tensor([[1.0 + 0.2 * math.cos(theta), 2.0 + 0.2 * math.sin(theta), theta]], dtype=torch.float64)
    torch.testing.assert_close(s.step(x, torch.tensor([[delta]], dtype=torch.float64)), expected)


def test_ks_speed_actions_are_a_product_grid_and_speed_steps_first():
    s = make_system("ks_speed")
    a = s.action_set(torch.float64)  # [15, 2]
    assert a.shape == (15, 2)
    steer = torch.linspace(-math.pi / 6, math.pi / 6, 5, dtype=torch.float64)
    torch.testing.assert_close(a[:, 0], steer.repeat_interleave(3))  # steering-major
    torch.testing.assert_close(a[:, 1], torch.tensor([-1.0, 0.0, 1.0], dtype=torch.float64).repeat(5))
    x = torch.tensor([[0.0, 0.0, 0.0, 0.5], [0.0, 0.0, 0.0, 0.9], [0.0, 0.0, 0.0, 0.1]], dtype=torch.float64)
    u = torch.tensor([[0.3, 1.0], [0.0, 1.0], [0.0, -1.0]], dtype=torch.float64)
    out = s.step(x, u)
    torch.testing.assert_close(out[:, 3], torch.tensor([0.7, 1.0, 0.0], dtype=torch.float64))  # clipped to [0, 1]
    theta = 0.7 * math.tan(0.3) / 0.324 * 0.2
    torch.testing.assert_close(out[0, :3], torch.tensor([0.7 * 0.2 * math.cos(theta), 0.7 * 0.2 * math.sin(theta),
                                                         theta], dtype=torch.float64))
    with pytest.raises(ValueError, match=r"need min_speed <= 0 <= max_speed"):
        make_system("ks_speed", min_speed=0.5)


@pytest.mark.parametrize("name", ["ks", "ks_speed"])
def test_float32_and_float64_land_in_the_same_cells(name):
    system = make_system(name)
    grid = Grid.of(system)
    A = system.action_set().shape[0]
    idx = torch.randint(0, A, (5000, 15), generator=torch.Generator().manual_seed(0))
    cells = []
    for dtype in (torch.float32, torch.float64):
        actions, x, out = system.action_set(dtype), torch.zeros(5000, grid.dim, dtype=dtype), []
        for t in range(idx.shape[1]):
            x = system.step(x, actions[idx[:, t]])
            out.append(grid.cells(x))
        cells.append(torch.stack(out))
    agree = (cells[0] == cells[1]).all(dim=-1).double().mean().item()
    assert agree > 0.995, agree


@pytest.fixture(scope="module")
def ks_speed_table():
    table, _ = build_table(make_system("ks_speed", **KS_SPEED_SMALL), BuildConfig(horizon=5))
    return table


@pytest.fixture(scope="module")
def ks_table():
    table, _ = build_table(make_system("ks", **KS_SMALL), BuildConfig(horizon=8))
    return table


def test_rollout_keeps_the_speed_through_the_frame_change(ks_speed_table):
    """Cross-check against a plain world-frame loop with the same actions; v is not touched by the frame change."""
    policy = TablePolicy(ks_speed_table, dtype=torch.float64)
    system = policy.system
    x0 = torch.tensor([1.0, -2.0, 2.5, 0.6], dtype=torch.float64)
    states, actions = rollout(system, policy, x0, 50, 5, torch.Generator().manual_seed(0))  # [50, 6, 4], [50, 5, 2]
    assert states.shape == (50, 6, 4) and actions.shape == (50, 5, 2)
    x = x0.expand(50, 4)
    for t in range(5):
        x = system.step(x, actions[:, t])
        torch.testing.assert_close(states[:, t + 1], x, atol=1e-9, rtol=0)
    assert states[:, 0, 3].eq(0.6).all()


def test_ks_speed_table_q2_policy_report_and_escape(ks_speed_table):
    table = ks_speed_table
    assert table.actions.shape == (9, 2) and table.cells.shape[1] == 4
    policy = TablePolicy(table)
    assert policy.action_probs(torch.zeros(3, 4), 0).shape == (3, 9)
    report = uniformity_report(table, num_rollouts=2000)
    # level sets from cell centres: a third of the states at some steps lie outside L_t, but always within one
    # cell of it (the nearest-cell fallback answers them); none escape the table
    assert report.miss_rate == 0.0 and 0 < report.nearest_rate < 0.5


def test_ks_table_and_ks_speed_table_distill_and_drive(ks_table, ks_speed_table, tmp_path):
    """A tiny distillation per table (d = 3 and q = 1; d = 4 and q = 2); the MLP's own proposals drive the closed
    loop (and a broken MLP does not)."""
    for name, table in (("ks", ks_table), ("ks_speed", ks_speed_table)):
        write_table(tmp_path / f"{name}.npz", table)
        argv = ["--tables", str(tmp_path / f"{name}.npz"), "--out", str(tmp_path / f"{name}.pt"),
                "--logdir", str(tmp_path / "runs"), *TINY]
        assert distill.main(argv) == 0
        policy = load_policy(tmp_path / f"{name}.pt")
        d, q = table.cells.shape[1], table.actions.shape[1]
        assert policy.config.state_dim == d and policy.actions.shape[1] == q
        states, actions = rollout(policy.system, policy, torch.zeros(d), 100, table.horizon)
        assert states.shape == (100, table.horizon + 1, d) and actions.shape == (100, table.horizon, q)
    # ks: around an obstacle on the straight line to the goal, on the MLP's proposals alone (no Gaussian pass)
    policy = load_policy(tmp_path / "ks.pt")
    env = Environment([Circle(center=(1.5, 0.0), radius=0.3)])
    cost = NavigationCost(env, goal=(3.0, 0.0), goal_tolerance=0.2)

    def outcome(controller) -> str:
        return simulate(policy.system, controller, torch.zeros(3), env, goal=(3.0, 0.0), goal_tolerance=0.2,
                        time_limit=8.0, cost=cost).outcome

    outcomes = [outcome(CUniformMPPI(policy, cost, num_samples=400, seed=s)) for s in range(4)]
    assert outcomes.count("goal") >= 3, outcomes
    assert outcome(CUMPPI(policy, cost, num_samples=400, seed=0)) == "goal"
    with torch.no_grad():  # the control: an MLP that always steers hard left drives neither controller there
        policy.net[-1].weight.zero_()
        policy.net[-1].bias.zero_()
        policy.net[-1].bias[0] = 50.0
    assert outcome(CUniformMPPI(policy, cost, num_samples=400, seed=0)) != "goal"
    assert outcome(CUMPPI(policy, cost, num_samples=400, seed=0)) != "goal"
    # ks_speed: from rest to a goal ahead
    policy = load_policy(tmp_path / "ks_speed.pt")
    env = Environment([])
    cost = NavigationCost(env, goal=(2.0, 0.5), goal_tolerance=0.25)
    result = simulate(policy.system, CUMPPI(policy, cost, num_samples=400, seed=0), torch.zeros(4), env,
                      goal=(2.0, 0.5), goal_tolerance=0.25, time_limit=8.0, cost=cost)
    assert result.outcome == "goal" and result.controls.shape[1] == 2


def test_proposal_bank_refuses_a_state_beyond_the_pose(ks_speed_table):
    cost = NavigationCost(Environment([]), goal=(1.0, 0.0))
    with pytest.raises(ValueError, match=r"proposal bank needs the state \(x, y, theta\) only; ks_speed has 4"):
        CUniformMPPI(TablePolicy(ks_speed_table), cost, num_samples=10, bank_size=20)


# ------------------------------------------------------------------------------------------ build CLI

def test_build_cli_with_a_user_module_and_params(user_module, tmp_path, capsys):
    out = tmp_path / "slow.npz"
    argv = ["--system-module", user_module, "--system", "slow_car", "--speed", "0.4", "--horizon", "3",
            "--out", str(out), "--quiet", "--rollouts", "200"]
    assert build_cli.main(argv) == 0
    _forget(user_module, "slow_car")
    assert read_table(out, trust_factory=f"{user_module}:SlowCar").make_system().speed == 0.4
    out2 = tmp_path / "crab.npz"
    argv = ["--system", f"{user_module}:make_crab", "--param", "step_size=0.2", "--horizon", "4", "--out", str(out2),
            "--quiet", "--no-report"]
    assert build_cli.main(argv) == 0
    assert read_table(out2).make_system().step_size == 0.2


@pytest.mark.parametrize("argv, match", [
    (["--system-module", "no_such_module_xyz"], r"--system-module no_such_module_xyz: cannot import it"),
    (["--system", "no_such_module_xyz:Car"], r"cannot import module 'no_such_module_xyz'"),
    (["--param", "speed"], r"--param needs KEY=VALUE"),
    (["--param", "speed=0.3", "--speed", "0.5"], r"speed given both as a flag and as --param"),
    (["--param", "speed=0.3", "--param", "speed=0.5"], r"--param speed given twice"),
    (["--param", "wheels=4"], r"system 'dubins' has no parameter\(s\) wheels"),
])
def test_build_cli_errors(argv, match, tmp_path, capsys):
    assert build_cli.main([*argv, "--out", str(tmp_path / "x.npz"), "--quiet"]) == 2
    assert re.search(match, capsys.readouterr().err)


def test_build_uses_the_system_default_horizon(tmp_path):
    out = tmp_path / "ks.npz"
    argv = ["--system", "ks_speed", "--cell-size", "0.4", "0.4", "0.6981317", "0.4", "--num-steer", "3",
            "--num-accel", "2", "--out", str(out), "--quiet", "--no-report"]
    assert build_cli.main(argv) == 0
    assert read_table(out).horizon == KinematicSingleTrackSpeed.default_horizon


# -------------------------------------------------------------------------------------- size guidance

def test_projection_leans_high_but_not_wildly(dubins_table, ks_table):
    for table in (dubins_table, ks_table):
        sizes = table.level_sizes
        for known in (5, 6):
            proj = project_level_sizes(sizes[:known + 1], table.horizon, table.actions.shape[0])
            assert proj[:known + 1] == sizes[:known + 1]
            assert 0.8 * sizes[-1] <= proj[-1] <= 4 * sizes[-1], (sizes, proj)
    with pytest.raises(ValueError, match=r"needs levels 0..3"):
        project_level_sizes([1, 4, 11], 10, 5)


def test_memory_estimate_grows_with_the_table():
    small = estimate_build_bytes([1, 10, 100], 20, 10, 3, 13)
    big = estimate_build_bytes([1, 10, 100, 1000, 10000], 20, 10, 3, 13)
    assert big > small > 0
    assert estimate_build_bytes([1, 10, 100], 20, 10, 3, 13, report=False) < small


def test_build_prints_the_projection_and_warns_before_exceeding_memory(tmp_path, capsys):
    argv = ["--system", "ks", "--cell-size", "0.1", "0.1", "0.2094395", "--num-actions", "7", "--horizon", "8",
            "--out", str(tmp_path / "ks.npz"), "--no-report", "--max-memory", "0.001"]
    assert build_cli.main(argv) == 0
    captured = capsys.readouterr()
    assert re.search(r"projected level sizes after 5 levels .*: \[\d+, \d+, \d+\] for levels 6..8", captured.out)
    assert re.search(r"warning: this build is projected to need about [\d.]+ GB, more than the 0.0 GB available "
                     r"\(--max-memory\); make it smaller with a shorter --horizon .* or a coarser grid \(--param cell_size=",
                     captured.err)
    report = json.loads((tmp_path / "ks.report.json").read_text())
    assert report["size_guide"]["warned"] and len(report["size_guide"]["projected_level_sizes"]) == 9
    # with room to spare: the projection, no warning
    argv[-1] = "1000"
    assert build_cli.main(argv) == 0
    captured = capsys.readouterr()
    assert "projected level sizes" in captured.out and "warning" not in captured.err


class _Step:
    def __init__(self, m):
        self.next_cells, self.src, self.arc_src = np.zeros((m, 3)), np.zeros(30 * m), np.zeros(10 * m)


def test_size_guide_is_silent_before_level_five_and_warns_once():
    guide = SizeGuide(horizon=10, num_actions=5, state_dim=3, budget_bytes=1.0)
    lines = [guide.update(_Step(m)) for m in (4, 11, 23, 44, 83)]
    assert lines[:4] == [[], [], [], []]
    assert lines[4][0].startswith("projected level sizes after 5 levels") and lines[4][1].startswith("warning")
    assert guide.update(_Step(157)) == [] and guide.exceeds  # warned once; the projection barely moved


def test_size_guide_retracts_a_warning_when_a_later_projection_fits():
    sizes = [1, 10, 57, 242, 772, 1997, 4436]  # the ks preset: level 5 projects 1.8 million cells, level 6 1.1
    guide = SizeGuide(horizon=15, num_actions=13, state_dim=3, budget_bytes=None)
    for m in sizes[1:6]:
        guide.update(_Step(m))
    guide.budget_bytes = guide.estimate_bytes * 0.9  # just below the level-5 projection
    guide.exceeds = True  # as if level 5 had warned
    lines = guide.update(_Step(sizes[6]))
    assert any(line.startswith("the projection now fits") for line in lines) and not guide.exceeds


# ------------------------------------------------------------------------------------- README example

def test_readme_your_own_robot_example(tmp_path, monkeypatch):
    text = README.read_text()
    section = text[text.index("## Your own robot"):]
    section = section[:section.index("\n## ", 1)]
    code = re.findall(r"```python\n(.*?)```", section, flags=re.S)[0]
    assert len(code.strip().splitlines()) < 30
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    exec(compile(code, "README.md (Your own robot)", "exec"), namespace)
    assert (tmp_path / "out" / "unicycle.npz").is_file() and (tmp_path / "out" / "unicycle.policy.pt").is_file()
    assert namespace["states"].shape == (200, 11, 3)
    assert namespace["policy"].system.speed == 0.5
    assert namespace["result"].outcome == "goal"


def test_built_in_systems_name_no_factory_and_user_systems_do():
    """A table of a built-in system is rebuilt from the registry by name; only a user system's JSON names its
    factory (so a built-in module that moves does not break its tables)."""
    import json

    from cuniform_torch.systems import is_builtin, known_systems, make_system, system_to_json
    from cuniform_torch.systems.registry import _REGISTRY

    for name in known_systems():
        if is_builtin(_REGISTRY[name]):
            assert "factory" not in json.loads(system_to_json(make_system(name), 3)), name
    assert {"double_integrator", "mountain_car", "dubins", "ks_speed"} <= {n for n in known_systems()
                                                                          if is_builtin(_REGISTRY[n])}
