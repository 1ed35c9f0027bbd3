"""No tests here: kept for the imports of tests/test_build_commands.py, tests/test_entry_points.py and
tests/test_nav_replay.py (``from test_cli_errors import _call, _one_error``). The tests that were here are in
tests/test_entry_build.py, tests/test_entry_distill.py, tests/test_entry_eval.py and tests/test_files_shared.py; the
helpers are in tests/hardening_helpers.py. Delete this file once those three import from there."""

from hardening_helpers import _call, _one_error

__all__ = ["_call", "_one_error"]
