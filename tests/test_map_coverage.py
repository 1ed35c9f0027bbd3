"""python -m training.maps.coverage: the free-space coverage of rollouts over an entry's safe cells (exact on a
hand-made case, more for a spread table than for one action), the command on a tiny data set, bad input.

The tiny data set and its system are test_distill_maps.py's (a Dubins car of 4 steps, 24 x 24 patches); the map
policy here is untrained (random weights): the command's numbers, not the policy's quality, are under test.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from test_distill_maps import MAPS, SPEC, SYSTEM, T, write_dataset

import training.maps.coverage as map_coverage
from cuniform_torch.grid.cells import Grid
from cuniform_torch.maps.checkpoint import map_policy_checkpoint, save_map_policy
from cuniform_torch.maps.policy import MapPolicy, MapPolicyConfig
from cuniform_torch.policies.table import TablePolicy
from cuniform_torch.sampling.rollout import rollout
from cuniform_torch.systems import make_system, system_to_json
from cuniform_torch.tables.file import write_table
from precompute.flow.builder import BuildConfig, build_table

GRID = Grid.of(SYSTEM)
OTHER = make_system("dubins", speed=0.9, dt=0.2, num_actions=5, max_omega=math.pi / 2,
                    cell_size=[0.1, 0.1, 2 * math.pi / 16])  # same actions and grid, another speed


@pytest.fixture(scope="module")
def blind():
    return build_table(SYSTEM, BuildConfig(horizon=T))[0]


@pytest.fixture(scope="module")
def files(blind, tmp_path_factory) -> dict[str, Path]:
    """The tiny data set (two maps), the blind table and an untrained map policy of SYSTEM; and a checkpoint
    and a table of OTHER."""
    root = tmp_path_factory.mktemp("coverage")
    out = {"maps": write_dataset(root / "walls", blind, MAPS[:2]), "table": root / "blind.npz",
           "checkpoint": root / "policy.pt", "other_checkpoint": root / "other.pt", "other_table": root / "other.npz"}
    write_table(out["table"], blind)
    write_table(out["other_table"], build_table(OTHER, BuildConfig(horizon=T))[0])
    for system, path in ((SYSTEM, out["checkpoint"]), (OTHER, out["other_checkpoint"])):
        torch.manual_seed(0)
        config = MapPolicyConfig(3, 5, T, [False, False, True], [1.0, 1.0, 1.0], SPEC.to_dict(), hidden=16,
                                 layers=1, embed=4, channels=2)
        policy = MapPolicy(config, system, system.action_set())
        save_map_policy(path, map_policy_checkpoint(policy, system_to_json(system, T)))
    return out


def test_coverage_is_the_share_of_safe_cells_hit_per_level():
    """Hand-made: level 1 has 4 safe cells, level 2 has 5; three rollouts hit 2 of level 1's (one cell twice,
    off its centre) and 1 of level 2's; a level-1 cell reached at step 2 does not count there."""
    level1 = [[2, 0, 0], [2, 1, 1], [2, -1, 15], [1, 1, 2]]  # angle cell 15: a heading just below 0 (wrapped)
    level2 = [[4, 0, 0], [4, 1, 1], [4, -1, 15], [3, 2, 2], [3, -2, 14]]
    cells = np.array([[0, 0, 0], *level1, *level2], dtype=np.int32)
    offsets = np.array([0, 1, 5, 10])
    c = lambda *cell: GRID.centers(torch.tensor(cell))  # noqa: E731  (a cell's centre, float64 [3])
    quarter = torch.tensor([0.03, -0.02, 0.1])  # well inside the cell (half a cell: 0.05, 0.05, 0.196)
    states = torch.stack([
        torch.stack([c(0, 0, 0), c(2, -1, 15) + quarter, c(4, 0, 0)]),  # level 1 hit, level 2 hit
        torch.stack([c(0, 0, 0), c(2, -1, 15), c(2, 0, 0)]),  # the same level-1 cell; at step 2 a level-1 cell
        torch.stack([c(0, 0, 0), c(1, 1, 2), c(9, 9, 9)]),  # another level-1 cell; nowhere at step 2
    ])  # [3, 3, 3]
    cov, free = map_coverage.free_coverage(states, cells, offsets, GRID)
    assert cov.tolist() == [2 / 4, 1 / 5]
    assert free.tolist() == [1.0, 1 / 3]
    cov, free = map_coverage.free_coverage(states.float(), cells, offsets, GRID)  # a rollout's float32 states
    assert cov.tolist() == [2 / 4, 1 / 5] and free.tolist() == [1.0, 1 / 3]
    empty = np.array([0, 1, 5, 5])  # no safe cell at level 2: NaN coverage, nothing in free
    cov, free = map_coverage.free_coverage(states, cells[:5], empty, GRID)
    assert cov[0] == 0.5 and math.isnan(cov[1]) and free.tolist() == [1.0, 0.0]
    with pytest.raises(ValueError, match="level_offsets"):
        map_coverage.free_coverage(states, cells, np.array([0, 1, 10]), GRID)


