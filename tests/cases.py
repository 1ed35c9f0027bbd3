"""Tables of hardening cases shared by the tests and the attack run (``python .ci/attack.py``).

One table per file family or entry point where the tests and the attack run try the same damage: the tests check
the exact error message, the attack run the outcome class (clear error, silent wrong, traceback, hang, ...) in a
forked process with its memory peak. A case added here is tried by both. Kept light: numpy and the table format
only, so .ci/attack.py can import it before it forks.
"""

from __future__ import annotations

import io
import json
import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np

from cuniform_torch.tables.file import TABLE_FORMAT

DEEP = "[" * 100000 + "]" * 100000
"""valid JSON nested deeper than the json module's recursion allows (it raises RecursionError)"""


# ------------------------------------------------------------------------------------------ table files (.npz)
# Files that are no table at all: each ``make(path, good)`` writes (or does not write) ``path`` from the valid table
# file ``good``; read_table must raise a TableError matching the regex.

def _missing(path: Path, good: Path) -> None:
    """Nothing at ``path``."""


def _folder(path: Path, good: Path) -> None:
    path.mkdir()


def _empty(path: Path, good: Path) -> None:
    path.write_bytes(b"")


def _truncated(path: Path, good: Path) -> None:
    data = good.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def _zeroed_middle(path: Path, good: Path) -> None:
    data = bytearray(good.read_bytes())
    mid = len(data) // 2
    data[mid - 64: mid + 64] = bytes(128)
    path.write_bytes(bytes(data))


def _garbage(path: Path, good: Path) -> None:
    path.write_bytes(np.random.default_rng(0).bytes(4096))


def _other_npz(path: Path, good: Path) -> None:
    with open(path, "wb") as fh:
        np.savez(fh, foo=np.arange(3))


def _zip_without_npy(path: Path, good: Path) -> None:
    with zipfile.ZipFile(path, "w") as zf:
        zf.writestr("readme.txt", b"not arrays")


def _npy_not_npz(path: Path, good: Path) -> None:
    with open(path, "wb") as fh:
        np.save(fh, np.arange(5))


def _raw_format_member(path: Path, good: Path) -> None:
    with zipfile.ZipFile(path, "w") as zf:
        zf.writestr("format", TABLE_FORMAT.encode())


