"""C-Uniform chosen for the user (precompute/auto.py, training/auto.py) on planted systems whose right answers are
known in closed form, its bad input, and a module:factory system's table set built by two worker processes."""

from __future__ import annotations

import dataclasses
import math
import sys
import textwrap

import pytest
import torch

from cuniform_torch.systems import DoubleIntegrator, register_system
from precompute.auto import AutoConfig, choose, level_sizes, parse_region


@dataclasses.dataclass(frozen=True)
class Walk:
    """A planted 1-D walk ``x' = x + u`` with ``num_actions`` moves evenly in ``[-step, step]``: its one-step
    resolution is ``2 step / (num_actions - 1)``, its spread after T steps ``2 step T``."""

    step_size: float = 0.3
    num_actions: int = 3
    cell_size: tuple = (0.1,)
    cell_offset: tuple = (0.0,)
    dt: float = 1.0
    name = "planted_walk"
    periodic = (False,)
    se2_invariant = False

    def action_set(self, dtype=torch.float32, device=None):
        return torch.linspace(-self.step_size, self.step_size, self.num_actions, dtype=dtype, device=device).unsqueeze(1)

    def step(self, x, u):
        return x + u

    def params(self):
        return dataclasses.asdict(self)


@pytest.fixture
def walk():
    register_system(Walk.name, Walk, overwrite=True)
    return Walk()


def test_walk_cell_is_its_step(walk):
    """With room in the budget the cell is the one-step resolution: every move is one whole cell."""
    c = choose(walk, "0=-1:1", AutoConfig(horizon=6, cell_budget=10_000, actions_per_dim=3))
    assert c.system.cell_size[0] == pytest.approx(0.3, rel=1e-9)
    assert c.spread[0] == pytest.approx(2 * 0.3 * 6, rel=1e-9)
    assert c.level_sizes == [1, 3, 5, 7, 9, 11, 13]  # exactly the walk's reachable cells
    assert c.system.action_set().shape == (3, 1)
    assert "one-step resolution" in " ".join(c.reasons)


def test_double_integrator_cells_follow_the_spread():
    """p' = p + v dt + a dt^2 / 2, v' = v + a dt: after T steps the position spreads a (T dt)^2 and the speed
    2 a T dt, so cells in proportion have c_p / c_v = T dt / 2; the scale is the finest that fits the budget."""
    T, dt, budget = 10, 0.1, 1500  # spreads 1 m and 2 m/s: unequal, so a wrong rule shows in the ratio
    c = choose(DoubleIntegrator(dt=dt), "0=-1:1 1=-1:1", AutoConfig(horizon=T, cell_budget=budget, member_budget=30))
    assert c.spread == pytest.approx([1.0 * (T * dt) ** 2, 2 * 1.0 * T * dt], rel=1e-9)
    cp, cv = c.system.cell_size
    assert cp / cv == pytest.approx(T * dt / 2, rel=1e-9)
    assert sum(c.level_sizes) <= budget
    finer = dataclasses.replace(c.system, cell_size=(cp / 1.05, cv / 1.05))
    worst = max(sum(level_sizes(finer, torch.tensor(s, dtype=torch.float64), T)) for s in
                [(0.0, 0.0), (1.0, 1.0), (-1.0, -1.0), (1.0, -1.0)])
    assert worst > budget  # 5% finer no longer fits: the budget binds
    # the start grid: moving p0 by h moves every position by h; moving v0 by h moves p_t by h t dt and v by h
    assert c.shift == pytest.approx([1 / cp, max(T * dt / cp, 1 / cv)], rel=1e-6)
    assert len(c.starts) <= 30 and c.counts[0] * c.counts[1] == len(c.starts)
    assert c.system.num_actions == 5


def test_member_budget_and_shift():
    """Enough members: a start half a spacing away sees level sets within the allowed shift; too few: the report
    says the budget binds and the predicted shift is larger."""
    cfg = AutoConfig(horizon=6, cell_budget=400, member_budget=10_000, shift_cells=2.0)
    roomy = choose(DoubleIntegrator(), "0=-0.2:0.2 1=-0.2:0.2", cfg)
    assert roomy.predicted_shift <= 2.0 + 1e-9
    tight = choose(DoubleIntegrator(), "0=-0.2:0.2 1=-0.2:0.2", dataclasses.replace(cfg, member_budget=4))
    assert len(tight.starts) <= 4 and tight.predicted_shift > 2.0
    assert "budget of 4 binds" in tight.reasons[-1]


