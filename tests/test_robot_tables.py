"""No hidden builds (issue 37): the navigation robot's tables ship as package data with their manifest (sizes,
sha256, content digests), the benchmark uses them without building, and the shipping command writes exactly what
the builder gives."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace

import numpy as np
import pytest

from cuniform_torch.systems import system_to_json
from cuniform_torch.tables.file import NOGRAPH_DIGEST_KEY, read_table, table_digests
from eval.navigate import robot_files
from eval.navigate.robot_files import (
    CHECK_TOLERANCE,
    MANIFEST,
    METHODS,
    SHIPPED_DIR,
    ShippedTableError,
    build_policy_table,
    compare_tables,
    ensure_table,
    ship_tables,
    shipped_table,
)
from precompute.worlds.robot import NAV_ROBOT, preset_dict

SMALL = replace(NAV_ROBOT, horizon=5)  # both 5-step tables build in about a second


@pytest.fixture(scope="module")
def small_shipped(tmp_path_factory):
    """The 5-step robot's tables shipped into a temporary folder, with the manifest."""
    folder = tmp_path_factory.mktemp("shipped")
    return folder, ship_tables(SMALL, folder)


@pytest.mark.parametrize("method", METHODS)
def test_the_shipped_tables_match_their_manifest_and_the_robot(method):
    manifest = json.loads((SHIPPED_DIR / MANIFEST).read_text())
    entry = next(e for e in manifest["tables"] if e["method"] == method)
    path = shipped_table(NAV_ROBOT, method)  # size and sha256 checked against the manifest
    assert path == SHIPPED_DIR / entry["file"]
    table = read_table(path, graph=False)  # the reader checks the content digest
    assert str(table_digests(table.to_arrays())[NOGRAPH_DIGEST_KEY]) == entry["content_sha256_nograph"]
    assert entry["robot"] == preset_dict(NAV_ROBOT) and entry["fingerprint"] == NAV_ROBOT.fingerprint(method)
    assert table.method == method and table.horizon == NAV_ROBOT.horizon
    assert table.system == system_to_json(robot_files._system(NAV_ROBOT), NAV_ROBOT.horizon)
    assert int(table.level_offsets[-1]) == entry["cells"]


def test_the_benchmark_uses_the_shipped_tables_without_building(tmp_path, capsys, monkeypatch):
    import precompute.build  # noqa: F401  (imported first: it binds the real build_table_file, not the patch below)
    import precompute.one_table as one_table

    def refuse(job):
        raise AssertionError(f"built {job.out}")

    monkeypatch.setattr(one_table, "build_table_file", refuse)
    for method in METHODS:
        assert ensure_table(NAV_ROBOT, tmp_path, method) == shipped_table(NAV_ROBOT, method)
    assert capsys.readouterr().out == "" and list(tmp_path.iterdir()) == []  # nothing said, nothing cached


def test_a_shipped_table_is_what_the_builder_gives(small_shipped, tmp_path):
    folder, manifest = small_shipped
    assert [e["method"] for e in manifest["tables"]] == list(METHODS)
    assert json.loads((folder / MANIFEST).read_text()) == manifest
    for entry in manifest["tables"]:
        method = entry["method"]
        path = shipped_table(SMALL, method, folder)
        assert path == folder / entry["file"]
        shipped = read_table(path, graph=False)
        assert shipped.transitions is None and shipped.arcs is None  # the flow graph is not shipped
        built, _, _ = build_policy_table(SMALL, method)
        for key, value in built.to_arrays().items():  # every key a policy reads, bit for bit
            assert np.array_equal(shipped.to_arrays()[key], value), (method, key)
        diff = compare_tables(built, shipped)
        assert diff == {"same_cells": True, "action_probs": 0.0, "cell_probs": 0.0}
        # the whole table the benchmark would cache has the same content digest over those keys
        full = np.load(ensure_table(SMALL, tmp_path, method, quiet=True))
        assert str(full[NOGRAPH_DIGEST_KEY]) == entry["content_sha256_nograph"]
        assert "transitions" in full.files  # ... and holds the graph the shipped file leaves out


