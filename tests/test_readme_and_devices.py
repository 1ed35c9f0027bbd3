"""Docs stay true (the README's and the guides' Python examples run) and the table policy agrees across devices."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import torch

from cuniform_torch.policies.table import TablePolicy
from cuniform_torch.tables.file import write_table

README = Path(__file__).resolve().parents[1] / "README.md"
GUIDES = sorted((README.parent / "docs" / "guides").glob("*.md"))


def _python_blocks(text: str) -> list[str]:
    return re.findall(r"```python\n(.*?)```", text, flags=re.S)


def guide_examples() -> list[tuple[str, str]]:
    """``(guide, code)`` of every guide example not already run from the README; a block opening with
    ``# after:`` (it needs a long run first) or ``# needs:`` (an optional extra; tests/test_docs.py runs it when
    the extra is there) is left out."""
    readme = set(_python_blocks(README.read_text()))
    return [(path.name, code) for path in GUIDES for code in _python_blocks(path.read_text())
            if code not in readme and not code.startswith(("# after:", "# needs:"))]


def test_readme_python_example_runs(tmp_path, dubins_table, monkeypatch):
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
    blocks = [b for b in blocks if not b.startswith("# after:")]  # those need a long run first (distillation)
    assert blocks, "the README has no python example"
    write_table(tmp_path / "out" / "dubins.npz", dubins_table)
    monkeypatch.chdir(tmp_path)
    namespaces = []
    for code in blocks:
        namespace: dict = {}
        exec(compile(code, "README.md", "exec"), namespace)
        namespaces.append(namespace)
    assert namespaces[0]["states"].shape == (1000, 11, 3)  # the ten-line API of the first screen
    assert namespaces[0]["result"].outcome == "goal"
    # the closed-loop example of the Controllers section: every one of its controllers reaches the goal
    (five,) = [ns for ns in namespaces if "controllers" in ns]
    assert set(five["results"]) == set(five["controllers"]) and len(five["results"]) == 5
    assert {name: r.outcome for name, r in five["results"].items()} == dict.fromkeys(five["controllers"], "goal")
    # the last example (your own robot: a unicycle distilled and driven by CU-MPPI)
    assert namespaces[-1]["result"].outcome == "goal"


@pytest.mark.parametrize("guide, code", guide_examples(), ids=lambda v: v if v.endswith(".md") else "")
def test_guide_python_example_runs(guide, code, tmp_path, dubins_table, monkeypatch):
    write_table(tmp_path / "out" / "dubins.npz", dubins_table)
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    exec(compile(code, f"docs/guides/{guide}", "exec"), namespace)
    if "states" in namespace and "policy" in namespace:  # a rollout example: [N, T+1, d] states
        assert namespace["states"].shape[1:] == (11, 3)
    if "result" in namespace:  # a closed-loop example: it reaches its goal
        assert namespace["result"].outcome == "goal"


def test_the_guides_have_runnable_examples():
    assert {guide for guide, _ in guide_examples()} >= {"python-api.md", "controllers.md"}


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_table_policy_lookups_agree_on_cpu_and_gpu(dubins_table):
    cpu, gpu = TablePolicy(dubins_table, "cpu"), TablePolicy(dubins_table, "cuda")
    gen = torch.Generator().manual_seed(0)
    x = torch.rand(5000, 3, generator=gen) * torch.tensor([2.0, 2.0, 6.28]) - torch.tensor([0.0, 1.0, 3.14])
    for t in range(dubins_table.horizon + 1):
        assert torch.equal(cpu.rows(x, t), gpu.rows(x.cuda(), t).cpu())
        torch.testing.assert_close(cpu.action_probs(x, t), gpu.action_probs(x.cuda(), t).cpu())
