"""MapPolicy's opt-in local features (``local_features = C > 0``, :mod:`cuniform_torch.maps.local_features`): C = 0 is the
old network bit for bit, the fast lookup and the training path agree, the sampling reads the patch where the
state is (x = column, y = row, cell centres as grid_sample's align_corners=False), and a policy trained with them
still avoids the wall the blind table hits (the data set and the wall of tests/test_distill_maps.py).
"""

from __future__ import annotations

import math

import pytest
import torch
from test_distill_maps import MAPS, SPEC, SYSTEM, TRAIN, T, wall_collision_rates, write_dataset

import training.maps.distill as distill_maps
from cuniform_torch.envs import OccupancyGrid
from cuniform_torch.maps.checkpoint import load_map_policy, map_policy_checkpoint
from cuniform_torch.maps.local_features import PROBES, LocalFeatures
from cuniform_torch.maps.policy import MapPolicy, MapPolicyConfig
from cuniform_torch.systems import system_to_json
from precompute.flow.builder import BuildConfig, build_table

pytestmark = pytest.mark.usefixtures("restore_threads")  # conftest: main sets torch's thread count

# action_probs of the C = 0 policy below, written by the code before local_features existed
GOLDEN = [[0.1755598485469818, 0.21438923478126526, 0.18082618713378906, 0.2245054841041565, 0.20471924543380737],
          [0.1811177283525467, 0.2083595097064972, 0.18107278645038605, 0.21795296669006348, 0.2114969789981842],
          [0.17314359545707703, 0.22553057968616486, 0.18878665566444397, 0.2168223112821579, 0.19571684300899506]]
OLD_KEYS = {"actions", "inv_scale", "encoder.conv.0.weight", "encoder.conv.0.bias", "encoder.conv.2.weight",
            "encoder.conv.2.bias", "encoder.conv.4.weight", "encoder.conv.4.bias", "encoder.out.weight",
            "encoder.out.bias", "inp_x.weight", "inp_x.bias", "inp_e.weight", "body.1.weight", "body.1.bias",
            "body.3.weight", "body.3.bias"}


def small_policy(local_features: int, seed: int = 0) -> MapPolicy:
    torch.manual_seed(seed)
    cfg = MapPolicyConfig(3, 5, T, [False, False, True], [1.0, 1.0, 1.0], SPEC.to_dict(), hidden=32, layers=2,
                          embed=8, channels=4, local_features=local_features)
    return MapPolicy(cfg, SYSTEM, SYSTEM.action_set())


def grid_of(occ: torch.Tensor) -> OccupancyGrid:
    return OccupancyGrid(occ, SPEC.origin, SPEC.resolution)


def box_map(i0: int, i1: int, j0: int, j1: int) -> torch.Tensor:
    occ = torch.zeros(SPEC.shape, dtype=torch.bool)
    occ[i0:i1, j0:j1] = True
    return occ


def centre(i: int, j: int) -> tuple[float, float]:
    """Robot-frame (x, y) of patch cell (i, j)'s centre (row i = y, column j = x)."""
    return SPEC.origin[0] + (j + 0.5) * SPEC.resolution, SPEC.origin[1] + (i + 0.5) * SPEC.resolution


def test_without_local_features_the_policy_is_the_old_one():
    """Same initial weights, keys and outputs as before the option; a checkpoint without the key loads as C = 0."""
    policy = small_policy(0)
    assert set(policy.state_dict()) == OLD_KEYS and policy.local is None
    assert "local_features" not in policy.config.to_dict()  # a C = 0 checkpoint is written as before
    policy.set_map(grid_of(box_map(10, 14, 16, 18)))
    x = torch.tensor([[0.0, 0.0, 0.0], [0.3, -0.2, 1.0], [-0.5, 0.4, -2.0]])
    probs = policy.action_probs(x, 1)
    assert torch.allclose(probs, torch.tensor(GOLDEN), atol=1e-6, rtol=0), probs.tolist()
    ckpt = map_policy_checkpoint(policy, system_to_json(SYSTEM, T))
    assert "local_features" not in ckpt["config"]
    loaded = load_map_policy(ckpt)
    assert loaded.config.local_features == 0 and loaded.local is None
    loaded.set_map(grid_of(box_map(10, 14, 16, 18)))
    assert torch.equal(loaded.action_probs(x, 1), probs)
    with_key = load_map_policy({**ckpt, "config": {**ckpt["config"], "local_features": 0}})
    with_key.set_map(grid_of(box_map(10, 14, 16, 18)))
    assert torch.equal(with_key.action_probs(x, 1), probs)


def test_the_fast_lookup_is_the_training_path():
    """action_probs after set_map == softmax(logits) with per-row maps (two maps interleaved in one batch)."""
    policy = small_policy(4)
    with torch.no_grad():  # untrained, the local features barely move the logits: make them count
        for weight in (*policy.local.parameters(), policy.inp_l.weight):
            weight.normal_(0.0, 0.5, generator=torch.Generator().manual_seed(2))
    maps = torch.stack((box_map(10, 14, 16, 18), box_map(3, 8, 5, 9)))
    x = (torch.rand(64, 3, generator=torch.Generator().manual_seed(1)) - 0.5) * torch.tensor([2.0, 2.0, 6.0])
    which = torch.arange(64) % 2
    for t in (0, 3):
        fast = []
        for k in range(2):
            policy.set_map(grid_of(maps[k]))
            fast.append(policy.action_probs(x, t))
        with torch.no_grad():
            slow = torch.softmax(policy.logits(x, t, policy.encode(maps)[which], policy.encode_local(maps), which), 1)
            one = torch.softmax(policy.logits(x, t, policy.encode(maps[:1]), policy.encode_local(maps[:1])), 1)
        assert torch.allclose(slow, torch.where(which[:, None] == 0, fast[0], fast[1]), atol=1e-6, rtol=0)
        assert torch.allclose(one, fast[0], atol=1e-6, rtol=0)
        assert float((fast[0] - fast[1]).abs().max()) > 0.05  # the maps matter at these states
    with pytest.raises(ValueError, match="needs local_map"):
        policy.logits(x, 0, policy.encode(maps[:1]))


