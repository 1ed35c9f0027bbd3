"""The reference lengths of a benchmark folder's tasks, and its episodes' BARN scores
(:mod:`eval.navigate.records.score`).

A BARN map's reference length is the Challenge's: start, the map's A* path, goal
(:func:`eval.navigate.records.score.barn_reference_length`). A world without such a path (the forest and clutter
suites) takes the geodesic distance instead: the shortest
8-connected path from the start's cell to the goal around the robot-inflated obstacles, all of them known, on
cells of :data:`GEODESIC_RESOLUTION` m (:func:`eval.navigate.cost_to_go.geodesic_distance`, the benchmark's cost-to-
go planner). A grid path is at most 8% longer than the true one (in the worst direction); along the corridors, which
run along x, much less: clutter task 5's is 36.13 m at 0.1 m cells, 36.01 m at 0.025 m. The moving suite's is the
geodesic around its still obstacles (the walls), the discs left out: they cross the way and leave it, so no fixed
path goes around them (DynaBARN scores the same way, against the static map); the sudden suite's goes around its
disc. The gap suite is not scored (its tasks depend on the sweep's length, which its settings do not record).

:func:`episode_scores` scores a folder's records (rebuilding each task from the folder's settings; the geodesic
lengths, seconds per task, are cached under ``cache`` when one is given). It rebuilds worlds (``precompute.worlds``)
and plans on them (torch): a report's work, not the records'.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

from cuniform_torch.common.fileio import MAX_JSON_BYTES, read_capped_text, write_json
from eval.navigate.records.score import barn_reference_length, barn_score

__all__ = ["GEODESIC_RESOLUTION", "SCORED_SUITES", "geodesic_length", "reference_lengths", "episode_scores"]

GEODESIC_RESOLUTION = 0.1
"""m: the cell of the geodesic distance where a world has no reference path"""
SCORED_SUITES = ("barn", "forest", "clutter", "moving", "sudden")
"""suites whose tasks get a reference length (module docstring)"""


def geodesic_length(task: Any, resolution: float = GEODESIC_RESOLUTION) -> float | None:
    """The grid geodesic (m) from ``task.start`` to ``task.goal`` around ``task.environment`` (the robot-inflated
    obstacles, all known; moving discs left out: module docstring); None when the goal cannot be reached on the
    grid."""
    import torch

    from cuniform_torch.envs import Environment
    from eval.navigate.cost_to_go import UNREACHABLE, CostToGo

    to_go = CostToGo(task.bounds, task.goal, resolution)
    to_go.update(Environment(task.environment.obstacles, bounds=task.environment.bounds))  # the still obstacles
    length = float(to_go(torch.tensor(task.start[:2], dtype=torch.float32)))
    return None if length >= UNREACHABLE else length




# ------------------------------------------------------------------------------------------------ a folder's tasks

def _digest(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()[:16]


def _barn_lengths(settings: Mapping[str, Any], ids: set[int], barn_file: Path | None) -> tuple[dict[int, float], str]:
    from precompute.worlds.barn import CHALLENGE_GOAL, CHALLENGE_START, load_barn

    recorded = settings.get("barn_file")
    if recorded is not None and (barn_file is None or _digest(barn_file) != recorded):
        given = "none given" if barn_file is None else f"{barn_file} has another digest"
        return {}, (f"the run used a BARN file of digest {recorded} ({given}): give it (--barn-file) to score its "
                    f"episodes")
    maps = {m.map_id: m for m in load_barn(barn_file if recorded is not None else None)}
    lengths = {i: barn_reference_length(maps[i].path, CHALLENGE_START, CHALLENGE_GOAL) for i in ids if i in maps}
    missing = sorted(ids - set(lengths))
    return lengths, (f"no BARN map {', '.join(map(str, missing))} in the file" if missing else "")


def _cache_file(cache: Path, settings: Mapping[str, Any], resolution: float) -> Path:
    key = dict(suite=settings["suite"], seed=settings["seed"], radius=settings["robot"]["radius"],
               resolution=resolution)
    return Path(cache) / "references" / f"{hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:16]}.json"


def _read_cache(path: Path) -> dict[int, float]:
    """The cached lengths of ``path`` (empty when absent or not such a file: it is rebuilt)."""
    try:
        data = json.loads(read_capped_text(path, MAX_JSON_BYTES, "a reference-length cache"))
        return {int(k): float(v) for k, v in data["lengths"].items() if math.isfinite(float(v)) and float(v) > 0}
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return {}


def _geodesic_lengths(settings: Mapping[str, Any], ids: set[int], cache: Path | None,
                      resolution: float) -> tuple[dict[int, float], str]:
    from precompute.worlds.suites import SuiteError
    from precompute.worlds.tasks import make_task

    path = _cache_file(cache, settings, resolution) if cache is not None else None
    lengths = _read_cache(path) if path is not None else {}
    known = {i: lengths[i] for i in ids if i in lengths}
    bad = []
    for i in sorted(ids - set(known)):
        try:
            task = make_task(settings["suite"], i, float(settings["robot"]["radius"]), seed=int(settings["seed"]))
        except SuiteError:
            bad.append(i)
            continue
        length = geodesic_length(task, resolution)
        if length is None:
            bad.append(i)
        else:
            known[i] = lengths[i] = length
    if path is not None and len(lengths) > len(_read_cache(path)):
        path.parent.mkdir(parents=True, exist_ok=True)
        write_json(path, dict(suite=settings["suite"], seed=settings["seed"], radius=settings["robot"]["radius"],
                              resolution=resolution, lengths={str(k): v for k, v in sorted(lengths.items())}))
    return known, (f"no reference for {settings['suite']} task(s) {', '.join(map(str, bad))}" if bad else "")


def reference_lengths(settings: Mapping[str, Any], task_ids: Iterable[int], barn_file: str | Path | None = None,
                      cache: str | Path | None = None,
                      resolution: float = GEODESIC_RESOLUTION) -> tuple[dict[int, float], str]:
    """``({task_id: reference length (m)}, note)`` for the tasks of a benchmark folder's ``settings``: BARN from
    each map's path (the run's BARN file: the shipped one, or ``barn_file`` when the settings name another), forest
    and clutter the grid geodesic (cached under ``cache``/references when given). The note says which tasks have
    none and why ("" when all do)."""
    ids = {int(i) for i in task_ids}
    suite = settings.get("suite")
    if suite not in SCORED_SUITES:
        return {}, f"the {suite} suite has no reference lengths (scored suites: {', '.join(SCORED_SUITES)})"
    if suite == "barn":
        return _barn_lengths(settings, ids, None if barn_file is None else Path(barn_file))
    return _geodesic_lengths(settings, ids, None if cache is None else Path(cache), resolution)


def episode_scores(settings: Mapping[str, Any], records: Sequence[Mapping[str, Any]],
                   barn_file: str | Path | None = None, cache: str | Path | None = None) -> tuple[dict[str, float], str]:
    """``({record key: BARN score}, note)``: each record's :func:`barn_score` (from its ``success`` and ``time`` and
    its task's reference length); records whose task has no reference length are left out, and the note says why."""
    lengths, note = reference_lengths(settings, {r["task_id"] for r in records}, barn_file, cache)
    scores = {str(r["key"]): barn_score(bool(r["success"]), float(r["time"]), lengths[int(r["task_id"])])
              for r in records if int(r["task_id"]) in lengths}
    return scores, note


