"""Map files: map data sets (the farm's shards and ``dataset.json``) and local map files (``read_map_file``).

Cells, rows, patches and metadata that do not match, members whose headers claim more than the file holds (refused
before allocation), a damaged content digest and special files are each one clear error; old files without a
digest still load, with a one-line note; the commands refuse the deep defects by default."""

from __future__ import annotations

import contextlib
import io
import json
import os
import re
import resource
import shutil
import tracemalloc
import zipfile

import numpy as np
import pytest
from cases import DEEP
from hardening_helpers import _fifo, _forged_member, _quick

from cuniform_torch.common.digest import DIGEST_KEY, content_digest
from cuniform_torch.common.fileio import (
    write_npz,
)
from precompute.levels.safe_map import LocalMap, MapError, read_map_file, write_map_file
from precompute.maps.dataset import MapDatasetError, file_sha256, read_map_dataset
from precompute.maps.farm import main as farm_main
from training.maps.data import load_map_data


def _system(**over):
    def meta(m):
        m["system"] = json.dumps({**json.loads(m["system"]), **over}, sort_keys=True)
    return meta


def _patch(**over):
    return lambda m: m["patch"].update(over)


@contextlib.contextmanager
def _memory_capped(extra: int):
    """The address space capped at what the process maps now + ``extra`` bytes (a reader that allocates what a
    forged count asks for fails with MemoryError here, not by taking the machine's memory)."""
    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    with open("/proc/self/status") as f:
        size = next(int(line.split()[1]) * 1024 for line in f if line.startswith("VmSize:"))
    cap = size + extra if hard == resource.RLIM_INFINITY else min(hard, size + extra)
    resource.setrlimit(resource.RLIMIT_AS, (cap, hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_AS, (soft, hard))


TINY = ["--suite", "barn", "--count", "2", "--poses-per-map", "2", "--split", "train", "--seed", "0",
        "--horizon", "3", "--patch", "20", "20", "--quiet"]


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    out = tmp_path_factory.mktemp("strict") / "ds"
    assert farm_main(TINY + ["--out", str(out)]) == 0
    return out


def _arrays(folder, k=0):
    with np.load(folder / f"shard-{k:05d}.npz", allow_pickle=False) as z:
        return {key: z[key] for key in z.files}


SHARD = "shard-00000.npz"


def _plant(tiny, tmp_path, change=None, meta=None, digest="recompute", k=0):
    """A copy of ``tiny`` whose shard ``k`` went through ``change(arrays)`` and whose dataset.json through
    ``meta(dict)``; the shard's digest recomputed (a forger's copy), kept (damage) or dropped (an old shard), and
    dataset.json's sha256 of it rewritten, so that only the check under test can refuse it."""
    out = tmp_path / "ds"
    shutil.copytree(tiny, out)
    if change is not None:
        arrays = _arrays(out, k)
        old = arrays.pop(DIGEST_KEY)
        change(arrays)
        if digest == "recompute":
            arrays[DIGEST_KEY] = np.array(content_digest(arrays))
        elif digest == "keep":
            arrays[DIGEST_KEY] = old
        write_npz(out / f"shard-{k:05d}.npz", arrays)
    m = json.loads((out / "dataset.json").read_text())
    m["shards"][k]["sha256"] = file_sha256(out / m["shards"][k]["file"])
    if meta is not None:
        meta(m)
    (out / "dataset.json").write_text(json.dumps(m))
    return out


def _level(a, m, t):
    """Rows of level t of entry m."""
    start = int(a["entry_offsets"][m])
    return start + int(a["level_offsets"][m][t]), start + int(a["level_offsets"][m][t + 1])


def _refused(folder, words, **kw):
    with pytest.raises(MapDatasetError, match=words) as info:
        read_map_dataset(folder, load=True, **kw)
    assert SHARD in str(info.value) or "dataset.json" in str(info.value)
    return str(info.value)


def _duplicate(a):
    lo, hi = _level(a, 0, 2)
    a["cells"][lo + 1] = a["cells"][lo]


def _swap_rows(a):  # whole rows (cell, action row, cell probability) swapped: the same table, out of order
    lo, hi = _level(a, 0, 2)
    for key in ("cells", "action_probs", "cell_probs"):
        a[key][[lo, hi - 1]] = a[key][[hi - 1, lo]]


def _origin(a):
    a["cells"][0, 0] += 1


def _huge_index(a):
    lo, hi = _level(a, 0, 3)
    a["cells"][hi - 1, 0] = 2**31 - 1  # the last row of its level: still ascending


def _reverse_actions(entry):
    def change(a):
        lo, hi = _level(a, entry, 2)
        a["action_probs"][lo:hi] = a["action_probs"][lo:hi][::-1]
    return change


def _full(a):
    a["patches"][1] = 1


def _transposed(a):
    a["patches"][:] = np.ascontiguousarray(a["patches"].transpose(0, 2, 1))


def _twos(a):
    a["patches"][0, 0, 0] = 2


def _system_param(key, value):
    def meta(m):
        s = json.loads(m["system"])
        s["params"][key] = value
        m["system"] = json.dumps(s)
    return meta


_MB = 1 << 20




def _rezip(path, arrays, forged):
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        for key, value in arrays.items():
            if key in forged:
                zf.writestr(f"{key}.npy", forged[key])
            else:
                buf = io.BytesIO()
                np.lib.format.write_array(buf, np.asarray(value), allow_pickle=False)
                zf.writestr(f"{key}.npy", buf.getvalue())


def _peak(fn):
    tracemalloc.start()
    try:
        fn()
    finally:
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    return peak


def _map(tmp_path):
    occ = np.zeros((8, 8), np.uint8)
    occ[2, 5] = 1
    path = tmp_path / "m.npz"
    write_map_file(path, LocalMap(occ, (-0.2, -0.2), 0.05))
    return path, occ


def _commands(tiny, tmp_path):
    """A map policy and the blind table of the tiny data set's system, for evaluate and coverage."""
    from cuniform_torch.maps.checkpoint import map_policy_checkpoint, save_map_policy
    from cuniform_torch.systems import system_from_json
    from cuniform_torch.tables.file import write_table
    from precompute.flow.builder import BuildConfig, build_table
    from training.maps.train import make_policy
    data = load_map_data([tiny], deep_checks=False)
    policy, table = tmp_path / "p.pt", tmp_path / "blind.npz"
    save_map_policy(policy, map_policy_checkpoint(make_policy(data, 8, 1, 4, 2, 0), data.system_json, {}, {}))
    system, horizon = system_from_json(data.system_json)
    write_table(table, build_table(system, BuildConfig(horizon=horizon))[0])
    return ["--checkpoint", str(policy), "--table", str(table)]


_DEFECTS = {"permuted action rows": (_reverse_actions(1), None, r"entry 1, level 3: its cell_probs are not"),
            "a smaller radius": (None, lambda m: m.update(radius=0.1), r"free successor\(s\) .* left out"),
            "a transposed patch": (_transposed, None, r"(lies within radius|free successor\(s\) .* left out)")}


# ---------------------------------------------------------------------------------------------- JSON nested too deeply

def test_a_dataset_json_nested_too_deeply_is_one_error(tmp_path):
    (tmp_path / "dataset.json").write_text(DEEP)
    with pytest.raises(MapDatasetError, match=r"dataset.json: not readable JSON \(RecursionError"):
        read_map_dataset(tmp_path)


# --------------------------------------------------------------------------------------------- the data set's metadata

@pytest.mark.parametrize("meta, match", [
    (_system(factory="evil:make"), r"names factory 'evil:make', but 'dubins' is a built-in system"),
    (_system(dt=1e38), r"dt does not match its params"),
    (_patch(resolution=1e38), r"patch origin \[-0.5, -0.5\] must be the centred origin .* = \[-1e\+39, -1e\+39\]"),
    (_patch(origin=[-1, -0.5]), r"patch origin \[-1, -0.5\] must be the centred origin"),
    (_patch(origin=[-0.5, 1e38]), r"patch origin \[-0.5, 1e\+38\] must be the centred origin"),
    (_patch(resolution=0.1, origin=[-1.0, -1.0]), None),  # consistent: the reach and inflation checks' to refuse
    (lambda m: m["grid"]["periodic"].__setitem__(0, 0), r"grid .* does not match the system's"),  # 0 for false
    (lambda m: m["shards"][0].update(entries=10**30), r"4 entries, but the shards hold 10000000000000000000000000000"
                                                       r"02"),  # refused before a list of 10^30 pairs is made
])
def test_a_dataset_json_the_farm_did_not_write_is_refused(tiny, tmp_path, meta, match):  # noqa: F811
    m = json.loads((tiny / "dataset.json").read_text())
    assert m["patch"]["origin"] == [-0.5, -0.5] and m["patch"]["shape"] == [20, 20]  # what the patterns assume
    folder = _plant(tiny, tmp_path, meta=meta)
    if match is None:
        read_map_dataset(folder)  # the metadata alone is consistent
        return
    with _memory_capped(1 << 30), pytest.raises(MapDatasetError, match=rf"dataset.json: .*{match}"):
        read_map_dataset(folder)


# ----------------------------------------------------------------------------------------------------------- local map

def test_a_local_maps_resolution_of_another_dtype_is_refused(tmp_path):
    """float32 0.1 is 0.10000000149...: another map, though its digest is fresh."""
    arrays = {"format": np.array("cuniform-local-map/1"), "occupied": np.zeros((4, 4), np.uint8),
              "origin": np.zeros(2), "resolution": np.array(0.1, dtype=np.float32)}
    write_npz(tmp_path / "m.npz", {**arrays, DIGEST_KEY: np.array(content_digest(arrays))})
    with pytest.raises(MapError, match=r"m.npz: 'resolution' must be float64, got float32"):
        read_map_file(tmp_path / "m.npz")
    arrays["resolution"] = np.array(0.1)
    write_npz(tmp_path / "m.npz", {**arrays, DIGEST_KEY: np.array(content_digest(arrays))})
    assert read_map_file(tmp_path / "m.npz").resolution == 0.1


# ------------------------------------------------------------------------------------------------------- special files

@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="POSIX special files")
@pytest.mark.parametrize("target", ["fifo", "/dev/zero"])
def test_a_barn_file_that_is_a_special_file_is_refused(tmp_path, target):
    from precompute.worlds.barn import load_barn
    from precompute.worlds.barn_format import BarnFormatError

    path = tmp_path / "barn.npz"
    if target == "fifo":
        _fifo(path)
    else:
        path.symlink_to(target)
    with pytest.raises(BarnFormatError, match="the BARN file is a (FIFO|character device)"):
        _quick(load_barn, path)