def test_a_damaged_shipped_table_or_manifest_is_one_clear_error(small_shipped, tmp_path):
    folder = tmp_path / "copy"
    shutil.copytree(small_shipped[0], folder)
    entry = small_shipped[1]["tables"][1]
    path = folder / entry["file"]
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 1
    path.write_bytes(bytes(data))
    with pytest.raises(ShippedTableError, match="does not match its manifest.*rebuild the tables"):
        shipped_table(SMALL, entry["method"], folder)
    assert shipped_table(SMALL, "maxflow", folder) is not None  # the other table is untouched
    path.unlink()
    with pytest.raises(ShippedTableError, match="is missing"):
        shipped_table(SMALL, entry["method"], folder)
    (folder / MANIFEST).write_text('{"format": "cuniform-shipped-tables/1", "tables": [{"file": "../x.npz"}]}')
    with pytest.raises(ShippedTableError, match="not a 'cuniform-shipped-tables/1' manifest"):
        shipped_table(SMALL, "maxflow", folder)
    assert shipped_table(SMALL, "maxflow", tmp_path) is None  # no manifest: nothing shipped
    assert shipped_table(replace(SMALL, horizon=4), "maxflow", small_shipped[0]) is None  # another robot


def test_the_command_refuses_a_flag_of_another_mode(tmp_path, capsys):
    assert robot_files.main(["--check", "--out", str(tmp_path)]) == 2
    assert "--out applies to --ship" in capsys.readouterr().err
    assert robot_files.main(["--ship", "--horizons", "6"]) == 2
    assert "--horizons applies to --time" in capsys.readouterr().err


@pytest.mark.slow
@pytest.mark.parametrize("method", METHODS)
def test_the_shipped_15_step_tables_equal_a_rebuild(method):
    diff = compare_tables(build_policy_table(NAV_ROBOT, method)[0], read_table(shipped_table(NAV_ROBOT, method),
                                                                               graph=False))
    assert diff["same_cells"] and diff["action_probs"] <= CHECK_TOLERANCE, diff


# ------------------------------------------------------------------ the coverage build's compiled passes

