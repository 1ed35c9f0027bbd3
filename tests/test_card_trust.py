"""The shipped map policy is what its card says (issue 38): the Python API refuses a card edited to another speed or
radius (the weights unchanged), weights of another robot under a card whose digest was updated, and a weights file
larger than its card says, from its size before it is read; a checkpoint far over any network's size is refused
from its size before ``torch.load``."""

from __future__ import annotations

import hashlib
import json
import shutil
import time

import pytest

import cuniform_torch.maps.pretrained as pretrained
from cuniform_torch.maps import MapPolicy, load_map_policy
from cuniform_torch.maps.checkpoint import MapCheckpointError
from cuniform_torch.maps.pretrained import PretrainedError
from cuniform_torch.policies.checkpoint import PolicyCheckpointError, load_policy

SHIPPED = "unicycle-0.5"


@pytest.fixture
def shelf(tmp_path, monkeypatch):
    """A copy of the shipped weights folder (its card and file), which the loaders then read."""
    folder = tmp_path / "weights"
    folder.mkdir()
    for path in pretrained.PRETRAINED_DIR.glob(f"{SHIPPED}*"):
        shutil.copy(path, folder / path.name)
    monkeypatch.setattr(pretrained, "PRETRAINED_DIR", folder)
    return folder


def _edit_card(folder, **robot) -> None:
    path = folder / f"{SHIPPED}.json"
    card = json.loads(path.read_text())
    for key, value in robot.items():
        if key in card["robot"]:
            card["robot"][key] = value
        else:
            card["robot"]["params"][key] = value
    path.write_text(json.dumps(card, indent=2))


def test_the_shipped_card_and_file_agree_and_load(shelf):
    assert isinstance(load_map_policy(SHIPPED), MapPolicy)


@pytest.mark.parametrize("edit, said", [({"speed": 0.6}, "speed: card 0.6, file 0.5"),
                                        ({"radius": 0.5}, "radius: card 0.5, file 0.2"),
                                        ({"horizon": 12}, "horizon: card 12, file 15"),
                                        ({"max_omega": 2.0}, "max_omega: card 2.0, file 1.5")])
def test_a_card_edited_to_another_robot_is_refused(shelf, edit, said):
    _edit_card(shelf, **edit)
    with pytest.raises(PretrainedError, match=f"does not describe the robot .*{said}"):
        load_map_policy(SHIPPED)


def test_weights_of_another_robot_under_an_updated_digest_are_refused(shelf):
    import torch

    from cuniform_torch.maps.checkpoint import save_map_policy

    weights = shelf / f"{SHIPPED}.map_policy.pt"
    ckpt = torch.load(weights, weights_only=True)
    system = json.loads(ckpt["system"])
    system["params"]["speed"] = 0.7  # another robot's file (still self-consistent: its digest is rewritten)
    ckpt["system"] = json.dumps(system, sort_keys=True)
    ckpt.pop("content_sha256")
    save_map_policy(weights, ckpt)
    card_path = shelf / f"{SHIPPED}.json"
    card = json.loads(card_path.read_text())
    raw = weights.read_bytes()
    card.update(file_sha256=hashlib.sha256(raw).hexdigest(), bytes=len(raw))
    card_path.write_text(json.dumps(card))
    with pytest.raises(PretrainedError, match="speed: card 0.5, file 0.7"):
        load_map_policy(SHIPPED)


def test_a_weights_file_larger_than_its_card_is_refused_before_it_is_read(shelf):
    weights = shelf / f"{SHIPPED}.map_policy.pt"
    with open(weights, "r+b") as fh:  # sparse: 2 GB claimed, nothing stored
        fh.truncate(2 << 30)
    begin = time.perf_counter()
    with pytest.raises(PretrainedError, match=r"2147483648 bytes, the card says \d+"):
        load_map_policy(SHIPPED)
    assert time.perf_counter() - begin < 5.0  # from its size: not hashed, not loaded


@pytest.mark.parametrize("load, error", [(load_map_policy, MapCheckpointError), (load_policy, PolicyCheckpointError)])
def test_a_checkpoint_over_any_networks_size_is_refused_from_its_size(tmp_path, load, error):
    path = tmp_path / "huge.pt"
    with open(path, "wb") as fh:
        fh.truncate(2 << 30)
    begin = time.perf_counter()
    with pytest.raises(error, match="2147483648 bytes, over the"):
        load(path)
    assert time.perf_counter() - begin < 5.0