# --------------------------------------------------------------------------------- shards and local maps: strict reads

def test_the_farm_writes_a_digest_and_the_reader_accepts_it(tiny, capsys):
    assert DIGEST_KEY in _arrays(tiny)
    ds = read_map_dataset(tiny, load=True, verify_all=True)
    assert len(ds) == 4 and "no content digest" not in capsys.readouterr().err


@pytest.mark.parametrize("change, words", [
    (_duplicate, r"cells of a level must be distinct and ascending.*repeats"),
    (_swap_rows, r"cells of a level must be distinct and ascending.*comes before"),
    (_origin, r"level 0 of entry 0 must be the origin cell"),
    (_huge_index, r"entry 0, level 3: 1 of its \d+ cells \(e.g. \[2147483647, .*not reached from the origin in 3"),
])
def test_planted_cells_and_rows_are_refused(tiny, tmp_path, change, words):
    _refused(_plant(tiny, tmp_path, change), words)
    _refused(_plant(tiny, tmp_path / "all", change), words.replace("not reached from the origin in 3",
                                                                   "not a cell reached from the level before"),
             verify_all=True)


@pytest.mark.parametrize("entry", [0, 1])
def test_permuted_action_rows_are_refused_with_verify_all(tiny, tmp_path, entry):
    bad = _plant(tiny, tmp_path, _reverse_actions(entry))
    _refused(bad, rf"entry {entry}, level 3: its cell_probs are not the level before's propagated", verify_all=True)
    assert len(read_map_dataset(bad, load=True)) == 4  # the library's default trusts the rows (the commands do not)