def test_bad_input_is_one_clear_error(walk):
    with pytest.raises(ValueError, match="not a start dimension|dimension 3"):
        parse_region("3=0:1", walk)
    with pytest.raises(ValueError, match="DIM=LO:HI"):
        parse_region("0=1", walk)
    with pytest.raises(ValueError, match="LO <= HI"):
        parse_region("0=1:-1", walk)

    @dataclasses.dataclass(frozen=True)
    class Forgetful(Walk):
        def params(self):
            return {"step_size": self.step_size}  # the chosen cell would be lost in a table file

    with pytest.raises(ValueError, match=r"params\(\) must return its"):
        choose(Forgetful(), "0=-1:1", AutoConfig(horizon=3))

    @dataclasses.dataclass(frozen=True)
    class NoCells:
        name = "no_cells"
        periodic = (False,)
        se2_invariant = False
        dt: float = 1.0

        @property
        def cell_size(self):
            return (0.1,)

        cell_offset = (0.0,)

        def action_set(self, dtype=torch.float32, device=None):
            return torch.tensor([[-1.0], [1.0]], dtype=dtype, device=device)

        def step(self, x, u):
            return x + u

        def params(self):
            return {}

    with pytest.raises(ValueError, match="cell_size field"):
        choose(NoCells(), "0=-1:1", AutoConfig(horizon=3))
    with pytest.raises(ValueError, match="cell_budget"):
        AutoConfig(cell_budget=0)


def test_auto_cuniform_builds_distils_and_reuses(tmp_path, restore_threads):
    """The one call: a set, its start-conditioned MLP, a controller that commands; a second call reuses both."""
    from cuniform_torch.policies.start_mlp import StartMLPPolicy
    from training.auto import DistillBudget, auto_cuniform

    kw = dict(out=tmp_path, config=AutoConfig(cell_budget=150, member_budget=4),
              distill=DistillBudget(hidden=8, layers=1, epochs=2), quiet=True)
    auto = auto_cuniform(DoubleIntegrator(), "0=-0.2:0.2 1=-0.2:0.2", 4, **kw)
    assert isinstance(auto.mlp, StartMLPPolicy) and len(auto.table_set.members) == len(auto.choice.starts) > 1
    ctrl = auto.controller(lambda s, a: (s[:, 1:, 0] ** 2).sum(dim=1), num_samples=16, seed=0)
    assert ctrl.command(torch.tensor([0.05, -0.1])).shape == (1,)
    again = auto_cuniform(DoubleIntegrator(), "0=-0.2:0.2 1=-0.2:0.2", 4, **kw)
    assert again.path == auto.path and again.seconds["build"] < 1.0 and again.seconds["distill"] < 1.0
    assert "why cells" in auto.report()


def test_module_factory_set_with_two_workers(tmp_path, monkeypatch):
    """``--system module:Factory --workers 2``: each spawned worker registers the factory before it builds (it
    used to fail: 'unknown system ... 0 of 3 were written')."""
    from precompute.build import main

    (tmp_path / "planted_robots.py").write_text(textwrap.dedent('''
        import dataclasses, torch
        @dataclasses.dataclass(frozen=True)
        class Drift:
            cell_size: tuple = (0.1, 0.1)
            cell_offset: tuple = (0.0, 0.0)
            dt: float = 0.1
            name = "planted_drift"
            periodic = (False, False)
            se2_invariant = False
            def action_set(self, dtype=torch.float32, device=None):
                return torch.tensor([[-1.0], [0.0], [1.0]], dtype=dtype, device=device)
            def step(self, x, u):
                return torch.stack((x[:, 0] + x[:, 1] * self.dt, x[:, 1] + u[:, 0] * self.dt), 1)
            def params(self):
                return dataclasses.asdict(self)
    '''))
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, "planted_robots", raising=False)
    out = tmp_path / "set"
    code = main(["--system", "planted_robots:Drift", "--horizon", "3", "--starts", "1=-0.5:0.5:3", "--out", str(out),
                 "--workers", "2", "--quiet"])
    assert code == 0
    assert sorted(p.name for p in out.glob("start_*.npz")) == ["start_0000.npz", "start_0001.npz", "start_0002.npz"]


def test_unimportable_factory_with_workers_is_a_clear_error(tmp_path):
    from precompute.one_table import TableJob
    from precompute.table_set import build_table_set

    @dataclasses.dataclass(frozen=True)
    class Local(Walk):
        name = "planted_local_walk"

    register_system(Local.name, Local, overwrite=True)
    job = TableJob(system=Local(), out=tmp_path / "s" / "start_0000.npz", report=False, quiet=True)
    with pytest.raises(ValueError, match="cannot be imported by a worker"):
        build_table_set(job, [[0.0], [1.0]], tmp_path / "s", workers=2)
    assert not (tmp_path / "s" / "start_0000.npz").exists()


def test_angle_cells_are_whole_turn_fractions():
    """A periodic dimension's chosen cell is 2 pi / K (the grid's contract)."""
    from cuniform_torch.systems import make_system

    dubins = make_system("dubins")
    with pytest.raises(ValueError, match="not a start dimension"):  # an SE(2)-invariant system: no pose starts
        parse_region("2=-1:1", dubins)
    from eval.auto_pendulum import Pendulum

    register_system(Pendulum.name, Pendulum, overwrite=True)
    c = choose(Pendulum(), "0=-3.141592653589793:3.141592653589793 1=-2:2", AutoConfig(horizon=6, cell_budget=300,
                                                                                        member_budget=8))
    k = 2 * math.pi / c.system.cell_size[0]
    assert abs(k - round(k)) < 1e-9
