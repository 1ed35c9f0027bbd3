"""Building C-Uniform tables: level sets, max-flow and coverage builders, table sets and map-table farms.

The library's building jobs are importable from here (:mod:`precompute.api`)::

    from precompute import BuildConfig, CoverageConfig, SetConfig, build_table, build_table_set

They load on first use, so ``python -m precompute.<command>`` does not import them before its own flags are read.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from precompute.startup import install_when_run_as_command

install_when_run_as_command()  # python -m ...: Ctrl-C during the imports is one line and exit 130

if TYPE_CHECKING:
    from precompute.api import BuildConfig, CoverageConfig, SetConfig, build_table, build_table_set

__all__ = ["BuildConfig", "CoverageConfig", "SetConfig", "build_table", "build_table_set"]


def __getattr__(name: str) -> Any:
    """The public names of :mod:`precompute.api`, imported on first use."""
    if name in __all__:
        import precompute.api

        return getattr(precompute.api, name)
    raise AttributeError(f"module 'precompute' has no attribute {name!r}")