def test_a_huge_cell_index_stops_the_training_data(tiny, tmp_path):
    with pytest.raises(MapDatasetError, match="not a cell reached from the level before"):  # deep by default
        load_map_data([_plant(tiny, tmp_path, _huge_index)])


@pytest.mark.parametrize("change, words, kw", [
    (_full, r"the patch of entry 1 is occupied everywhere", {}),
    (_transposed, r"(lies within radius 0.2 m of an obstacle of its patch|free successor\(s\) .* left out)",
     {"verify_all": True}),
    (_twos, r"patches must hold only 0 and 1", {}),
])
def test_planted_patches_are_refused(tiny, tmp_path, change, words, kw):
    a = _arrays(tiny)
    assert not np.array_equal(a["patches"], a["patches"].transpose(0, 2, 1))
    _refused(_plant(tiny, tmp_path, change), words, **kw)


@pytest.mark.parametrize("meta, words, kw", [
    (_system_param("speed", 0.25), r"not reached from the origin in 1 step", {}),
    (_system_param("speed", 0.25), r"not a cell reached from the level before in one step", {"verify_all": True}),
    (lambda m: m.update(radius=0.45), r"lies within radius 0.45 m of an obstacle", {}),
    (lambda m: m["patch"].update(resolution=0.1, origin=[-1.0, -1.0]),  # the origin centred, as the farm writes it
     r"(lies within radius 0.2 m of an obstacle|free successor\(s\) .* left out)", {"verify_all": True}),
    (lambda m: m.update(radius=0.1), r"free successor\(s\) of the level before are left out", {"verify_all": True}),
])
def test_metadata_that_contradicts_the_shards_is_refused(tiny, tmp_path, meta, words, kw):
    _refused(_plant(tiny, tmp_path, meta=meta), words, **kw)


def test_a_damaged_shard_is_refused_by_its_digest(tiny, tmp_path):
    def change(a):
        a["cell_probs"][5] += 1e-4  # within every tolerance: only the digest sees it
    _refused(_plant(tiny, tmp_path, change, digest="keep"), r"shard-00000\.npz is damaged")


