"""CI runs exactly the README's setup and test commands: .ci/run reads them from the README with
.ci/readme_commands.py, and the README holds exactly one of each."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
spec = importlib.util.spec_from_file_location("readme_commands", ROOT / ".ci" / "readme_commands.py")
readme_commands = importlib.util.module_from_spec(spec)
spec.loader.exec_module(readme_commands)


def test_ci_runs_the_readme_commands():
    run = (ROOT / ".ci" / "run").read_text()
    assert '"$(python .ci/readme_commands.py setup)"' in run and '"$(python .ci/readme_commands.py test)"' in run
    assert 'bash -euo pipefail -c "$setup"' in run and 'bash -euo pipefail -c "$test_cmd"' in run
    text = (ROOT / "README.md").read_text()
    setup = readme_commands.readme_command(text, "setup")
    assert setup.startswith("pip install torch==2.13.0")  # the CPU build first: a loose torch pulls CUDA wheels
    assert '-e ".[dev]"' in setup
    assert readme_commands.readme_command(text, "test") == "python -m pytest"


def test_a_missing_or_repeated_block_is_refused():
    block = '<!-- ci:test -->\n```bash\npython -m pytest\n```\n'
    assert readme_commands.readme_command(block, "test") == "python -m pytest"
    with pytest.raises(ValueError, match="exactly one"):
        readme_commands.readme_command(block + block, "test")
    with pytest.raises(ValueError, match="exactly one"):
        readme_commands.readme_command(block.replace("ci:test", "ci:tests"), "test")
    with pytest.raises(ValueError, match="found 0"):
        readme_commands.readme_command("```bash\npython -m pytest\n```\n", "setup")


def test_the_extras_tests_are_marked(request):
    from conftest import EXTRAS_TESTS

    for prefix in EXTRAS_TESTS:
        assert (ROOT / prefix.split("::")[0]).is_file(), prefix
