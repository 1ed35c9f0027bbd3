"""Checks run once, at the edges (issue 35 item 2): one ``check_config`` and one read of each table file per
distillation; K checked at the flag and at the public constructor, and still one clear error at each."""

from __future__ import annotations

import hashlib
import io
import os
from pathlib import Path

import pytest
import torch

import training.distill as distill
from cuniform_torch.systems import make_system
from cuniform_torch.tables.file import read_table, read_table_sha256, write_table
from precompute.flow.builder import BuildConfig, build_table

TINY = ["--quiet", "--epochs", "1", "--hidden", "8", "--layers", "1", "--jitter", "1", "--batch-size", "64",
        "--eval-samples", "16", "--eval-every", "1000", "--threads", "1"]


@pytest.fixture(scope="module", autouse=True)
def restore_threads():
    """distill sets torch's thread count; give the other test modules theirs back."""
    threads = torch.get_num_threads()
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def walk_path(tmp_path_factory) -> Path:
    table, _ = build_table(make_system("random_walk_1d"), BuildConfig(horizon=3))
    path = tmp_path_factory.mktemp("tables") / "walk.npz"
    write_table(path, table)
    return path


def _count_opens(monkeypatch, target: Path) -> list[str]:
    """Every open of ``target`` (``os.open`` and ``io.open``, which zipfile and open_regular use) is recorded."""
    opened: list[str] = []
    real_os_open, real_io_open = os.open, io.open

    def os_open(path, *a, **k):
        if Path(path) == target:
            opened.append("os.open")
        return real_os_open(path, *a, **k)

    def io_open(file, *a, **k):
        if isinstance(file, (str, os.PathLike)) and Path(file) == target:
            opened.append("io.open")
        return real_io_open(file, *a, **k)

    monkeypatch.setattr(os, "open", os_open)
    monkeypatch.setattr(io, "open", io_open)
    return opened


def test_distill_checks_its_config_once_and_reads_the_table_once(walk_path, tmp_path, monkeypatch):
    calls: list[int] = []
    real = distill.check_config
    monkeypatch.setattr(distill, "check_config", lambda cfg: calls.append(1) or real(cfg))
    opened = _count_opens(monkeypatch, walk_path)
    argv = ["--tables", str(walk_path), "--out", str(tmp_path / "p.pt"), "--logdir", str(tmp_path / "runs"), *TINY]
    assert distill.main(argv) == 0
    assert len(calls) == 1, f"check_config ran {len(calls)} times in one distillation"
    assert len(opened) == 1, f"the table file was opened {len(opened)} times: {opened}"
    ckpt = torch.load(tmp_path / "p.pt", weights_only=True)
    assert ckpt["source"]["sha256"] == hashlib.sha256(walk_path.read_bytes()).hexdigest()


def test_read_table_sha256_is_read_table_and_the_file_digest(walk_path, tmp_path):
    table, sha = read_table_sha256(walk_path, graph=False)
    assert sha == hashlib.sha256(walk_path.read_bytes()).hexdigest()
    plain = read_table(walk_path, graph=False)
    assert (table.action_probs == plain.action_probs).all() and table.system == plain.system
    empty = tmp_path / "empty.npz"
    empty.write_bytes(b"")
    with pytest.raises(ValueError, match="not a readable .npz table"):
        read_table_sha256(empty)


def test_distill_library_call_still_checks_its_config(walk_path, tmp_path):
    cfg = distill.DistillConfig(tables=[str(walk_path)], out=str(tmp_path / "p.pt"), logdir=str(tmp_path), hidden=0)
    with pytest.raises(distill.UsageError, match="--hidden must be a positive integer, got 0"):
        distill.distill(cfg)


# ------------------------------------------------------------------------------------------ K, from --budgets on

def test_navigate_checks_its_budgets_once_from_the_flags(monkeypatch, tmp_path, capsys):
    """``main`` checks the config before any work and hands it to the unchecked ``_run``; ``run`` (the library
    edge) checks it itself."""
    from eval.navigate import run as nav

    calls: list[int] = []
    real = nav.check_config
    monkeypatch.setattr(nav, "check_config", lambda cfg: calls.append(1) or real(cfg))

    class Stop(Exception):
        pass

    def stop(*a, **k):
        raise Stop

    monkeypatch.setattr(nav, "_run", stop)
    with pytest.raises(Stop):
        nav.run(nav.NavConfig(budgets=(8,)), tmp_path / "lib")
    assert len(calls) == 1
    calls.clear()
    with pytest.raises(Stop):
        nav.main(["--budgets", "8", "--tasks", "1", "--out", str(tmp_path / "cli"), "--quiet"])
    assert len(calls) == 1, f"the config was checked {len(calls)} times on the way from the flags"


