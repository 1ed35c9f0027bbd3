"""Pretrained map policies shipped as package data, loaded by name: ``load_map_policy("unicycle-0.5")``.

Each lives in ``cuniform_torch/maps/weights/`` as ``NAME.map_policy.pt`` and its model card ``NAME.json``
(format :data:`CARD_FORMAT`: the robot it was trained for, its data and training, and the file's sha256). A name
resolves to its file only when the card is readable and the file's sha256 is the card's, so a damaged or swapped
file is one clear error, never a different policy. ``python -m training.maps.pretrained --install`` rebuilds them.
"""

from __future__ import annotations

import hashlib
import json
import re
from pathlib import Path
from typing import Any

__all__ = ["CARD_FORMAT", "PRETRAINED_DIR", "PretrainedError", "pretrained_names", "pretrained_card",
           "pretrained_path", "robot_mismatch"]

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
    if path.stat().st_size > _MAX_CARD_BYTES:
        raise PretrainedError(f"{path}: a model card of {path.stat().st_size} bytes is not one this package wrote")
    try:
        card = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
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
    if not path.is_file():
        raise PretrainedError(f"the pretrained map policy {name!r}: its file {path} is missing (reinstall the "
                              "package, or rebuild it: python -m training.maps.pretrained --install)")
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    if digest != card["file_sha256"]:
        raise PretrainedError(f"{path} does not match its model card (sha256 {digest[:12]}... != "
                              f"{card['file_sha256'][:12]}...): a damaged or replaced file; reinstall or rebuild it")
    return path


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
