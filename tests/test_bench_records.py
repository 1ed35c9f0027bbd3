"""The navigation benchmark folder's one parser (eval.navigate.records.store.EpisodeStore): records without settings, a key
twice, NaN or infinite numbers, and settings or records of the wrong shape are each one clear error naming the file
(and line, and field), for a resumed run and for the read-only readers alike; nothing passes silently."""

from __future__ import annotations

import json

import pytest

from eval.navigate.compare import main as compare_main
from eval.navigate.records.store import EpisodeStore, StoreError


def bench_settings(suite: str = "gaps", **kw) -> dict:
    """A complete settings record (the shape eval.navigate.run.settings_record writes), changed by ``kw``."""
    robot = dict(system="dubins", params=dict(speed=0.5, dt=0.2), radius=0.2, horizon=6)
    gaps = dict(gap_widths=[0.6, 1.2]) if suite == "gaps" else {}
    return dict(suite=suite, seed=0, sensing_range=3.0, horizon=6, lambda_=0.5, collision_penalty=1e6,
                cost_resolution=0.01, robot=robot, time_limit=30.0, barn_file=None,
                sources=dict(table="00000000000000aa", coverage_table=None, policy=None)) | gaps | kw


def bench_record(task_id: int = 0, method: str = "mppi_1.0", budget: int = 16, repeat: int = 0,
                 outcome: str = "goal", suite: str = "gaps", **kw) -> dict:
    """A complete episode record (eval.navigate.episode.run_nav_episode's shape), changed by ``kw``."""
    return dict(key=f"{suite}/{task_id}/{method}/{budget}/{repeat}", suite=suite, task_id=task_id, method=method,
                budget=budget, seed=7 + task_id, repeat=repeat, outcome=outcome, success=outcome == "goal",
                time=3.2, path_length=1.6, steps=16, cycles=16, cycle_hist={"120": 16}, wall_s=0.4) | kw


_settings, _record = bench_settings, bench_record


def _folder(tmp_path, lines: list[str], settings: dict | None = None) -> EpisodeStore:
    """A folder opened with ``settings`` whose episodes.jsonl then holds ``lines`` as written."""
    store = EpisodeStore(tmp_path / "run")
    store.open(settings or _settings())
    store.records_file.write_text("".join(line + "\n" for line in lines))
    return store


def _line(rec: dict) -> str:
    return json.dumps(rec, separators=(",", ":"))


def _refused(store: EpisodeStore, match: str) -> None:
    """The resuming run (check, then open) and the read-only readers (load) refuse the folder, naming the problem."""
    for read in (store.check, lambda: store.open(_settings()), store.load):
        with pytest.raises(StoreError, match=match):
            read()


def test_a_good_folder_reads_back_and_resumes(tmp_path):
    recs = [_record(0), _record(1, outcome="collision"), _record(0, method="cu_table")]
    store = _folder(tmp_path, [_line(r) for r in recs])
    settings, got = store.load()
    assert settings == _settings() and got == {r["key"]: r for r in recs}
    assert store.open(_settings()) == got
    store.append(_record(2, path=[[0.0, 0.0], [0.1, 0.0]], extra="kept"))  # optional and unknown fields pass
    assert len(store.load()[1]) == 4


def test_records_without_settings_are_refused(tmp_path):
    """The attack: delete settings.json, rerun with another horizon, and the old episodes pass for the new one's."""
    store = _folder(tmp_path, [_line(_record(0))])
    store.settings_file.unlink()
    with pytest.raises(StoreError, match=r"run holds episode records \(episodes.jsonl\) but no settings.json.*"
                                         r"another --out, or delete .*episodes.jsonl"):
        store.open(_settings(horizon=20))
    assert not store.settings_file.exists()  # nothing written: the folder is as it was
    for read in (store.load, store.check):  # the read-only readers, and the run before it builds anything
        with pytest.raises(StoreError, match="run holds episode records .* but no settings.json"):
            read()
    store.records_file.write_text("\n")  # no record at all: a fresh folder
    store.check()
    assert store.open(_settings(horizon=20)) == {} and store.read_settings()["horizon"] == 20


def test_a_key_twice_is_refused_naming_the_file_and_both_lines(tmp_path):
    first, second = _record(0), _record(0, outcome="collision")  # the second would override the first
    _refused(_folder(tmp_path / "a", [_line(_record(1)), _line(first), _line(second)]),
             r"episodes.jsonl: line 3: episode 'gaps/0/mppi_1.0/16/0' again \(first on line 2\)")
    # an exact copy too: records are appended once each under the folder's lock, so a copy means hand edits
    _refused(_folder(tmp_path / "b", [_line(first), _line(first)]), r"line 2: episode .* again \(first on line 1\)")


@pytest.mark.parametrize("field, text", [("time", "NaN"), ("path_length", "Infinity"), ("wall_s", "1e999"),
                                         ("cycle_hist.120", "-Infinity")])
def test_a_nan_or_infinite_number_is_refused_naming_the_field(tmp_path, field, text):
    head, _, sub = field.partition(".")
    rec = _record(0)
    rec[head] = {sub: "X"} if sub else "X"
    line = _line(rec).replace('"X"', text)
    _refused(_folder(tmp_path, [_line(_record(1)), line]), rf"episodes.jsonl: line 2: field '{field}' is not a finite "
                                                             "number")