@pytest.mark.parametrize("budgets, message", [(("1",), "argument --budgets: must be an integer in [2, "),
                                               (("0",), "argument --budgets: must be an integer in [2, "),
                                               (("x",), "argument --budgets:")])
def test_a_bad_budget_flag_is_one_error_line(budgets, message, tmp_path, capsys):
    from eval.navigate import run as nav

    with pytest.raises(SystemExit) as exit_:  # argparse's exit, with the project's code
        nav.main(["--budgets", *budgets, "--out", str(tmp_path)])
    assert exit_.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and message in err[0], err


def test_a_bad_budget_at_the_library_edge(tmp_path):
    from eval.navigate import run as nav

    with pytest.raises(ValueError, match=r"every budget must be an integer >= 2 \(CU-MPPI splits it in two\), got \[1\]"):
        nav.run(nav.NavConfig(budgets=(1, 8)), tmp_path)


def _cost(states, actions):
    return (states ** 2).sum((-1, -2))


@pytest.mark.parametrize("k", [0, -3, 2.5, True, "8"])
def test_a_bad_k_at_each_public_constructor(k):
    from cuniform_torch.controllers.mppi import CUMPPI, MPPI
    from cuniform_torch.controllers.proposals import GaussianProposal
    from cuniform_torch.policies.table import TablePolicy

    system = make_system("random_walk_1d")
    table, _ = build_table(system, BuildConfig(horizon=3))
    message = rf"num_samples must be a positive integer, got {k!r}".replace(".", r"\.")
    for make in (lambda: MPPI(system, _cost, num_samples=k, horizon=3),
                 lambda: GaussianProposal(system, k, 3),
                 lambda: CUMPPI(TablePolicy(table), _cost, num_samples=k)):
        with pytest.raises(ValueError, match=message):
            make()


def test_a_plug_in_proposals_bad_k_at_the_core():
    """A user's proposal reaches the core unchecked: the core is its edge, and says which attribute is wrong."""
    from cuniform_torch.controllers.core import MPPICore

    class Plugin:
        system = make_system("random_walk_1d")
        num_samples, horizon, num_robots, device, dtype = 0, 3, 1, torch.device("cpu"), torch.float32

        def propose_batch(self, states, streams):
            raise AssertionError("never called")

        def update(self, result):
            pass

        def reset(self, robots=None):
            pass

    with pytest.raises(ValueError, match="num_samples must be a positive integer, got 0"):
        MPPICore(Plugin(), _cost)


# ------------------------------------------------------------------------------------------ one checks vocabulary

def test_one_positive_integer_check_keeps_each_sites_message_and_types():
    """The folded copies say what they said, and a config field still refuses a numpy integer (it is written
    to JSON as given) while a controller's K takes one (a K computed with numpy)."""
    import numpy as np

    from cuniform_torch.common.checks import check_positive_int
    from cuniform_torch.controllers.checks import check_positive_int as reexported
    from cuniform_torch.pytorch_mppi import MPPI_Batched
    from precompute.coverage.method import CoverageConfig

    assert reexported is check_positive_int
    assert check_positive_int("num_samples", np.int64(8)) == 8 and type(check_positive_int("K", np.int64(8))) is int
    with pytest.raises(ValueError, match=r"^steps must be a positive integer, got 0$"):
        CoverageConfig(steps=0)
    with pytest.raises(ValueError, match=r"^steps must be a positive integer, got np.int64\(3\)$|^steps must be a "
                                         r"positive integer, got 3$"):
        CoverageConfig(steps=np.int64(3))
    with pytest.raises(ValueError, match=r"^num_envs must be a positive integer, got True$"):
        MPPI_Batched(lambda s, a: s, lambda s, a: s.sum(-1), 1, torch.eye(1), num_envs=True)
