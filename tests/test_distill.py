"""Distillation of a table into an MLP (python -m training.distill): quality, checkpoint, resume, outputs, errors.

Every run here is tiny: the 1-D random walk table of 4 steps (45 cells).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

import training.distill as distill
from cuniform_torch import CUniformMPPI, load_policy, read_table
from cuniform_torch.policies import PolicyCheckpointError
from cuniform_torch.systems import make_system
from cuniform_torch.tables.file import write_table
from precompute.flow.builder import BuildConfig, build_table
from training.tables.evaluate import cell_centres

# reaches a max abs probability error of about 0.044 at the cell centres (seed 0); one epoch gives about 0.6
QUALITY = ["--hidden", "128", "--layers", "3", "--epochs", "300", "--jitter", "16", "--batch-size", "256",
           "--lr", "1e-2"]
TOLERANCE = 0.06
TINY = ["--hidden", "16", "--layers", "2", "--jitter", "2", "--batch-size", "32", "--lr", "1e-2"]


pytestmark = pytest.mark.usefixtures("restore_threads")  # conftest: main sets torch's thread count


@pytest.fixture(scope="module")
def walk_path(tmp_path_factory) -> Path:
    """The 1-D random walk table, 4 steps (levels of 1, 5, 9, 13, 17 cells), as a file."""
    table, _ = build_table(make_system("random_walk_1d"), BuildConfig(horizon=4))
    path = tmp_path_factory.mktemp("tables") / "walk.npz"
    write_table(path, table)
    return path


def _argv(table: Path, folder: Path, *extra: str, name: str = "walk.policy.pt") -> list[str]:
    return ["--tables", str(table), "--out", str(folder / name), "--logdir", str(folder / "runs"), "--quiet",
            "--eval-samples", "64", "256", "--eval-every", "1000", *extra]


def _max_centre_error(policy, table) -> float:
    """Largest |pi(u | centre, t) - table row| over every cell and action."""
    centres = cell_centres(table).float()
    err = 0.0
    for t in range(table.horizon + 1):
        rows = table.level(t)
        q = policy.action_probs(centres[rows], t)
        err = max(err, float((q - torch.from_numpy(table.action_probs[rows])).abs().max()))
    return err


@pytest.fixture(scope="module")
def trained(walk_path, tmp_path_factory, train_capturing):
    """One quality distillation of the walk table; the trained module is captured where it is checkpointed."""
    folder = tmp_path_factory.mktemp("distill")
    module = train_capturing(distill, distill.main, _argv(walk_path, folder, *QUALITY))
    return {"folder": folder, "out": folder / "walk.policy.pt", "module": module}


class TestQuality:
    def test_walk_distillation_reaches_the_table_rows(self, trained, walk_path):
        err = _max_centre_error(load_policy(trained["out"]), read_table(walk_path))
        assert err < TOLERANCE, f"max abs probability error {err:.4f} at the cell centres"

    def test_the_tolerance_can_fail(self, walk_path, tmp_path):
        assert distill.main(_argv(walk_path, tmp_path, *QUALITY[:4], "--epochs", "1")) == 0
        assert _max_centre_error(load_policy(tmp_path / "walk.policy.pt"), read_table(walk_path)) > TOLERANCE


# The README's bound on the default table (mean KL at the cell centres); the default reaches about 0.03 here
DEFAULT_KL_BOUND = 0.08


@pytest.fixture(scope="module")
def dubins6_path(tmp_path_factory) -> Path:
    """The Dubins table of 6 steps (353 cells): small enough for a default distillation in a few seconds, with
    the cell-to-cell detail of the default table's last levels."""
    table, _ = build_table(make_system("dubins"), BuildConfig(horizon=6))
    path = tmp_path_factory.mktemp("tables") / "dubins6.npz"
    write_table(path, table)
    return path


