"""The map-table farm (precompute.maps.farm) and its data set reader (precompute.maps.dataset): a tiny BARN data set,
serial = --workers 2 byte for byte, resume per shard, the reader refusing broken or foreign shards, and the
train / test splits sharing no map."""

from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pytest
import torch

from precompute.levels.safe_map import LocalMap, SafeCells
from precompute.maps.dataset import MapDatasetError, file_sha256, read_map_dataset
from precompute.maps.farm import main as farm_main
from precompute.maps.worlds import World, crop_patch, split_of, suite_worlds

TINY = ["--suite", "barn", "--count", "2", "--poses-per-map", "2", "--split", "train", "--seed", "0",
        "--horizon", "3", "--patch", "20", "20", "--quiet"]
FILES = ("dataset.json", "shard-00000.npz", "shard-00001.npz")


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    out = tmp_path_factory.mktemp("farm") / "serial"
    assert farm_main(TINY + ["--out", str(out)]) == 0
    return out


def _copy(src, dst):
    shutil.copytree(src, dst)
    return dst


def test_the_farm_builds_a_data_set_the_reader_accepts(tiny):
    ds = read_map_dataset(tiny, load=True)
    assert len(ds) == 4 and ds.patch_shape == (20, 20) and ds.horizon == 3 and ds.split == "train"
    assert ds.patch_origin == (-0.5, -0.5) and ds.radius == 0.2 and ds.system.name == "dubins"
    entries = list(ds)
    assert [e.source for e in entries][::2] == [ds.entries[0]["source"], ds.entries[2]["source"]]
    for e in entries:
        assert e.level_offsets[1] == 1 and len(e.cells) == e.level_offsets[-1]
        np.testing.assert_allclose(e.action_probs.sum(axis=1), 1.0, atol=1e-6)
        # every entry's table is safe on its own patch: no cell centre in the inflated obstacles
        safe = SafeCells(ds.system, LocalMap(e.patch, ds.patch_origin, ds.patch_resolution), ds.radius)
        assert bool(safe.keep(torch.from_numpy(e.cells.astype(np.int64))).all())
    assert any(e.patch.any() for e in entries)  # BARN crops do see cylinders


def test_serial_and_two_workers_write_the_same_bytes(tiny, tmp_path):
    out = tmp_path / "workers"
    assert farm_main(TINY + ["--out", str(out), "--workers", "2"]) == 0
    for name in FILES:
        assert (out / name).read_bytes() == (tiny / name).read_bytes(), name


def test_a_rerun_skips_finished_shards_and_rebuilds_a_deleted_one(tiny, tmp_path, capsys):
    out = _copy(tiny, tmp_path / "resume")
    stamp = (out / "shard-00000.npz").stat().st_mtime_ns
    assert farm_main([a for a in TINY if a != "--quiet"] + ["--out", str(out)]) == 0
    assert "(0 built, 2 kept)" in capsys.readouterr().out
    assert (out / "shard-00000.npz").stat().st_mtime_ns == stamp
    (out / "shard-00001.npz").unlink()
    (out / "shard-00000.npz").write_bytes(b"damaged")  # a sha256 mismatch: rebuilt as well
    assert farm_main([a for a in TINY if a != "--quiet"] + ["--out", str(out)]) == 0
    assert "(2 built, 0 kept)" in capsys.readouterr().out
    for name in FILES:
        assert (out / name).read_bytes() == (tiny / name).read_bytes(), name
    assert farm_main(TINY + ["--out", str(out), "--seed", "1"]) == 2
    assert "other settings" in capsys.readouterr().err


def _rewrite_sha(out, k=0):
    meta = json.loads((out / "dataset.json").read_text())
    meta["shards"][k]["sha256"] = file_sha256(out / meta["shards"][k]["file"])
    (out / "dataset.json").write_text(json.dumps(meta))


