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