def test_the_default_reaches_the_kl_bound(dubins6_path, tmp_path):
    """No training flag: the defaults of DistillConfig (a quality test, not a timed one)."""
    assert distill.main(_argv(dubins6_path, tmp_path, name="d6.policy.pt")) == 0
    comparison = json.loads((tmp_path / "d6.policy.comparison.json").read_text())
    kl = comparison["kl_centres"]["mean"]
    assert kl <= DEFAULT_KL_BOUND, f"mean KL at the cell centres {kl:.4f} with the default settings"


def test_default_epochs_shrink_on_large_tables():
    """The default stays 100 epochs on small tables and bounds cell passes on large ones (the paper-scale table of
    168,933 cells: 41 epochs, within 5 minutes on a 2-core CPU); a given --epochs is kept."""
    from training.tables.config import DistillConfig, with_epochs
    assert with_epochs(DistillConfig(), 4_027).epochs == 100
    assert with_epochs(DistillConfig(), 68_000).epochs == 100
    assert with_epochs(DistillConfig(), 168_933).epochs == 41
    assert with_epochs(DistillConfig(), 10**8).epochs == 20
    assert with_epochs(DistillConfig(epochs=7), 168_933).epochs == 7


class TestCheckpoint:
    def test_loads_with_weights_only_and_names_its_table(self, trained, walk_path):
        ckpt = torch.load(trained["out"], weights_only=True)
        assert ckpt["format"] == "cuniform-policy/1"
        assert ckpt["source"]["path"] == str(walk_path) and len(ckpt["source"]["sha256"]) == 64
        assert ckpt["metrics"]["kl_centres_mean"] < 0.05
        assert ckpt["config"]["hidden"] == 128 and ckpt["config"]["layers"] == 3

    def test_loaded_policy_equals_the_trained_module(self, trained):
        module, loaded = trained["module"], load_policy(trained["out"])
        x = torch.linspace(-2.5, 2.5, 41).unsqueeze(1)
        for t in range(5):
            assert torch.equal(loaded.action_probs(x, t), module.action_probs(x, t))

    @pytest.mark.parametrize("as_dict", [True, False])
    def test_controller_accepts_dict_and_module(self, trained, as_dict):
        policy = torch.load(trained["out"], weights_only=True) if as_dict else load_policy(trained["out"])
        ctrl = CUniformMPPI(policy, lambda states, actions: (states[:, -1, 0] - 1.0) ** 2, num_samples=64, seed=0)
        command = ctrl.command(torch.zeros(1))
        assert command.shape == (1,) and bool(torch.isfinite(command).all())

    def test_corrupt_file(self, tmp_path):
        path = tmp_path / "bad.pt"
        path.write_bytes(b"not a checkpoint at all")
        with pytest.raises(PolicyCheckpointError, match="not a readable policy checkpoint"):
            load_policy(path)

    def test_wrong_format(self, trained):
        ckpt = torch.load(trained["out"], weights_only=True)
        ckpt["format"] = "cuniform-policy/99"
        with pytest.raises(PolicyCheckpointError, match="unknown policy format"):
            load_policy(ckpt)

    def test_missing_tensor(self, trained):
        ckpt = torch.load(trained["out"], weights_only=True)
        del ckpt["state_dict"]["net.0.weight"]
        with pytest.raises(PolicyCheckpointError, match="state_dict does not match"):
            load_policy(ckpt)

    def test_misshaped_tensor(self, trained):
        ckpt = torch.load(trained["out"], weights_only=True)
        ckpt["state_dict"]["net.2.weight"] = torch.zeros(3, 3)
        with pytest.raises(PolicyCheckpointError, match="state_dict does not match"):
            load_policy(ckpt)