def _torch_transitions(levels, probs, A):
    """The torch assembly of the recorded transitions the compiled one replaced (the slow reference)."""
    import torch

    out, state_mass = [], torch.ones(1, dtype=torch.float64)
    for t in range(len(levels.successor)):
        sc, succ = levels.state_cell[t], levels.successor[t]
        n, m = len(levels.cells[t]), len(levels.cells[t + 1])
        ok = (succ >= 0).reshape(-1)
        src = sc.unsqueeze(1).expand_as(succ).reshape(-1)[ok]
        act = torch.arange(A).repeat(len(sc))[ok]
        dst = levels.state_cell[t + 1][succ.reshape(-1)[ok]]
        weight = state_mass.unsqueeze(1).expand_as(succ).reshape(-1)[ok]
        uniq, inv = torch.unique((src * A + act) * m + dst, return_inverse=True)
        w = torch.zeros(len(uniq), dtype=torch.float64).index_add(0, inv, weight)
        cnt = torch.zeros(len(uniq), dtype=torch.float64).index_add(0, inv, torch.ones_like(weight))
        sa = uniq // m
        tot_w = torch.zeros(n * A, dtype=torch.float64).index_add(0, sa, w)
        tot_c = torch.zeros(n * A, dtype=torch.float64).index_add(0, sa, cnt)
        frac = torch.where(tot_w[sa] > 0, w / tot_w[sa].clamp(min=1e-300), cnt / tot_c[sa])
        out.append((torch.stack((sa // A, sa % A, uniq % m), 1).numpy(), frac.numpy()))
        state_mass = torch.zeros(levels.num_states[t + 1], dtype=torch.float64).index_add(
            0, succ.reshape(-1)[ok], (state_mass.unsqueeze(1) * probs[t][sc]).reshape(-1)[ok])
    return out


@pytest.mark.parametrize("pruned", [False, True])
def test_the_compiled_transitions_are_the_torch_assembly_to_the_bit(pruned):
    import torch

    from cuniform_torch.systems import make_system
    from precompute.coverage.loops import level_transitions
    from precompute.coverage.method import enumerate_reachable

    levels = enumerate_reachable(make_system("dubins"), 6, state_budget=2000)
    gen = torch.Generator().manual_seed(0)
    if pruned:  # every fifth pair lost to a map, and one level's states all without mass on action 0
        levels.successor = [torch.where(torch.rand(s.shape, generator=gen) < 0.2, -1, s) for s in levels.successor]
    A = levels.successor[0].shape[1]
    probs = [torch.softmax(3 * torch.randn(len(c), A, generator=gen, dtype=torch.float64), 1)
             for c in levels.cells[:-1]]
    if pruned:
        probs[2][:, 0] = 0.0
    state_mass = torch.ones(1, dtype=torch.float64)
    for t, (rows, frac) in enumerate(_torch_transitions(levels, probs, A)):
        sc, succ = levels.state_cell[t], levels.successor[t]
        src, act, dst, got = level_transitions(sc.numpy(), succ.reshape(-1).numpy(),
                                               levels.state_cell[t + 1].numpy(), state_mass.numpy(),
                                               len(levels.cells[t]), A)
        assert np.array_equal(np.stack((src, act, dst), 1), rows) and np.array_equal(got, frac), t
        ok = (succ >= 0).reshape(-1)
        state_mass = torch.zeros(levels.num_states[t + 1], dtype=torch.float64).index_add(
            0, succ.reshape(-1)[ok], (state_mass.unsqueeze(1) * probs[t][sc]).reshape(-1)[ok])


@pytest.mark.parametrize("pruned", [False, True])
def test_the_compiled_ascent_passes_are_the_autograd_gradient(pruned):
    """StatePropagator (compiled loops) against autograd through the torch propagation, with pruned successors."""
    import torch

    from cuniform_torch.systems import make_system
    from precompute.coverage.adjoint import StatePropagator
    from precompute.coverage.method import CoverageConfig, _propagate, coverage_objective, enumerate_reachable

    levels = enumerate_reachable(make_system("dubins"), 5)
    gen = torch.Generator().manual_seed(1)
    if pruned:
        levels.successor = [torch.where(torch.rand(s.shape, generator=gen) < 0.2, -1, s) for s in levels.successor]
    config = CoverageConfig(horizon=5, target_samples=100)
    logits = [torch.randn((len(c), 5), generator=gen, dtype=torch.float64, requires_grad=True)
              for c in levels.cells[:-1]]
    coverage_objective(_propagate(levels, logits)[1:], config).backward()
    probs = [torch.softmax(l.detach(), dim=1) for l in logits]
    propagator = StatePropagator(levels, 5, torch.float64)
    cells = propagator.forward(probs)
    for got, want in zip(cells, _propagate(levels, [l.detach() for l in logits])):
        torch.testing.assert_close(got, want)
    leaves = [c.requires_grad_() for c in cells[1:]]
    cell_grads = [torch.zeros_like(cells[0])] + list(torch.autograd.grad(coverage_objective(leaves, config), leaves))
    for t, (g, p, l) in enumerate(zip(propagator.backward(probs, cell_grads), probs, logits)):
        torch.testing.assert_close(p * (g - (g * p).sum(1, keepdim=True)), l.grad, msg=f"level {t}")
    with pytest.raises(ValueError, match="expected torch.float64 tensors, got torch.float32"):
        propagator.forward([p.float() for p in probs])