def test_a_spread_table_covers_more_than_one_action(blind):
    """Over the blind table's own cells, its rollouts cover far more than a table that always goes straight,
    which covers exactly one cell per level."""
    straight = np.zeros_like(blind.action_probs)
    straight[:, 2] = 1.0  # action 2 of 5: omega = 0
    one = dataclasses.replace(blind, action_probs=straight)
    x0 = torch.zeros(3)
    shares = {}
    for name, table in (("spread", blind), ("straight", one)):
        states, _ = rollout(SYSTEM, TablePolicy(table), x0, 500, T, torch.Generator().manual_seed(0))
        shares[name] = map_coverage.free_coverage(states, blind.cells, blind.level_offsets, GRID)
    sizes = np.diff(blind.level_offsets)[1:]
    assert np.allclose(shares["straight"][0], 1.0 / sizes) and shares["straight"][1].tolist() == [1.0] * T
    assert shares["spread"][0].mean() > 0.6 and shares["spread"][0].mean() > 3 * shares["straight"][0].mean()
    assert shares["spread"][1].min() < 1.0  # real max-flow rollouts drift out of the level sets (README)


def test_in_free_is_the_tables_own_lookup(blind):
    """A state is in a safe cell exactly when the table policy's own lookup finds it in the level (the same
    cell indexing): over the blind table's cells, "in free" is the share that ``TablePolicy.rows`` finds."""
    policy = TablePolicy(blind)
    states, _ = rollout(SYSTEM, policy, torch.zeros(3), 2000, T, torch.Generator().manual_seed(1))
    _, free = map_coverage.free_coverage(states, blind.cells, blind.level_offsets, GRID)
    found = [float((policy.rows(states[:, t].contiguous(), t) >= 0).double().mean()) for t in range(1, T + 1)]
    assert free.tolist() == found and min(found) < 1.0


def test_the_command_on_a_tiny_data_set(files, tmp_path, capsys):
    out = tmp_path / "coverage.json"
    assert map_coverage.main(["--checkpoint", str(files["checkpoint"]), "--maps", str(files["maps"]), "--table",
                              str(files["table"]), "--samples", "16", "256", "--json", str(out), "--quiet",
                              "--skip-deep-checks"]) == 0  # hand-pruned tables (test_distill_maps: SKIP)
    text = capsys.readouterr().out
    print(text)
    lines = text.splitlines()
    assert sum(line.startswith("entry ") for line in lines) == 2 * 2  # entries x N
    assert "free-space coverage over 2 entries" in text and "map policy / blind table: N 16" in text
    result = json.loads(out.read_text())
    assert result["samples"] == [16, 256] and result["entries"] == ["test:0", "test:1"]
    for method in ("map_policy", "blind_table"):
        for n in ("16", "256"):
            cov = result["shares"][method][n]["coverage"]
            assert len(cov) == 2 and all(0 < v <= 1 for v in cov)
            assert result["summary"][method][n]["coverage"]["mean"] == pytest.approx(np.mean(cov))
    blind256 = result["shares"]["blind_table"]["256"]
    assert max(blind256["in_free"]) < 0.95  # the blind table drives into the walls, out of the safe cells
    assert np.mean(blind256["coverage"]) > np.mean(result["shares"]["blind_table"]["16"]["coverage"])
    ratio = result["ratio"]["256"]["coverage"]
    assert ratio == pytest.approx(result["summary"]["map_policy"]["256"]["coverage"]["mean"]
                                  / result["summary"]["blind_table"]["256"]["coverage"]["mean"])


@pytest.mark.parametrize("change, message", [
    ({"--checkpoint": "other_checkpoint"}, "is a map policy of another system than the data set"),
    ({"--table": "other_table"}, "is a table of another system than the data set"),
    ({"--samples": "0"}, "--samples: must be an integer in [1, "),
    ({"--samples": "-5"}, "--samples: must be an integer in [1, "),
    ({"--entries": "-1"}, "--entries: must be an integer in [0, "),
])
def test_bad_input_is_one_clear_error(files, change, message, capsys):
    args = {"--checkpoint": str(files["checkpoint"]), "--maps": str(files["maps"]), "--table": str(files["table"]),
            "--samples": "8"}
    for flag, value in change.items():
        args[flag] = str(files[value]) if value in files else value
    argv = [w for flag, value in args.items() for w in (flag, value)] + ["--quiet", "--skip-deep-checks"]
    try:
        code = map_coverage.main(argv)
    except SystemExit as exc:  # a bad flag value: argparse's exit, as it parses
        code = exc.code
    assert code == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and message in err and len(err.splitlines()) == 1, err