class TestOutputs:
    def test_comparison_json(self, trained):
        path = trained["folder"] / "walk.policy.comparison.json"
        c = json.loads(path.read_text())
        for key in ("tables", "checkpoint", "run", "config", "epochs_run", "best_epoch", "best_val_kl", "wall_seconds",
                    "sizes", "kl_centres", "kl_jitter", "coverage"):
            assert key in c, key
        assert set(c["sizes"]) == {"table_arrays_bytes", "table_file_bytes", "checkpoint_bytes", "compression_ratio",
                                   "file_ratio"}
        assert c["sizes"]["checkpoint_bytes"] == trained["out"].stat().st_size
        assert len(c["kl_centres"]["per_level"]) == 5 and len(c["kl_jitter"]["per_level"]) == 5
        assert set(c["coverage"]) == {"64", "256"}
        cov = c["coverage"]["256"]
        for side in ("table", "policy"):
            assert set(cov[side]) >= {"total", "per_level", "in_level_set", "nearest_rate", "miss_rate"}
        assert cov["policy"]["nearest_rate"] == 0 and cov["policy"]["miss_rate"] == 0
        assert cov["ratio"]["total"] == pytest.approx(cov["policy"]["total"] / cov["table"]["total"])
        # a good distillation covers about as much as its table (stated margin: 90%)
        assert cov["ratio"]["in_level_set_sum"] > 0.9

    def test_tensorboard_events(self, trained):
        runs = list((trained["folder"] / "runs").iterdir())
        assert len(runs) == 1 and runs[0].name.startswith("walk__distill__0__")
        assert list(runs[0].glob("events.out.tfevents.*"))

    def test_training_state_loads_with_weights_only(self, trained):
        state = torch.load(trained["folder"] / "walk.policy.pt.train.pt", weights_only=True)
        assert state["epoch"] >= 1 and state["finished"] and isinstance(state["rng_data"], torch.Tensor)


class _Interrupt(Exception):
    pass


class TestResume:
    def test_resumed_run_ends_at_the_same_weights(self, walk_path, tmp_path, monkeypatch):
        steady = _argv(walk_path, tmp_path / "steady", *TINY, "--epochs", "6")
        assert distill.main(steady) == 0
        original, calls = distill.save_train_state, []

        def interrupted(path, state):
            original(path, state)
            calls.append(state["epoch"])
            if len(calls) == 3:
                raise _Interrupt

        broken = _argv(walk_path, tmp_path / "broken", *TINY, "--epochs", "6")
        with monkeypatch.context() as mp:
            mp.setattr(distill, "save_train_state", interrupted)
            with pytest.raises(_Interrupt):
                distill.main(broken)
        assert not (tmp_path / "broken" / "walk.policy.pt").exists()
        assert distill.main(broken + ["--resume"]) == 0
        a = torch.load(tmp_path / "steady" / "walk.policy.pt", weights_only=True)["state_dict"]
        b = torch.load(tmp_path / "broken" / "walk.policy.pt", weights_only=True)["state_dict"]
        assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
        runs = list((tmp_path / "broken" / "runs").iterdir())
        assert len(runs) == 1  # the resumed run logs into the interrupted run's folder

    def test_resume_refuses_other_settings(self, walk_path, tmp_path, capsys):
        argv = _argv(walk_path, tmp_path, *TINY, "--epochs", "2")
        assert distill.main(argv) == 0
        assert distill.main(argv[:-2] + ["--lr", "2e-2", "--resume"]) == 2
        assert "different run" in capsys.readouterr().err

    def test_resume_without_state(self, walk_path, tmp_path, capsys):
        assert distill.main(_argv(walk_path, tmp_path, *TINY, "--epochs", "2", "--resume")) == 2
        assert "no training state" in capsys.readouterr().err