@pytest.mark.parametrize("change, match", [
    (dict(key="gaps/9/mppi_1.0/16/0"), r"key 'gaps/9/mppi_1.0/16/0' is not its fields' \('gaps/0/mppi_1.0/16/0'\)"),
    (dict(success=False), "success False contradicts outcome 'goal'"),
    (dict(outcome="crash", success=False), "field 'outcome' must be 'goal' or 'collision' or 'timeout'"),
    (dict(budget="16"), "field 'budget' must be an integer >= 1, got '16'"),
    (dict(steps=True), "field 'steps' must be an integer >= 0, got True"),
    (dict(time=-1.0), "field 'time' must be a number >= 0"),
    (dict(path=[[0.0, 0.0], [1.0]]), "field 'path' must be a list of"),
])
def test_a_record_of_the_wrong_shape_is_refused(tmp_path, change, match):
    _refused(_folder(tmp_path, [_line(_record(0) | change)]), f"episodes.jsonl: line 1: .*{match}")


def test_records_missing_a_field_not_an_object_or_of_another_suite_are_refused(tmp_path):
    rec = _record(0)
    del rec["time"]
    _refused(_folder(tmp_path / "a", [_line(rec)]), r"line 1: field\(s\) 'time' missing")
    _refused(_folder(tmp_path / "b", ["[1, 2]", _line(_record(0))]), "line 1: not a JSON object but a list")
    barn = _record(0) | dict(suite="barn", key="barn/0/mppi_1.0/16/0")
    _refused(_folder(tmp_path / "c", [_line(barn)]), "line 1: suite 'barn' in a folder of the 'gaps' suite")
    _refused(_folder(tmp_path / "d", ['{"key":"a","key":"b"}', _line(_record(0))]), "line 1 .*'key' given twice")
    _refused(_folder(tmp_path / "e", [_line(_record(0)), '{"key":"a","key":"b"}']), "line 2 .*'key' given twice")


def test_a_cut_short_last_line_is_dropped_and_a_whole_one_kept(tmp_path):
    store = _folder(tmp_path, [_line(_record(0))])
    with open(store.records_file, "ab") as f:
        f.write(_line(_record(1)).encode()[:-9])
    assert set(store.load()[1]) == {"gaps/0/mppi_1.0/16/0"}  # read only: left alone
    with pytest.warns(UserWarning, match="incomplete last line"):
        assert len(store.open(_settings())) == 1
    with open(store.records_file, "ab") as f:
        f.write(_line(_record(1)).encode())  # whole, but cut before its newline
    assert len(store.open(_settings())) == 2
    store.append(_record(2))  # starts on a fresh line
    assert len(store.load()[1]) == 3


@pytest.mark.parametrize("text, match", [
    ("[1, 2]", "not a JSON object but a list"),
    (_settings(sources="abc"), r"field 'sources' must be an object of digests \(16 hex digits\) or nulls, got 'abc'"),
    (_settings(sources={"table": 3}), "field 'sources' must be"),
    (_settings(horizon="15"), "field 'horizon' must be an integer >= 1, got '15'"),
    (_settings(seed=1.5), "field 'seed' must be an integer"),
    (_settings(robot={"system": "dubins"}), "field 'robot' must be an object"),
    (_settings(gap_widths=[0.6, "x"]), "field 'gap_widths' must be a list of numbers > 0"),
    (_settings(lambda_="NaN"), "field 'lambda_' is not a finite number"),
    (_settings(extra=1), r"unknown field\(s\) 'extra'"),
    ({k: v for k, v in _settings().items() if k != "time_limit"}, r"field\(s\) 'time_limit' missing"),
    ('{"suite": "gaps", "suite": "barn"}', "field 'suite' given twice"),
    ("{not json", "unreadable"),
])
def test_settings_of_the_wrong_shape_are_one_clear_error(tmp_path, capsys, text, match):
    store = _folder(tmp_path, [_line(_record(0))])
    if isinstance(text, dict):
        text = json.dumps(text).replace('"NaN"', "NaN")
    store.settings_file.write_text(text)
    _refused(store, f"settings.json: .*{match}")
    # a read-only reader's command: one line, no traceback
    assert compare_main(["--out", str(store.folder), "--method", "mppi_1.0@16", "--against", "cu_table@16"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1 and "Traceback" not in err and "settings.json" in err


def test_the_run_refuses_to_write_settings_of_the_wrong_shape(tmp_path):
    """settings_record and the store's schema move together: a field the schema lacks is refused before any write."""
    with pytest.raises(ValueError, match=r"unknown field\(s\) 'new_knob'"):
        EpisodeStore(tmp_path / "run").open(_settings(new_knob=1))
    assert not (tmp_path / "run").exists()


def test_the_run_refuses_records_without_settings_before_building_any_table(tmp_path, capsys):
    """The attack end to end: python -m eval.navigate into a folder whose settings.json was deleted."""
    from eval.navigate.run import main as navigate_main

    store = _folder(tmp_path, [_line(_record(0))])
    store.settings_file.unlink()
    argv = ["--suite", "gaps", "--tasks", "1", "--budgets", "16", "--methods", "mppi_1.0", "--horizon", "8",
            "--out", str(store.folder), "--cache", str(tmp_path / "cache"), "--quiet"]
    assert navigate_main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1 and "but no settings.json" in err, err
    assert not (tmp_path / "cache").exists() and not store.settings_file.exists()  # no work done, nothing written
