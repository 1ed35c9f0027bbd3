"""Paired comparison of two benchmark cells (python -m eval.navigate compare): pairs on (task, seed) across budgets,
counts wins and losses, and the margin verdicts follow the interval; bad cells are one clear error."""

from __future__ import annotations

import json

import pytest
from test_bench_records import bench_record, bench_settings  # complete settings and records (the store checks them)

from eval.navigate.compare import compare_cells, main, parse_cell


def _folder(tmp_path, outcomes: dict[tuple[str, int], list[bool]]):
    """A benchmark folder whose cell (method, budget) succeeded on task k as ``outcomes[cell][k]``."""
    (tmp_path / "settings.json").write_text(json.dumps(bench_settings("clutter")))
    lines = [json.dumps(bench_record(k, m, b, outcome="goal" if s else "collision", suite="clutter", seed=1000 + k))
             for (m, b), col in outcomes.items() for k, s in enumerate(col)]
    (tmp_path / "episodes.jsonl").write_text("\n".join(lines) + "\n")
    return tmp_path


def test_cells_pair_on_task_and_seed_across_budgets(tmp_path):
    a = [True] * 18 + [False] * 2  # 0.90
    b = [True] * 10 + [False] * 10  # 0.50: a wins on tasks 10..17, never loses
    recs = [json.loads(x) for x in _folder(tmp_path, {("cfu", 256): a, ("mppi", 1024): b}).joinpath(
        "episodes.jsonl").read_text().splitlines()]
    row = compare_cells(recs, ("cfu", 256), ("mppi", 1024))
    assert (row["n"], row["wins"], row["losses"]) == (20, 8, 0)
    assert row["diff"] == pytest.approx(0.4) and row["diff_low"] < 0.4 < row["diff_high"]
    assert row["method_rate"] == pytest.approx(0.9) and row["baseline_rate"] == pytest.approx(0.5)
    assert row["p_value"] == pytest.approx(2 / 2 ** 8)  # exact McNemar: 8 discordant pairs, all one way


def test_cli_margin_verdicts(tmp_path, capsys):
    out = _folder(tmp_path, {("cfu", 256): [True] * 18 + [False] * 2, ("cu", 256): [True] * 10 + [False] * 10,
                             ("mppi", 1024): [True] * 17 + [False] * 3})
    assert main(["--out", str(out), "--method", "cfu@256", "--against", "cu@256", "mppi@1024", "--margin", "0.1"]) == 0
    rows = [line for line in capsys.readouterr().out.splitlines() if line.startswith("| cfu@256")]
    assert rows[0].endswith("| yes | yes |")  # +0.40, interval well above +0.10
    assert rows[1].endswith("| no | no |")  # +0.05


def test_bad_cells_are_one_clear_error(tmp_path, capsys):
    out = _folder(tmp_path, {("cfu", 256): [True, False]})
    with pytest.raises(ValueError, match="METHOD@BUDGET"):
        parse_cell("cfu256")
    assert main(["--out", str(out), "--method", "cfu@256", "--against", "cu@64"]) == 2
    err = capsys.readouterr().err
    assert "no episode of cu@64" in err and "cfu@256" in err and len(err.strip().splitlines()) == 1