class TestBadInput:
    @pytest.fixture
    def corrupt(self, tmp_path) -> Path:
        path = tmp_path / "corrupt.npz"
        path.write_bytes(b"PK\x03\x04 truncated zip")
        return path

    @pytest.mark.parametrize("extra, message", [
        (["--hidden", "0"], "argument --hidden: must be an integer in [1, 65536]"),
        (["--layers", "-1"], "argument --layers: must be an integer in [1, 65536]"),
        (["--lr", "nan"], "argument --lr:"),
        (["--jitter", "-2"], "argument --jitter:"),
        (["--frequencies", "13"], "argument --frequencies:"),
        (["--threads", "-1"], "argument --threads:"),
        (["--device", "tpu:x"], "--device"),
        (["--eval-samples", "0"], "--eval-samples"),
        (["--epochs", "two"], "invalid int value"),
        (["--no-such-flag"], "unrecognized arguments"),
    ])
    def test_bad_flags(self, walk_path, tmp_path, capsys, extra, message):
        assert distill.main(_argv(walk_path, tmp_path, *extra)) == 2
        err = capsys.readouterr().err
        assert err.startswith("error: ") and message in err

    def test_missing_table(self, tmp_path, capsys):
        assert distill.main(_argv(tmp_path / "nowhere.npz", tmp_path)) == 2
        assert "no table file" in capsys.readouterr().err

    def test_corrupt_table(self, corrupt, tmp_path, capsys):
        assert distill.main(_argv(corrupt, tmp_path)) == 2
        assert "not a readable .npz table" in capsys.readouterr().err

    def test_tables_of_different_systems(self, walk_path, tmp_path, capsys):
        other, _ = build_table(make_system("random_walk_1d", max_speed=2.0), BuildConfig(horizon=4))
        write_table(tmp_path / "fast.npz", other)
        argv = _argv(walk_path, tmp_path)
        argv[2:2] = [str(tmp_path / "fast.npz")]  # --tables walk.npz fast.npz
        assert distill.main(argv) == 2
        assert "must share the system JSON" in capsys.readouterr().err

    def test_no_output_on_error(self, tmp_path):
        distill.main(_argv(tmp_path / "nowhere.npz", tmp_path))
        assert not any(tmp_path.iterdir())


def test_two_tables_of_one_system_are_pooled(walk_path, tmp_path):
    argv = _argv(walk_path, tmp_path, *TINY, "--epochs", "1")
    argv[2:2] = [str(walk_path)]
    assert distill.main(argv) == 0
    ckpt = torch.load(tmp_path / "walk.policy.pt", weights_only=True)
    assert len(json.loads(ckpt["source"]["all_tables"])) == 2
    assert np.isfinite(ckpt["metrics"]["kl_centres_mean"])


def test_checkpoint_records_the_tables_cells_as_support(trained, walk_path):
    """The loaded MLP knows exactly the cells it was trained on (and falls back outside them, as a table)."""

    table = read_table(walk_path)
    ckpt = torch.load(trained["out"], weights_only=True)
    np.testing.assert_array_equal(ckpt["support"]["cells"].numpy(), table.cells)
    np.testing.assert_array_equal(ckpt["support"]["level_offsets"].numpy(), table.level_offsets)
    policy = load_policy(trained["out"])
    far = torch.tensor([[float(table.cells.max()) * 0.1 + 5.0]])  # beyond level 1's cells and their halo
    probs = policy.action_probs(far, 1)
    assert torch.allclose(probs, torch.full_like(probs, 1 / probs.shape[1])) and int(policy.misses) == 1


def test_checkpoint_records_the_encoding(trained):
    """The default network reads the sin / cos encoding (config ``frequencies``); a network without it writes the
    config keys of the checkpoints written before the encoding, and one with it refuses a start-conditioned use."""
    from cuniform_torch.policies import MLPConfig, StartMLPPolicy, StartRegion

    ckpt = torch.load(trained["out"], weights_only=True)
    assert ckpt["config"]["frequencies"] == distill.DistillConfig.frequencies == 6
    module = trained["module"]
    assert module.net[0].in_features == module.config.num_state_features * 13
    plain = MLPConfig(**{**ckpt["config"], "frequencies": 0})
    assert "frequencies" not in plain.to_dict() and plain.num_features == plain.num_state_features
    with pytest.raises(ValueError, match="frequencies must be an integer in 0..12"):
        MLPConfig(**{**ckpt["config"], "frequencies": 13})
    cfg = MLPConfig(**{**ckpt["config"], "start_dims": [0]})
    with pytest.raises(ValueError, match="plain features"):
        StartMLPPolicy(cfg, module.system, module.actions, StartRegion(torch.zeros(1, 1, dtype=torch.float64), [0]))
