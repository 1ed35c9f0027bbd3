"""The navigation benchmark's records layer (eval.navigate.records): importing it, and reading a folder through it,
loads no torch and nothing of the runner; the reports import only public names from eval.navigate; its torch-free
file readers refuse what cuniform_torch.common.fileio's refuse, with the same messages."""

from __future__ import annotations

import ast
import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from test_bench_records import bench_record, bench_settings

from cuniform_torch.common import fileio
from eval.navigate.records import files

ROOT = Path(__file__).resolve().parents[1]
NAVIGATE = ROOT / "eval" / "navigate"
RUNNER = ("eval.navigate.run", "eval.navigate.episode", "eval.navigate.execute", "eval.navigate.robot_files",
          "eval.navigate.cost_to_go", "eval.navigate.dynamics", "eval.navigate.gym_env")
"""the runner's modules: the records import none of them"""

RUNNER_PRIVATES: set = set()
"""private names of the runner that reports may still import: none (the runner's names they read are public)"""


def _python(code: str, cwd: Path = ROOT) -> str:
    """stdout of ``python -c code`` in a fresh interpreter on this checkout (its stderr in the failure)."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    proc = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    return proc.stdout


_LOADED = """
    import sys
    runner = {runner!r}
    print(sorted(m for m in sys.modules if m.split(".")[0] in ("torch", "cuniform_torch") or m in runner))
"""


def test_importing_the_records_loads_no_torch_and_nothing_of_the_runner():
    out = _python("import eval.navigate.records\n" + textwrap.dedent(_LOADED.format(runner=RUNNER)))
    assert out.strip() == "[]", f"import eval.navigate.records loaded {out.strip()}"


def test_reading_and_summarizing_a_folder_loads_no_torch(tmp_path):
    folder = tmp_path / "run"
    folder.mkdir()
    (folder / "settings.json").write_text(json.dumps(bench_settings()))
    recs = [bench_record(task_id=i, method=m, outcome="goal" if (i + (m == "cu_table")) % 3 else "collision")
            for i in range(6) for m in ("mppi_1.0", "cu_table")]
    (folder / "episodes.jsonl").write_text("".join(json.dumps(r) + "\n" for r in recs))
    code = f"""
        from eval.navigate.records import (by_episode, compare_pair, load_episode, load_folder, paired_comparisons,
                                           summarize)
        settings, by_key = load_folder({str(folder)!r})
        records = list(by_key.values())
        rows = summarize(records)
        pairs = paired_comparisons(records, ["mppi_1.0"])
        mine, base = ([r for r in records if r["method"] == m] for m in ("cu_table", "mppi_1.0"))
        one = compare_pair(None, None, "cu_table", "mppi_1.0", by_episode(mine, "a"), by_episode(base, "b"))
        load_episode({str(folder)!r}, records[0]["key"])
        print(len(records), len(rows), len(pairs), one is not None)
    """
    code = textwrap.dedent(code) + textwrap.dedent(_LOADED.format(runner=RUNNER))
    counts, loaded = _python(code).strip().splitlines()
    assert counts == "12 2 1 True"
    assert loaded == "[]", f"reading a folder loaded {loaded}"


def _imports(path: Path) -> list[tuple[str, str, int]]:
    """``(module, name, line)`` of every ``from module import name`` in ``path``, in functions too."""
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module:
            out += [(node.module, alias.name, node.lineno) for alias in node.names]
        elif isinstance(node, ast.Import):
            out += [(alias.name, "", node.lineno) for alias in node.names]
    return out


def test_the_records_import_nothing_of_the_rest_of_eval_navigate_and_no_runtime():
    bad = []
    for path in sorted((NAVIGATE / "records").glob("*.py")):
        for module, name, line in _imports(path):
            where = f"{path.relative_to(ROOT)}:{line}: {module} {name}".strip()
            if module.startswith("eval.navigate") and not module.startswith("eval.navigate.records"):
                bad.append(where)  # the runner or a report: records are below both
            if module.split(".")[0] == "torch" or (module.startswith("cuniform_torch")
                                                    and (path.name, module) != ("store.py", "cuniform_torch.common.fileio")):
                bad.append(where)  # only the run's write of settings.json, inside EpisodeStore.open, reaches the runtime
    assert not bad, bad


def test_the_reports_import_only_public_names_from_eval_navigate():
    found = set()
    for path in sorted(NAVIGATE.rglob("*.py")):
        for module, name, _ in _imports(path):
            if module.startswith("eval.navigate") and name.startswith("_"):
                found.add((path.relative_to(NAVIGATE).as_posix(), module, name))
    records = sorted(f for f in found if f[1].startswith("eval.navigate.records"))
    assert not records, f"private names of the records imported: {records}"
    assert found - RUNNER_PRIVATES == set(), f"private names imported (make them public): {sorted(found - RUNNER_PRIVATES)}"
    assert RUNNER_PRIVATES - found == set(), f"no longer imported, drop from RUNNER_PRIVATES: {RUNNER_PRIVATES - found}"


def _outcome(read, *args) -> tuple[str, str]:
    try:
        return "bytes", repr(read(*args))
    except (OSError, ValueError) as err:
        kind = "FileNotFoundError" if isinstance(err, FileNotFoundError) else type(err).__mro__[1].__name__
        return kind, str(err)


@pytest.mark.parametrize("case", ["regular", "folder", "fifo", "link to a fifo", "over the cap", "missing",
                                  "not utf-8"])
def test_the_torch_free_readers_refuse_what_fileio_refuses(tmp_path, case):
    path = tmp_path / "settings.json"
    if case in ("regular", "over the cap"):
        path.write_text('{"suite": "barn"}' + " " * (64 if case == "over the cap" else 0))
    elif case == "not utf-8":
        path.write_bytes(b"\xff\xfe{}")
    elif case == "folder":
        path.mkdir()
    elif case in ("fifo", "link to a fifo"):
        os.mkfifo(tmp_path / "fifo")
        if case == "fifo":
            path = tmp_path / "fifo"
        else:
            path.symlink_to(tmp_path / "fifo")
    cap = 32
    ours = _outcome(files.read_capped_text, path, cap, "the benchmark settings")
    theirs = _outcome(fileio.read_capped_text, path, cap, "the benchmark settings")
    assert ours == theirs
    assert (ours[0] == "bytes") == (case == "regular"), ours
    assert files.file_kind(os.lstat(tmp_path).st_mode) == fileio.file_kind(os.lstat(tmp_path).st_mode) == "a folder"


def test_the_torch_free_readers_have_fileios_caps():
    assert (files.MAX_SMALL_JSON_BYTES, files.MAX_JSONL_BYTES) == (fileio.MAX_SMALL_JSON_BYTES, fileio.MAX_JSONL_BYTES)