def _raw_cells_member(path: Path, good: Path) -> None:
    """The valid table with its ``cells`` member raw bytes, not an ``.npy`` array."""
    with np.load(good, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    with zipfile.ZipFile(path, "w") as zf:
        for key, value in arrays.items():
            if key == "cells":
                zf.writestr("cells", b"not an array")
            else:
                buf = io.BytesIO()
                np.lib.format.write_array(buf, value, allow_pickle=False)
                zf.writestr(f"{key}.npy", buf.getvalue())


UNREADABLE_TABLES: list[tuple[str, Callable[[Path, Path], None], str]] = [
    ("missing", _missing, r"no table file there"),
    ("a-folder", _folder, r"no table file there"),
    ("empty", _empty, r"not a readable .npz table"),
    ("truncated", _truncated, r"not a readable .npz table|corrupt or truncated"),
    ("zeroed-middle", _zeroed_middle, r"not a readable .npz table|corrupt or truncated"),
    ("random-garbage", _garbage, r"not a readable .npz table"),
    ("another-npz", _other_npz, r"no 'format' key"),
    ("zip-without-npy", _zip_without_npy, r"no 'format' key"),
    ("npy-not-npz", _npy_not_npz, r"not a .*table|npz"),
    ("format-not-an-array", _raw_format_member, r"format"),
    ("cells-not-an-array", _raw_cells_member, r"cells"),
]
"""(id, make(path, good), the TableError's regex): a file at a table's path that is no table"""

# Content: each mutation edits the arrays of a small valid Dubins table (levels 1, 5, 13, 25 for horizon 3) in
# place; the reader must refuse the result with a TableError matching the regex (the shapes in the regexes are
# horizon 3's).
# The tests write the arrays without content digests, the attack run with fresh ones: either way the content
# checks, not the digest, must catch it.

def _scale_row(a):
    a["action_probs"][0] *= 0.5


def _negative_prob(a):
    a["action_probs"][1] = 0.0
    a["action_probs"][1, :2] = (1.5, -0.5)


def _nan_prob(a):
    a["action_probs"][2, 0] = np.nan


def _nan_cell_prob(a):
    a["cell_probs"][3] = np.nan


def _inf_cell_size(a):
    a["cell_size"][0] = np.inf


def _offsets_end_short(a):
    a["level_offsets"][-1] -= 1


def _offsets_end_long(a):
    a["level_offsets"][-1] += 1


def _offsets_not_increasing(a):
    a["level_offsets"][2] = a["level_offsets"][1]


def _offsets_not_from_zero(a):
    a["level_offsets"][0] = 1


def _cell_probs_short(a):
    a["cell_probs"] = a["cell_probs"][:-1]


def _action_probs_narrow(a):
    a["action_probs"] = np.ascontiguousarray(a["action_probs"][:, :-1])


def _cell_probs_level_sum(a):
    a["cell_probs"][-1] += 0.01


def _flow_target(a):
    a["flow_target"][0] += 1


def _flow_value(a):
    a["flow_value"][0] = a["flow_target"][0] + 1


def _angle_cell(a):
    a["cells"][-1, 2] = 40  # K = 40 angle cells: valid indices are 0..39


def _arc_outside(a):
    a["arcs"][0, 1] = len(a["cells"]) + 5


def _arc_wrong_level(a):
    a["arcs"][0, 1] = 0  # step 0 arcs must end in level 1


def _transitions_alone(a):
    del a["transition_frac"]


def _periodic_changed(a):
    a["periodic"][2] = False


def _format_bytes(a):
    a["format"] = np.array(TABLE_FORMAT.encode())


def _format_list(a):
    a["format"] = np.array([TABLE_FORMAT])


def _system_not_string(a):
    a["system"] = np.array(3)


def _method_not_string(a):
    a["method"] = np.arange(2)


TABLE_CORRUPTIONS: list[tuple[str, Callable[[dict[str, np.ndarray]], None], str]] = [
    # dtype / ndim
    ("action_probs-float64", lambda a: a.update(action_probs=a["action_probs"].astype(np.float64)),
     r"'action_probs' must be float32"),
    ("cells-int32", lambda a: a.update(cells=a["cells"].astype(np.int32)), r"'cells' must be int64"),
    ("level_offsets-float64", lambda a: a.update(level_offsets=a["level_offsets"].astype(np.float64)),
     r"'level_offsets' must be int64"),
    ("periodic-uint8", lambda a: a.update(periodic=a["periodic"].astype(np.uint8)), r"'periodic' must be bool"),
    ("actions-float64", lambda a: a.update(actions=a["actions"].astype(np.float64)), r"'actions' must be float32"),
    ("cell_probs-2d", lambda a: a.update(cell_probs=a["cell_probs"][:, None]), r"'cell_probs' must be float64 with 1"),
    ("arcs-float", lambda a: a.update(arcs=a["arcs"].astype(np.float64)), r"'arcs' must be int64"),
    ("format-bytes", _format_bytes, r"'format' must be a string"),
    ("format-list", _format_list, r"'format' must be a string"),
    ("system-int", _system_not_string, r"'system' must be a string"),
    ("method-array", _method_not_string, r"'method' must be a string"),
    # probabilities
    ("nan-action_probs", _nan_prob, r"action_probs contains NaN"),
    ("nan-cell_probs", _nan_cell_prob, r"cell_probs contains NaN"),
    ("inf-cell_size", _inf_cell_size, r"cell_size contains NaN or infinite"),
    ("row-sum", _scale_row, r"action_probs rows must sum to 1; row 0 sums to 0\.5"),
    ("negative-prob", _negative_prob, r"action_probs must lie in \[0, 1\]"),
    ("level-sum", _cell_probs_level_sum, r"cell_probs must sum to 1 in every level"),
    # shapes and offsets
    ("cell_probs-short", _cell_probs_short, r"'cell_probs' must have shape \[44\] .*header says \[43\]"),
    ("action_probs-narrow", _action_probs_narrow, r"'action_probs' must have shape \[44, 5\] .*header says \[44, 4\]"),
    ("offsets-end-short", _offsets_end_short, r"'cells' must have shape \[43, 3\] .*header says \[44, 3\]"),
    ("offsets-end-long", _offsets_end_long, r"'cells' must have shape \[45, 3\] .*header says \[44, 3\]"),
    ("offsets-flat", _offsets_not_increasing, r"level_offsets must .*increase strictly"),
    ("offsets-start", _offsets_not_from_zero, r"level_offsets must start at 0"),
    ("flow_target", _flow_target, r"flow_target must be n_t \* n_\{t\+1\}"),
    ("flow_value", _flow_value, r"flow_value must lie in \[0, flow_target\]"),
    ("angle-cell", _angle_cell, r"cells of angle dimension 2 must lie in \[0, 40\)"),
    ("arc-outside", _arc_outside, r"arcs refer to rows outside the table"),
    ("arc-level", _arc_wrong_level, r"arcs of step t must go from level t to level t\+1"),
    ("transitions-alone", _transitions_alone, r"transition_offsets, transitions and transition_frac must be stored together"),
    ("periodic-changed", _periodic_changed, r"periodic .* does not match the system"),
]


SYSTEM_JSON_MALFORMED: list[tuple[str, str]] = [
    ("{not json", r"system JSON does not parse"),
    ("[1, 2]", r"system JSON must be an object with name, params and horizon"),
    ('{"name": "dubins", "params": {}}', r"system JSON must be an object with name, params and horizon"),
    ('{"name": "dubins", "params": {"speeed": 1}, "horizon": 3}', r"no parameter\(s\) speeed"),
    ('{"name": "dubins", "params": {"num_actions": 0}, "horizon": 3}', r"num_actions must be a positive integer"),
    ('{"name": "dubins", "params": {}, "horizon": "3"}', r"horizon must be a positive integer"),
]
"""(the ``system`` key's text, the TableError it must raise): system JSON that does not describe a system"""


# ------------------------------------------------------------------------------------------ policy cards

CARD_EDITS: list[tuple[dict[str, float], str]] = [({"speed": 0.6}, "speed: card 0.6, file 0.5"),
                                                  ({"radius": 0.5}, "radius: card 0.5, file 0.2"),
                                                  ({"horizon": 12}, "horizon: card 12, file 15"),
                                                  ({"max_omega": 2.0}, "max_omega: card 2.0, file 1.5")]
"""(robot fields written into the shipped card ``unicycle-0.5.json``, what the PretrainedError says): a card edited
to another robot, its weights unchanged"""


def edit_card(card: Path, **robot: float) -> None:
    """Write ``robot``'s fields into the policy card ``card`` (a top-level robot field or one of its params)."""
    doc = json.loads(card.read_text())
    for key, value in robot.items():
        if key in doc["robot"]:
            doc["robot"][key] = value
        else:
            doc["robot"]["params"][key] = value
    card.write_text(json.dumps(doc, indent=2))


# ------------------------------------------------------------------------------------------ table sets

SET_MEMBER_NAMES: list[tuple[str, str, str]] = [("too-long", "a" * 300 + ".npz", "is not usable .*File name too long"),
                                                ("nul", "nul\0.npz", "but missing")]
"""(id, a member's file name in tables.json, what the TableError says): names the file system cannot use"""


def too_many_entries(limit: int) -> list[dict]:
    """tables.json entries, one more than ``limit`` (``MAX_SET_TABLES``): refused from the count, at once."""
    return [{"file": f"start_{i:06d}.npz", "start": [float(i)]} for i in range(limit + 1)]


def one_member_repeated(times: int = 20_000) -> list[dict]:
    """tables.json entries naming ``start_0000.npz`` ``times`` times: refused in a moment (it was 47 s)."""
    return [{"file": "start_0000.npz", "start": [float(i)]} for i in range(times)]


# ------------------------------------------------------------------------------------------ benchmark folders

RECORD_LINK_TARGETS: list[str] = ["other", "/dev/null"]
"""where a benchmark folder's episodes.jsonl links: ``"other"`` (another benchmark folder's records) or a device;
refused by every reader, never written through"""


# ------------------------------------------------------------------------------------------ precompute.build

STARTS_GRIDS: list[tuple[str, str]] = [("0=-1:1:20001", "20,001"), ("random:1000000 0=-1:1", "1,000,000")]
"""(a random-walk ``--starts`` value, the count the error names): more than the limit of 10,000, refused before
any work"""