def test_an_old_shard_without_digest_loads_with_one_note(tiny, tmp_path, capsys):
    old = _plant(tiny, tmp_path, lambda a: None, digest="drop")
    assert DIGEST_KEY not in _arrays(old)
    assert len(read_map_dataset(old, load=True)) == 4
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no content digest" in err[0] and SHARD in err[0]


def test_a_shard_whose_header_claims_a_huge_array_is_refused_before_allocation(tiny, tmp_path):
    R = 2**26  # cells [R, 3] int32: 768 MiB claimed by a member of a few bytes

    def change(a):
        a["entry_offsets"][-1] = R
    out = _plant(tiny, tmp_path, change)
    arrays = _arrays(out)
    _rezip(out / SHARD, arrays, {"cells": _forged_member("cells", (R, 3), np.int32),
                                 "action_probs": _forged_member("action_probs", (R, 7), np.float16),
                                 "cell_probs": _forged_member("cell_probs", (R,), np.float32)})
    m = json.loads((out / "dataset.json").read_text())
    m["shards"][0]["sha256"] = file_sha256(out / SHARD)
    (out / "dataset.json").write_text(json.dumps(m))

    def read():
        with pytest.raises(MapDatasetError, match=r"shard-00000\.npz: not a readable \.npz shard .*member 'cells'.*"
                                                  r"claims \[67108864, 3\] int32"):
            read_map_dataset(out, load=True)
    assert _peak(read) < 256 * _MB


def test_a_local_map_whose_header_claims_a_huge_array_is_refused_before_allocation(tmp_path):
    path = tmp_path / "m.npz"
    arrays = {"format": np.array("cuniform-local-map/1"), "occupied": None, "origin": np.array([-0.2, -0.2]),
              "resolution": np.array(0.05)}
    _rezip(path, arrays, {"occupied": _forged_member("occupied", (100, 4096, 4096), np.uint8)})

    def read():
        with pytest.raises(MapError, match=r"m\.npz: not a readable \.npz map .*member 'occupied'.*claims"):
            read_map_file(path)
    assert _peak(read) < 256 * _MB
    _rezip(path, arrays, {"occupied": _forged_member("occupied", (40000, 40000), np.uint8)})
    with pytest.raises(MapError, match=r"'occupied' must be between 1 x 1 and 4096 x 4096, got \[40000, 40000\]"):
        read_map_file(path)


def test_a_local_map_carries_its_digest_and_a_damaged_one_is_refused(tmp_path, capsys):
    path, occ = _map(tmp_path)
    assert np.array_equal(read_map_file(path).occupied, occ) and "no content digest" not in capsys.readouterr().err
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    assert DIGEST_KEY in arrays
    arrays["occupied"] = occ.copy()
    arrays["occupied"][2, 5] = 0  # an obstacle erased: still a valid map
    write_npz(path, arrays)
    with pytest.raises(MapError, match=r"m\.npz is damaged: its content does not match the digest"):
        read_map_file(path)


def test_an_old_local_map_without_digest_loads_with_one_note(tmp_path, capsys):
    path, occ = _map(tmp_path)
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files if k != DIGEST_KEY}
    write_npz(path, arrays)
    assert np.array_equal(read_map_file(path).occupied, occ)
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no content digest" in err[0] and "m.npz" in err[0]


# --------------------------------------------------------------------------------- the commands refuse them by default

@pytest.mark.parametrize("defect", list(_DEFECTS))
def test_the_commands_refuse_the_deep_defects_by_default(tiny, tmp_path, capsys, defect):
    import training.maps.coverage as coverage
    import training.maps.distill as distill
    import training.maps.evaluate as evaluate
    change, meta, words = _DEFECTS[defect]
    bad = str(_plant(tiny, tmp_path, change, meta=meta))
    inputs = _commands(tiny, tmp_path)
    runs = {"distill": (distill.main, ["--maps", bad, "--out", str(tmp_path / "x.pt"), "--epochs", "1", "--quiet",
                                       "--logdir", str(tmp_path / "runs")]),
            "evaluate": (evaluate.main, [*inputs, "--maps", bad, "--samples", "4"]),
            "coverage": (coverage.main, [*inputs, "--maps", bad, "--samples", "4", "--quiet"])}
    capsys.readouterr()
    for name, (main, argv) in runs.items():
        assert main(argv) == 2, name
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("error: ") and SHARD in err[0], (name, err)
        assert re.search(words, err[0]), (name, err[0])
    if defect == "permuted action rows":  # trusting the files is explicit: the opt-out reads them
        for name, (main, argv) in runs.items():
            assert main([*argv, "--skip-deep-checks"]) == 0, (name, capsys.readouterr().err)
