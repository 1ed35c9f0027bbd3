"""Pretrained map policies shipped as package data, loaded by name: ``load_map_policy("unicycle-0.5")``.

Each lives in ``cuniform_torch/maps/weights/`` as ``NAME.map_policy.pt`` and its model card ``NAME.json``
(format :data:`CARD_FORMAT`: the robot it was trained for, its data and training, and the file's sha256). A name
resolves to its file only when the card is readable, the file's size and sha256 are the card's (the size checked
first, so a huge file is refused before it is read), and the robot the card describes is the one the file itself
records (its system JSON: system, parameters, horizon; its ``robot_radius`` metric): a damaged or swapped file, or
a card edited to another speed or radius, is one clear error, never a different policy. ``python -m training.maps.pretrained --install`` rebuilds them.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from pathlib import Path
from typing import Any

from cuniform_torch.common.fileio import open_regular, read_capped_text

__all__ = ["CARD_FORMAT", "PRETRAINED_DIR", "PretrainedError", "pretrained_names", "pretrained_card",
           "pretrained_path", "robot_mismatch", "card_mismatch"]

CARD_FORMAT = "cuniform-model-card/1"
PRETRAINED_DIR = Path(__file__).parent / "weights"
"""``cuniform_torch/maps/weights/``: the shipped files"""

_NAME = re.compile(r"^[a-z0-9][a-z0-9.\-]{0,63}$")
_MAX_CARD_BYTES = 1 << 20


class PretrainedError(ValueError):
    """An unknown name, or a shipped file that does not match its card."""


def pretrained_names() -> list[str]:
    """The names of the shipped policies (those with a card)."""
    return sorted(p.stem for p in PRETRAINED_DIR.glob("*.json") if _NAME.match(p.stem))


def pretrained_card(name: str) -> dict[str, Any]:
    """The model card of the shipped policy ``name``; :class:`PretrainedError` for an unknown name or a bad card."""
    if not isinstance(name, str) or not _NAME.match(name) or not (PRETRAINED_DIR / f"{name}.json").is_file():
        known = ", ".join(pretrained_names()) or "none are installed"
        raise PretrainedError(f"no pretrained map policy named {name!r} (known: {known})")
    path = PRETRAINED_DIR / f"{name}.json"
    try:
        card = json.loads(read_capped_text(path, _MAX_CARD_BYTES, "a model card"))
    except (OSError, ValueError, RecursionError) as exc:
        raise PretrainedError(f"{path}: not a readable model card ({exc})") from None
    if not isinstance(card, dict) or card.get("format") != CARD_FORMAT or card.get("name") != name \
            or not isinstance(card.get("file"), str) or not isinstance(card.get("file_sha256"), str) \
            or not isinstance(card.get("robot"), dict):
        raise PretrainedError(f"{path}: not a {CARD_FORMAT!r} card of {name!r} (format, name, file, file_sha256, "
                              "robot)")
    return card


def pretrained_path(name: str) -> Path:
    """The shipped file of ``name``, after checking its sha256 against the card (:class:`PretrainedError`)."""
    card = pretrained_card(name)
    path = PRETRAINED_DIR / Path(card["file"]).name
    if not path.exists():
        raise PretrainedError(f"the pretrained map policy {name!r}: its file {path} is missing (reinstall the "
                              "package, or rebuild it: python -m training.maps.pretrained --install)")
    try:
        fh = open_regular(path, "a shipped policy file")
    except (OSError, ValueError) as exc:
        raise PretrainedError(f"the pretrained map policy {name!r}: {exc}") from None
    with fh:
        size = os.fstat(fh.fileno()).st_size
        if isinstance(card.get("bytes"), int) and size != card["bytes"]:  # before reading a byte of it
            raise PretrainedError(f"{path} does not match its model card ({size} bytes, the card says "
                                  f"{card['bytes']}): a damaged or replaced file; reinstall or rebuild it")
        digest = hashlib.sha256()
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    if digest.hexdigest() != card["file_sha256"]:
        raise PretrainedError(f"{path} does not match its model card (sha256 {digest.hexdigest()[:12]}... != "
                              f"{card['file_sha256'][:12]}...): a damaged or replaced file; reinstall or rebuild it")
    from cuniform_torch.policies.checkpoint import read_checkpoint_file  # torch: only when a file is resolved

    ckpt = read_checkpoint_file(path, PretrainedError, "shipped policy file")
    system = ckpt.get("system") if isinstance(ckpt, dict) else None
    metrics = ckpt.get("metrics") if isinstance(ckpt, dict) else None
    differ = card_mismatch(card["robot"], system if isinstance(system, str) else "",
                           metrics if isinstance(metrics, dict) else {})
    if differ:
        raise PretrainedError(f"the model card {PRETRAINED_DIR / (name + '.json')} does not describe the robot its "
                              f"file {path.name} was trained for ({'; '.join(differ[:4])}): an edited card; "
                              "reinstall or rebuild it (python -m training.maps.pretrained --install)")
    return path


def card_mismatch(card_robot: dict[str, Any], system_json: str, metrics: dict[str, Any]) -> list[str]:
    """What the card's robot says that the policy file's own record contradicts, as ``"name: card X, file Y"``
    lines (empty: they agree): the system, horizon and every parameter the card gives against the file's system
    JSON, the radius against its ``robot_radius`` metric (when the file has one)."""
    try:
        spec = json.loads(system_json)
    except (ValueError, RecursionError):
        spec = None
    if not isinstance(spec, dict):
        return ["system: the file records no readable system JSON"]
    out = []
    for key, theirs in (("system", spec.get("name")), ("horizon", spec.get("horizon"))):
        if card_robot.get(key) != theirs:
            out.append(f"{key}: card {card_robot.get(key)!r}, file {theirs!r}")
    card_params, file_params = card_robot.get("params"), spec.get("params")
    if not isinstance(card_params, dict) or not isinstance(file_params, dict):
        out.append("params: not an object")
    else:
        for key in sorted(card_params):
            if json.dumps(card_params[key]) != json.dumps(file_params.get(key)):
                out.append(f"{key}: card {card_params[key]!r}, file {file_params.get(key)!r}")
    radius = metrics.get("robot_radius")
    if radius is not None and card_robot.get("radius") != radius:
        out.append(f"radius: card {card_robot.get('radius')!r}, file {radius!r}")
    return out


def robot_mismatch(card_robot: dict[str, Any], robot: dict[str, Any]) -> list[str]:
    """What differs between the robot a policy was trained for and ``robot`` (both ``preset_dict`` form: system,
    params, radius, horizon), as ``"name: trained X, given Y"`` lines (empty: the same robot)."""
    out = []
    for key in ("system", "radius", "horizon"):
        if card_robot.get(key) != robot.get(key):
            out.append(f"{key}: trained {card_robot.get(key)!r}, given {robot.get(key)!r}")
    a, b = card_robot.get("params") or {}, robot.get("params") or {}
    for key in sorted(set(a) | set(b)):
        if json.dumps(a.get(key)) != json.dumps(b.get(key)):
            out.append(f"{key}: trained {a.get(key)!r}, given {b.get(key)!r}")
    return out
