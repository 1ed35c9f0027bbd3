"""Shared fixtures: small seeded tables built once per session."""

from __future__ import annotations

import pytest

from cuniform_torch.systems import make_system
from precompute.builder import BuildConfig, build_table


@pytest.fixture(scope="session")
def dubins_table():
    """The default Dubins table (10 levels, built in well under a second)."""
    table, _ = build_table(make_system("dubins"), BuildConfig(horizon=10))
    return table


@pytest.fixture(scope="session")
def walk_table():
    """The default 1-D random walk table, 8 levels."""
    table, _ = build_table(make_system("random_walk_1d"), BuildConfig(horizon=8))
    return table