def test_the_reader_refuses_corrupted_truncated_and_foreign_shards(tiny, tmp_path):
    bad = _copy(tiny, tmp_path / "flip")
    data = bytearray((bad / "shard-00000.npz").read_bytes())
    data[len(data) // 2] ^= 0xFF
    (bad / "shard-00000.npz").write_bytes(bytes(data))
    with pytest.raises(MapDatasetError, match=r"shard-00000\.npz: sha256 does not match"):
        read_map_dataset(bad)

    cut = _copy(tiny, tmp_path / "cut")
    (cut / "shard-00001.npz").write_bytes((tiny / "shard-00001.npz").read_bytes()[:-200])
    _rewrite_sha(cut, 1)
    with pytest.raises(MapDatasetError, match=r"shard-00001\.npz: not a readable \.npz shard"):
        read_map_dataset(cut, load=True)

    foreign = tmp_path / "other"  # another patch spec: its shard does not fit this data set
    assert farm_main([a if a != "20" else "16" for a in TINY] + ["--out", str(foreign), "--count", "1"]) == 0
    mixed = _copy(tiny, tmp_path / "mixed")
    shutil.copy(foreign / "shard-00000.npz", mixed / "shard-00000.npz")
    _rewrite_sha(mixed)
    with pytest.raises(MapDatasetError, match=r"shard-00000\.npz: patches must have shape \[2, 20, 20\]"):
        read_map_dataset(mixed, load=True)

    other_system = _copy(tiny, tmp_path / "system")
    meta = json.loads((other_system / "dataset.json").read_text())
    meta["actions"] = meta["actions"][:-1]
    (other_system / "dataset.json").write_text(json.dumps(meta))
    with pytest.raises(MapDatasetError, match=r"dataset\.json: actions do not match the system"):
        read_map_dataset(other_system)


def test_train_and_test_splits_share_no_map():
    for suite, count in (("barn", 30), ("forest", 6), ("gaps", 6)):
        for seed in (0, 1):
            train = {w.key for w in suite_worlds(suite, count, "train", seed, 0.2)}
            test = {w.key for w in suite_worlds(suite, count, "test", seed, 0.2)}
            assert len(train) == len(test) == count and not train & test, suite
            assert {split_of(k) for k in train} == {"train"} and {split_of(k) for k in test} == {"test"}
    with pytest.raises(ValueError, match="only 30 maps"):
        suite_worlds("barn", 31, "test", 0, 0.2)


def test_a_crop_is_the_world_in_the_robot_frame():
    """A disc at (1, 0.4) in the world, seen from a robot at (0.2, 0) heading +y, lies 0.8 m to its right and 0.4 m
    ahead: at (0.4, -0.8) in the robot frame."""
    world = World("t", 1, "t:1", np.array([[1.0, 0.4, 0.12]]), np.zeros((0, 4)), None, (-1, -1, 1, 1))
    patch = crop_patch(world, np.array([0.2, 0.0, math.pi / 2]), (60, 60), 0.05, (-1.5, -1.5))
    i, j = np.argwhere(patch == 1).mean(axis=0)
    assert abs((-1.5 + (j + 0.5) * 0.05) - 0.4) < 0.03 and abs((-1.5 + (i + 0.5) * 0.05) + 0.8) < 0.03
    assert 15 <= patch.sum() <= 25  # about pi 0.12^2 / 0.05^2 = 18 cells


def test_coverage_settings_reach_the_builder_and_the_header(tmp_path, capsys):
    """--steps / --tol / --state-budget / --merge-resolution are the coverage builder's (a farm run with them must
    differ from the defaults, and say so in its header); with --method maxflow they are refused."""
    cov = TINY + ["--method", "coverage"]
    cov[cov.index("--count") + 1] = "1"
    cov[cov.index("--poses-per-map") + 1] = "1"
    assert farm_main(cov + ["--out", str(tmp_path / "d")]) == 0
    assert farm_main(cov + ["--steps", "1", "--out", str(tmp_path / "s")]) == 0
    head_d = json.loads((tmp_path / "d" / "dataset.json").read_text())
    head_s = json.loads((tmp_path / "s" / "dataset.json").read_text())
    assert "coverage" not in head_d and head_s["coverage"] == {"steps": 1}
    a = read_map_dataset(tmp_path / "d").shard(0).arrays["action_probs"]
    b = read_map_dataset(tmp_path / "s").shard(0).arrays["action_probs"]
    assert a.shape == b.shape and not np.array_equal(a, b)  # one ascent step is not three hundred
    capsys.readouterr()
    assert farm_main(TINY + ["--steps", "5", "--out", str(tmp_path / "m")]) == 2
    assert "--steps: only for --method coverage" in capsys.readouterr().err
    assert farm_main(cov + ["--tol", "-1", "--out", str(tmp_path / "t")]) == 2
    assert "coverage settings: tol must be non-negative" in capsys.readouterr().err
