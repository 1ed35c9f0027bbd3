"""The public API: ``cuniform_torch`` exports exactly the names its docstring lists, each resolves, is documented
and typed, and importing the package loads none of the scripts (precompute, training, eval) nor their heavy
dependencies. The sub-packages' ``__all__`` resolve too."""

from __future__ import annotations

import importlib
import inspect
import re
import subprocess
import sys
from pathlib import Path

import pytest

import cuniform_torch

ROOT = Path(__file__).resolve().parents[1]

PUBLIC = [
    "System", "Dubins", "RandomWalk1D", "KinematicSingleTrack", "make_system", "register_system", "check_system",
    "Table", "read_table", "write_table", "load_table",
    "TablePolicy", "load_policy", "load_map_policy",
    "rollout", "rollout_actions",
    "MPPI", "LogMPPI", "CUniformMPPI", "CUMPPI", "CFUMPPI", "MPPICore", "Proposal",
    "Environment", "Circle", "Rect", "Polygon", "NavigationCost", "simulate",
]
"""the user API; a change here is a change of the API (and of the module docstring, the README and the docs)"""

SUBPACKAGES = ["systems", "grid", "tables", "policies", "sampling", "controllers", "maps", "envs"]


def _documented() -> list[str]:
    """The names the package docstring lists (its roles before "Everything else")."""
    doc = (cuniform_torch.__doc__ or "").split("Everything else")[0]
    return re.findall(r":(?:class|func):`~?([A-Za-z_][A-Za-z0-9_]*)`", doc.split("The names a user needs are here:")[1])


def test_the_exports_are_the_documented_list():
    assert cuniform_torch.__all__ == PUBLIC, "cuniform_torch.__all__ changed: update PUBLIC, the docstring, the docs"
    documented = _documented()
    assert sorted(documented) == sorted(PUBLIC), (f"docstring lists {sorted(set(documented) - set(PUBLIC))} not "
                                                  f"exported, exports {sorted(set(PUBLIC) - set(documented))} unlisted")
    assert len(documented) == len(set(documented))


def test_nothing_else_public_at_the_top():
    """``from cuniform_torch import *`` gives the list; no other public name sits in the namespace (sub-packages
    and ``__version__`` aside), so a stray import is not a silent addition to the API."""
    extra = sorted(name for name, value in vars(cuniform_torch).items()
                   if not name.startswith("_") and name not in PUBLIC and not inspect.ismodule(value))
    assert not extra, f"public names not in __all__: {extra}"
    namespace: dict = {}
    exec("from cuniform_torch import *", namespace)
    assert sorted(k for k in namespace if k != "__builtins__") == sorted(PUBLIC)


def _missing_hints(fn) -> list[str]:
    sig = inspect.signature(fn)
    missing = [p.name for p in sig.parameters.values()
               if p.name not in ("self", "cls") and p.annotation is inspect.Parameter.empty]
    if fn.__name__ != "__init__" and sig.return_annotation is inspect.Signature.empty:
        missing.append("return")
    return missing


@pytest.mark.parametrize("name", PUBLIC)
def test_each_public_name_resolves_documented_and_typed(name):
    obj = getattr(cuniform_torch, name)
    assert obj.__module__.startswith("cuniform_torch."), obj.__module__
    assert inspect.getdoc(obj), f"{name} has no docstring"
    if inspect.isfunction(obj):
        assert not _missing_hints(obj), f"{name} lacks type hints: {_missing_hints(obj)}"
        return
    assert inspect.isclass(obj), f"{name} is a {type(obj).__name__}"
    for attr, member in vars(obj).items():
        if isinstance(member, (staticmethod, classmethod)):
            member = member.__func__
        if isinstance(member, property):
            member = member.fget
        if not inspect.isfunction(member) or (attr.startswith("_") and attr != "__init__"):
            continue
        if attr == "__init__" and getattr(obj, "_is_protocol", False):
            continue  # typing's own placeholder
        assert not _missing_hints(member), f"{name}.{attr} lacks type hints: {_missing_hints(member)}"


@pytest.mark.parametrize("sub", SUBPACKAGES)
def test_each_sub_package_all_resolves(sub):
    module = importlib.import_module(f"cuniform_torch.{sub}")
    names = getattr(module, "__all__", None)
    assert names, f"cuniform_torch.{sub} has no __all__"
    assert len(names) == len(set(names)), f"cuniform_torch.{sub}.__all__ repeats a name"
    missing = [n for n in names if not hasattr(module, n)]
    assert not missing, f"cuniform_torch.{sub}.__all__ names missing attributes: {missing}"


def test_each_public_name_is_also_in_its_sub_package():
    """The top level is a shortcut: every name there is the same object as in a sub-package's ``__all__``."""
    homes = {n: sub for sub in SUBPACKAGES for n in importlib.import_module(f"cuniform_torch.{sub}").__all__}
    orphans = [n for n in PUBLIC if n not in homes]
    assert not orphans, f"public names no sub-package exports: {orphans}"
    for n in PUBLIC:
        assert getattr(importlib.import_module(f"cuniform_torch.{homes[n]}"), n) is getattr(cuniform_torch, n)


def test_importing_the_package_loads_no_script_and_nothing_heavy():
    """``import cuniform_torch`` in a fresh interpreter: no module of precompute/training/eval, and none of the
    offline tools' dependencies (matplotlib, scipy, tensorboard) a controller does not need."""
    script = ("import sys, cuniform_torch\n"
              "bad = sorted({k.split('.')[0] for k in sys.modules} & {'precompute', 'training', 'eval', 'matplotlib',"
              " 'scipy', 'tensorboard'})\n"
              "print(','.join(bad))\n")
    done = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip() == "", f"import cuniform_torch loads {done.stdout.strip()}"
