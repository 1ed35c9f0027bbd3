"""The classic built-in systems (cuniform_torch/systems/classic.py): ``double_integrator`` and ``mountain_car``."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
import torch

from cuniform_torch import load_table, read_table, rollout
from cuniform_torch.systems import DoubleIntegrator, MountainCar, check_system, known_systems, make_system
from precompute.build import main


def test_both_are_registered_and_pass_check_system():
    assert {"double_integrator", "mountain_car"} <= set(known_systems())
    for name in ("double_integrator", "mountain_car"):
        system = make_system(name)
        check_system(system)
        assert system.state_dim == 2 and system.periodic == (False, False) and not system.se2_invariant
    assert make_system("mountain_car", repeat=3).dt == 3.0  # one env step is the env's unit of time
    with pytest.raises(ValueError, match="repeat"):
        MountainCar(repeat=0)
    with pytest.raises(ValueError, match="max_accel"):
        DoubleIntegrator(max_accel=-1.0)


def test_double_integrator_moves_exactly():
    system = DoubleIntegrator(dt=0.3, max_accel=2.0, num_actions=5)
    actions = system.action_set(torch.float64)
    assert actions[:, 0].tolist() == [-2.0, -1.0, 0.0, 1.0, 2.0]
    gen = torch.Generator().manual_seed(0)
    x = torch.randn((64, 2), generator=gen, dtype=torch.float64)
    u = actions[torch.randint(0, 5, (64,), generator=gen)]
    out = system.step(x, u)
    p, v, a, dt = x[:, 0], x[:, 1], u[:, 0], 0.3
    torch.testing.assert_close(out[:, 0], p + v * dt + 0.5 * a * dt**2, rtol=0, atol=1e-15)
    torch.testing.assert_close(out[:, 1], v + a * dt, rtol=0, atol=1e-15)
    assert system.step(x.float(), u.float()).dtype == torch.float32


def _env():
    gym = pytest.importorskip("gymnasium")
    env = gym.make("MountainCarContinuous-v0").unwrapped
    env.reset(seed=0)
    return env


def _env_steps(env, state, force: float, k: int) -> np.ndarray:
    """The env's state after ``k`` steps of ``force`` from ``state``."""
    env.state = np.array(state, dtype=np.float64)
    for _ in range(k):
        obs, *_ = env.step(np.array([force], dtype=np.float32))
    return np.asarray(obs, dtype=np.float64)


# states and forces that reach every branch: both walls, both speed limits, forces outside [-1, 1]
_EDGES = [((-1.19, -0.07), -1.0), ((-1.2, 0.0), -1.0), ((-1.2, -0.01), 0.5), ((0.59, 0.07), 1.0),
          ((0.0, 0.0699), 1.0), ((-0.5, -0.0699), -1.0), ((-0.5, 0.0), 3.0), ((-0.5, 0.0), -7.5), ((0.3, 0.02), 0.2)]


@pytest.mark.parametrize("repeat", [1, 4])
def test_mountain_car_is_the_gymnasium_env_step_for_step(repeat):
    env = _env()
    system = MountainCar(repeat=repeat)
    rng = np.random.default_rng(1)
    cases = _EDGES + [((rng.uniform(-1.2, 0.6), rng.uniform(-0.07, 0.07)), rng.uniform(-1.5, 1.5))
                      for _ in range(40)]
    want = np.stack([_env_steps(env, s, f, repeat) for s, f in cases])  # [C, 2]
    x = torch.tensor([s for s, _ in cases], dtype=torch.float64)
    u = torch.tensor([[f] for _, f in cases], dtype=torch.float64)
    got = system.step(x, u).numpy()
    np.testing.assert_allclose(got, want, rtol=0, atol=2e-6)  # the env rounds its state to float32
    assert np.array_equal(got[:, 1] == 0, want[:, 1] == 0)  # the inelastic left wall, exactly
    if repeat == 1:  # the cases that hit the wall in their first env step
        assert (got[[0, 2], 1] == 0).all() and got[0, 0] == -1.2 and got[1, 1] > 0  # gravity pushes off the wall


def test_mountain_car_follows_a_whole_episode():
    """From the env's reset state, 150 model steps of 5 env steps each (a swing that reaches the left wall and
    the right end), the model resynced to the env's float32 state every model step."""
    env = _env()
    system = MountainCar(repeat=5)
    state, _ = env.reset(seed=3)
    rng = np.random.default_rng(2)
    walls, right = 0, -1.0
    for t in range(150):
        force = float(np.sign(state[1]) or 1.0) if rng.random() < 0.8 else float(rng.uniform(-1, 1))
        force = -1.0 if 40 <= t < 60 else force  # pushed into the left wall
        model = system.step(torch.tensor(np.array([state]), dtype=torch.float64), torch.tensor([[force]], dtype=torch.float64))
        env.state = np.array(state, dtype=np.float64)
        for _ in range(5):
            state, *_ = env.step(np.array([force], dtype=np.float32))
            walls += bool(state[0] <= -1.2 + 1e-6)
            right = max(right, float(state[0]))
        np.testing.assert_allclose(model[0].numpy(), state, rtol=0, atol=2e-6)
    assert walls >= 1 and right >= 0.6 - 1e-6


@pytest.mark.parametrize("name,start,starts", [("double_integrator", ["0.5", "-0.5"], "0=-1:1:2 1=-0.5:0.5:2"),
                                               ("mountain_car", ["-0.5", "0"], "0=-1:0.2:2 1=-0.04:0.04:2")])
def test_tables_and_a_four_start_set_build(tmp_path, name, start, starts):
    base = ["--system", name, "--horizon", "6", "--quiet", "--no-report"]
    assert main([*base, "--start", *start, "--out", str(tmp_path / "one.npz")]) == 0
    table = read_table(tmp_path / "one.npz")
    assert table.start.tolist() == [float(s) for s in start] and len(table.level_offsets) == 6 + 2
    system = make_system(name)
    want = np.round(np.array([float(s) for s in start]) / system.cell_size + system.cell_offset)
    assert table.cells[0].tolist() == want.tolist()  # level 0 is the start's cell
    assert main([*base, "--starts", starts, "--out", str(tmp_path / "set")]) == 0
    index = json.loads((tmp_path / "set" / "tables.json").read_text())
    assert index["system"] == name and len(index["tables"]) == 4
    policy = load_table(tmp_path / "set")
    x0 = torch.tensor(index["tables"][3]["start"], dtype=torch.float32)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # from a start of the set: no StartMismatchWarning
        rollout(policy.system, policy, x0, 200, 6, torch.Generator().manual_seed(0))
    assert policy.last_index == 3 and policy.last_start_distance < 1e-5  # x0 in float32