def test_the_sampling_reads_the_cell_under_each_probe():
    """A one-cell feature map (cell (5, 17): row != column) read at the probes of states placed around it."""
    local = LocalFeatures(SPEC, 1)
    fmap = box_map(5, 6, 17, 18).float()[None, None]  # [1, 1, H, W]
    cx, cy = centre(5, 17)
    d = 0.5  # probe 2 is 0.5 m straight ahead, probe 4 0.5 m ahead 0.3 m to the left
    assert PROBES[2] == (0.5, 0.0) and PROBES[4] == (0.5, 0.3)
    x = torch.tensor([[cx, cy, 0.0],  # on the cell: probe 0 reads it
                      [cx - d, cy, 0.0],  # behind it facing +x: probe 2
                      [cx, cy - d, math.pi / 2],  # below it facing +y: probe 2
                      [cx - d, cy - 0.3, 0.0],  # behind and right of it: probe 4 (left)
                      [cx + 0.3, cy - d, math.pi / 2],  # below and right of it facing +y: probe 4 (left = -x)
                      [*centre(17, 5), 0.0],  # on the transposed cell (free)
                      [cx + 3.0, cy, math.pi]])  # off the patch, facing it: every probe is off
    got = local.sample(fmap, x)  # [7, P]
    want = torch.zeros(7, len(PROBES))
    want[0, 0] = want[1, 2] = want[2, 2] = want[3, 4] = want[4, 4] = 1.0
    assert torch.allclose(got, want, atol=1e-5), got
    # half a cell off the centre: half of the cell (bilinear between centres)
    assert float(local.sample(fmap, torch.tensor([[cx + 0.05, cy, 0.0]]))[0, 0]) == pytest.approx(0.5, abs=1e-5)


def test_the_learned_features_see_the_obstacle_and_free_space_reads_zero():
    """The policy's own feature map: nonzero on an occupied cell, exactly 0 on a free cell far from it."""
    policy = small_policy(4)
    occ = box_map(5, 7, 16, 18)
    policy.set_map(grid_of(occ))
    fmap = policy._local_map
    x = torch.tensor([[*centre(5, 17), 0.0], [*centre(17, 5), 0.0]])  # on the obstacle; on its transposed cell
    feats = policy.local.sample(fmap, x).reshape(2, len(PROBES), 4)
    assert float(feats[0, 0].abs().max()) > 1e-3
    assert float(feats[1].abs().max()) == 0.0


@pytest.fixture(scope="module")
def trained_local(tmp_path_factory):
    table = build_table(SYSTEM, BuildConfig(horizon=T))[0]
    dataset = write_dataset(tmp_path_factory.mktemp("maps") / "walls", table, MAPS)
    out = tmp_path_factory.mktemp("policy") / "walls.local.map_policy.pt"
    assert distill_maps.main(["--maps", str(dataset), "--out", str(out), "--logdir", str(out.parent / "runs"),
                              *TRAIN, "--local-features", "4"]) == 0
    return out, table, dataset


def test_a_policy_with_local_features_avoids_the_wall(trained_local):
    """The key test of tests/test_distill_maps.py with --local-features 4; the checkpoint records C."""
    path, table, _ = trained_local
    policy = load_map_policy(path)
    assert policy.config.local_features == 4 and torch.load(path, weights_only=True)["config"]["local_features"] == 4
    rate_map, rate_blind = wall_collision_rates(policy, table)
    print(f"collision rate: map policy with local features {rate_map:.3f}, blind table {rate_blind:.3f}")
    assert rate_blind > 0.3
    assert rate_map < 0.5 * rate_blind
    assert policy.miss_rate == 0.0


def test_bad_local_features_are_refused(tmp_path, capsys):
    with pytest.raises(ValueError, match="local_features must be an integer"):
        small_policy(-1)
    cfg = small_policy(0).config.to_dict()
    with pytest.raises(ValueError, match="need states"):
        MapPolicyConfig(**{**cfg, "periodic": [True, False, False], "local_features": 2})
    assert distill_maps.main(["--maps", str(tmp_path), "--local-features", "-1", "--quiet"]) == 2
    assert "--local-features" in capsys.readouterr().err


def test_a_resume_across_local_features_is_refused(trained_local, tmp_path, capsys):
    """The resume fingerprint holds local_features when > 0, and a C = 0 run does not resume a C > 0 state."""
    dataset = trained_local[2]  # hand-pruned tables: read with --skip-deep-checks (test_distill_maps: SKIP)
    args = ["--maps", str(dataset), "--out", str(tmp_path / "p.pt"), "--logdir", str(tmp_path / "runs"), "--quiet",
            "--skip-deep-checks", "--epochs", "1", "--hidden", "8", "--embed", "4", "--channels", "2", "--val-fraction", "0"]
    assert distill_maps.main([*args, "--local-features", "2"]) == 0
    assert distill_maps.main([*args, "--resume"]) == 2
    assert "local_features: saved 2, now 0" in capsys.readouterr().err
    assert distill_maps.main([*args, "--local-features", "3", "--resume"]) == 2
    assert "local_features: saved 2, now 3" in capsys.readouterr().err
    assert distill_maps.main([*args, "--local-features", "2", "--resume"]) == 0
