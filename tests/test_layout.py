"""The package's layout: cuniform_torch imports none of precompute/training/eval, its modules import each other
one way only (no cycle, lazy imports inside functions included), and each module imports on its own."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = "cuniform_torch"
SCRIPTS = ("precompute", "training", "eval")


def _modules(root: Path = ROOT) -> dict[str, Path]:
    """Dotted name -> file of every module of the package (a package's ``__init__.py`` is the package)."""
    out = {}
    for path in sorted((root / PACKAGE).rglob("*.py")):
        parts = path.relative_to(root).with_suffix("").parts
        out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return out


def _type_checking_only(tree: ast.AST) -> set[ast.AST]:
    """Import nodes under ``if TYPE_CHECKING:``: they never run, so they make no cycle."""
    skip: set[ast.AST] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            for child in node.body:
                skip.update(ast.walk(child))
    return skip


def import_graph(root: Path = ROOT) -> tuple[dict[str, set[str]], dict[str, set[str]]]:
    """``(edges, outside)``: the package modules each module imports (at the top or inside a function), and the
    top-level names of the other packages it imports."""
    modules = _modules(root)
    edges: dict[str, set[str]] = {name: set() for name in modules}
    outside: dict[str, set[str]] = {name: set() for name in modules}

    def resolve(dotted: str) -> str:  # the longest prefix that is a module of ours
        while dotted not in modules:
            dotted = dotted.rpartition(".")[0]
        return dotted

    for name, path in modules.items():
        tree = ast.parse(path.read_text(), str(path))
        here = name if path.name == "__init__.py" else name.rpartition(".")[0]  # the package of relative imports
        skip = _type_checking_only(tree)
        for node in ast.walk(tree):
            if node in skip:
                continue
            targets: list[str] = []
            if isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = here.rsplit(".", node.level - 1)[0] if node.level > 1 else here
                    base = f"{base}.{node.module}" if node.module else base
                else:
                    base = node.module or ""
                # `from . import models` imports the submodule; `from .grid import Grid` the module grid
                targets = [f"{base}.{alias.name}" if f"{base}.{alias.name}" in modules else base for alias in node.names]
            for target in targets:
                top = target.split(".")[0]
                if top == PACKAGE:
                    target = resolve(target)
                    if target != name:
                        edges[name].add(target)
                else:
                    outside[name].add(top)
    return edges, outside


def find_cycle(edges: dict[str, set[str]]) -> list[str] | None:
    """One import cycle ``[a, b, ..., a]``, or None."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        path.append(node)
        for nxt in sorted(edges.get(node, ())):
            if state.get(nxt) == 1:
                return path[path.index(nxt):] + [nxt]
            if nxt not in state:
                found = visit(nxt)
                if found:
                    return found
        path.pop()
        state[node] = 2
        return None

    for node in sorted(edges):
        if node not in state:
            found = visit(node)
            if found:
                return found
    return None


def test_the_runtime_library_imports_none_of_the_scripts():
    _, outside = import_graph()
    bad = {name: sorted(tops & set(SCRIPTS)) for name, tops in outside.items() if tops & set(SCRIPTS)}
    assert not bad, f"cuniform_torch must not import {SCRIPTS}: {bad}"


def test_the_package_import_graph_has_no_cycle():
    edges, _ = import_graph()
    cycle = find_cycle(edges)
    assert cycle is None, "import cycle: " + " -> ".join(cycle)
    assert edges["cuniform_torch.common.frames"] == {"cuniform_torch.common.checks"}  # systems -> frames, never back
    assert "cuniform_torch.common.frames" in edges["cuniform_torch.systems.protocol"]


def test_a_planted_cycle_is_found(tmp_path):
    """The check itself: a copy of the package where checks.py imports systems (which imports checks) fails."""
    subprocess.run(["cp", "-r", str(ROOT / PACKAGE), str(tmp_path / PACKAGE)], check=True)
    checks = tmp_path / PACKAGE / "checks.py"
    checks.write_text(checks.read_text() + "\n\ndef _late():\n    from .systems import make_system  # noqa: F401\n")
    cycle = find_cycle(import_graph(tmp_path)[0])
    assert cycle is not None and cycle[0] == cycle[-1] and "cuniform_torch.common.checks" in cycle


def test_every_module_imports_on_its_own():
    """Each module first, with none of the package loaded before it (torch is imported once, for speed): an
    import-order dependence or a cycle that bites at import time fails here, naming the module."""
    names = sorted(_modules())
    script = (
        "import importlib, sys, torch\n"
        f"for name in {names!r}:\n"
        f"    for key in [k for k in sys.modules if k == {PACKAGE!r} or k.startswith({PACKAGE + '.'!r})]:\n"
        "        del sys.modules[key]\n"
        "    try:\n"
        "        importlib.import_module(name)\n"
        "    except Exception as exc:\n"
        "        sys.exit(f'importing {name} first fails: {type(exc).__name__}: {exc}')\n"
        f"    loaded = sorted(k for k in sys.modules if k.split('.')[0] in {SCRIPTS!r})\n"
        "    if loaded:\n"
        "        sys.exit(f'importing {name} loads {loaded}')\n"
    )
    done = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
