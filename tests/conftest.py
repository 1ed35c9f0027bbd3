"""Shared fixtures: small seeded tables built once per session."""

from __future__ import annotations

import pytest

from cuniform_torch.systems import make_system
from precompute.flow.builder import BuildConfig, build_table


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


@pytest.fixture
def start_warnings():
    """``start_warnings(policy, x0, n=300)``: the StartMismatchWarnings of one seeded rollout from ``x0`` (the
    policy's counters reset first, so ``policy.miss_rate`` is that rollout's)."""
    import warnings

    import torch

    from cuniform_torch import rollout
    from cuniform_torch.sampling import StartMismatchWarning

    def run(policy, x0, n: int = 300) -> list:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            policy.reset_counters()
            rollout(policy.system, policy, torch.tensor(x0), n, policy.horizon, torch.Generator().manual_seed(0))
        return [w for w in caught if issubclass(w.category, StartMismatchWarning)]

    return run


@pytest.fixture(scope="module")
def restore_threads():
    """A module that calls a training ``main`` (which sets torch's thread count, ``--threads``) gives the other
    test modules theirs back."""
    import torch

    threads = torch.get_num_threads()
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="session")
def train_capturing():
    """``train_capturing(module, main, argv)``: run ``main(argv)`` (asserting it returns 0) with
    ``module.policy_checkpoint`` wrapped; the trained policy module it checkpointed."""

    def run(module, main, argv):
        captured = {}
        original = module.policy_checkpoint

        def capture(policy, *args, **kwargs):
            captured["module"] = policy
            return original(policy, *args, **kwargs)

        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(module, "policy_checkpoint", capture)
            assert main(argv) == 0
        return captured["module"]

    return run



@pytest.fixture(scope="module")
def small_table():
    """A small valid Dubins table (levels 1, 5, 13, 25: ``hardening_helpers.HORIZON``), built once per module."""
    from hardening_helpers import HORIZON

    table, _ = build_table(make_system("dubins"), BuildConfig(horizon=HORIZON))
    return table


@pytest.fixture(scope="module")
def small_policy(small_table):
    """A TablePolicy of ``small_table``, one per module (its miss counters are the module's own)."""
    from cuniform_torch.policies.table import TablePolicy

    return TablePolicy(small_table)


@pytest.fixture()
def evil(tmp_path, monkeypatch):
    """A module next to the table, on sys.path and in the working directory, that leaves markers when it is
    imported or its factory is called: ``(module name, {"import": path, "call": path})``."""
    import sys
    import uuid

    from hardening_helpers import EVIL_MODULE

    from cuniform_torch.systems.registry import _REGISTRY

    name = f"evil_{uuid.uuid4().hex[:8]}"
    markers = {"import": tmp_path / "imported", "call": tmp_path / "called"}
    (tmp_path / f"{name}.py").write_text(EVIL_MODULE.format(import_marker=str(markers["import"]),
                                                          call_marker=str(markers["call"])))
    monkeypatch.chdir(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))
    yield name, markers
    sys.modules.pop(name, None)
    _REGISTRY.pop("evil_car", None)


@pytest.fixture(scope="module")
def walk_path(tmp_path_factory):
    """A tiny random-walk table (2 levels) written by ``python -m precompute.build``, once per module."""
    from hardening_helpers import _build

    import precompute.build as build

    out = tmp_path_factory.mktemp("tables") / "walk.npz"
    assert build.main(_build(out)) == 0
    return out


EXTRAS_TESTS = (
    "tests/test_gym_env.py::",
    "tests/test_mountain_car.py::",
    "tests/test_classic_systems.py::test_mountain_car_is_the_gymnasium_env_step_for_step",
    "tests/test_docs.py::test_readme_gymnasium_example_runs",
    "tests/test_table_set.py::test_ray_set_is_the_same_tables",
    "tests/test_navigate.py::test_serial_workers_and_ray_give_the_same_episodes",
)
"""the tests of the optional extras (gymnasium, ray, pytorch-mppi): each skips with its reason when the extra is
absent; CI runs them again with the extras installed (``pytest -m extras``)"""


def pytest_collection_modifyitems(config, items):
    for item in items:
        if item.nodeid.startswith(EXTRAS_TESTS):
            item.add_marker(pytest.mark.extras)
