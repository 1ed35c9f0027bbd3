"""The project's layout: the layers import only down, no module import cycle, a layered tree of sub-packages, and
each module imports on its own.

* Layers: ``cuniform_torch`` <- ``precompute`` <- ``training`` <- ``eval``; a module imports nothing of a package
  above its own (tests and docs are outside the layers).
* No import cycle between modules, counting every import: top-level, inside a function, and under
  ``if TYPE_CHECKING:`` (a type-only cycle still ties two modules together: neither can move or be read alone).
  ``from X import name`` where ``X.name`` is a module imports that module; importing ``a.b.c`` from outside the
  package ``a.b`` also runs ``a/b/__init__.py``, so it counts as importing that package too.
* Inside each package, its sub-packages and top-level modules (each one node) form a DAG too, so the tree stays
  layered (``controllers`` may use ``envs``, never the other way round).
* The runtime (``cuniform_torch``) imports no ``argparse``: the commands' plumbing lives in ``precompute.cli``.

The checks read the source (``ast``), so they see imports that a run never reaches. The planted-bug tests run the
same checks on a copy of the tree with one bad import added, so each rule is shown to fail.
"""

from __future__ import annotations

import ast
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LAYERS = ("cuniform_torch", "precompute", "training", "eval")
"""the packages, lowest first: each may import those before it, never those after it"""
OPTIONAL_EXTRAS = ("gymnasium", "ray", "pytorch_mppi")
"""packages of optional extras: a module that needs one is not imported when it is absent"""

Edges = dict[str, dict[str, str]]
"""module -> {imported module: "file:line" of the first import of it}"""


# ------------------------------------------------------------------------------------------ the graph

def _modules(root: Path = ROOT) -> dict[str, Path]:
    """Dotted name -> file of every module of the layers (a package's ``__init__.py`` is the package)."""
    out = {}
    for layer in LAYERS:
        for path in sorted((root / layer).rglob("*.py")):
            parts = path.relative_to(root).with_suffix("").parts
            out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return out


def _packages(modules: dict[str, Path]) -> set[str]:
    return {name for name, path in modules.items() if path.name == "__init__.py"}


def _imported_names(node: ast.AST, here: str, modules: dict[str, Path]) -> list[str]:
    """The dotted names one node imports (before resolving to modules); ``here`` is the package of relative imports."""
    if isinstance(node, ast.Import):
        return [alias.name for alias in node.names]
    if isinstance(node, ast.ImportFrom):
        if node.level:
            base = here.rsplit(".", node.level - 1)[0] if node.level > 1 else here
            base = f"{base}.{node.module}" if node.module else base
        else:
            base = node.module or ""
        # `from pkg import sub` imports the module pkg.sub; `from pkg.mod import name` the module pkg.mod
        return [f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base for a in node.names]
    if isinstance(node, ast.Call) and node.args and isinstance(node.args[0], ast.Constant) \
            and isinstance(node.args[0].value, str) and ast.unparse(node.func) in ("importlib.import_module",
                                                                                   "import_module", "__import__"):
        return [node.args[0].value]  # a literal dynamic import is an import too
    return []


def import_graph(root: Path = ROOT) -> Edges:
    """The modules each module of the layers imports: at the top, in a function, or under ``TYPE_CHECKING``."""
    modules = _modules(root)
    packages = _packages(modules)
    edges: Edges = {name: {} for name in modules}

    def resolve(dotted: str) -> str | None:  # the longest prefix that is one of our modules
        while dotted and dotted not in modules:
            dotted = dotted.rpartition(".")[0]
        return dotted or None

    for name, path in modules.items():
        tree = ast.parse(path.read_text(), str(path))
        here = name if path.name == "__init__.py" else name.rpartition(".")[0]
        for node in ast.walk(tree):
            for dotted in _imported_names(node, here, modules):
                target = resolve(dotted)
                if target is None:
                    continue  # another project's module
                # the packages above the target that the importer is not inside of run their __init__ first
                parts = target.split(".")
                runs = [".".join(parts[:i]) for i in range(1, len(parts))]
                runs = [p for p in runs if p in packages and not (name == p or name.startswith(p + "."))]
                for hit in [*runs, target]:
                    if hit != name:
                        edges[name].setdefault(hit, f"{path.relative_to(root)}:{node.lineno}")  # type: ignore[attr-defined]
    return edges


def strongly_connected(edges: dict[str, set[str]] | Edges) -> list[list[str]]:
    """The import cycles: every strongly connected component with more than one node, each sorted (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(edges.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.append(sorted(comp))

    sys.setrecursionlimit(max(sys.getrecursionlimit(), 10_000))
    for v in sorted(edges):
        if v not in index:
            visit(v)
    return sorted(found)


def _describe(comp: list[str], edges: Edges) -> str:
    members = set(comp)
    lines = [f"  {a} -> {b}  ({w})" for a in comp for b, w in sorted(edges.get(a, {}).items()) if b in members]
    return " <-> ".join(comp) + "\n" + "\n".join(lines)


def layer_violations(edges: Edges) -> list[str]:
    """Every import of a package above the importer's own layer."""
    rank = {layer: i for i, layer in enumerate(LAYERS)}
    return [f"{a} imports {b}  ({w})" for a, out in sorted(edges.items()) for b, w in sorted(out.items())
            if rank[b.split(".")[0]] > rank[a.split(".")[0]]]


RUNTIME_REFUSES = ("argparse",)
"""standard-library modules no runtime module imports: flags are the command layers' (``precompute.cli``)"""


def runtime_refused_imports(root: Path = ROOT) -> list[str]:
    """Every import of :data:`RUNTIME_REFUSES` by a ``cuniform_torch`` module (any form: plain, ``from``, in a
    function, a literal ``import_module``), as ``module imports name  (file:line)``."""
    modules = _modules(root)
    found = []
    for name, path in modules.items():
        if name.split(".")[0] != LAYERS[0]:
            continue
        here = name if path.name == "__init__.py" else name.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            for dotted in _imported_names(node, here, modules):
                if dotted.split(".")[0] in RUNTIME_REFUSES:
                    found.append(f"{name} imports {dotted}  ({path.relative_to(root)}:{node.lineno})")  # type: ignore[attr-defined]
    return found


def module_cycles(edges: Edges) -> list[str]:
    """The module import cycles, each with the imports that make it."""
    return [_describe(comp, edges) for comp in strongly_connected(edges)]


def subpackage_cycles(edges: Edges, root: Path = ROOT) -> list[str]:
    """For each package, the cycles between its children (sub-packages and top-level modules, one node each); a
    cycle of top-level modules only is a module cycle, left to :func:`module_cycles`."""
    out = []
    packages = _packages(_modules(root))
    for package in sorted(packages):
        def child(module: str, package: str = package) -> str | None:
            if module == package:
                return package  # the package's own __init__
            if not module.startswith(package + "."):
                return None
            return f"{package}.{module[len(package) + 1:].split('.')[0]}"

        graph: Edges = {}
        for a, targets in edges.items():
            for b, where in targets.items():
                ca, cb = child(a), child(b)
                if ca and cb and ca != cb:
                    graph.setdefault(ca, {}).setdefault(cb, where if (ca, cb) == (a, b) else f"{a} -> {b}, {where}")
        out += [f"inside {package}: {_describe(comp, graph)}" for comp in strongly_connected(graph)
                if any(node in packages for node in comp)]
    return out


# ------------------------------------------------------------------------------------------ the rules

def test_no_module_imports_a_layer_above_its_own():
    bad = layer_violations(import_graph())
    assert not bad, f"the layers are {' <- '.join(LAYERS)}; these import up:\n" + "\n".join(bad)


def test_no_import_cycle_between_modules():
    cycles = module_cycles(import_graph())
    assert not cycles, "import cycles (function-level and TYPE_CHECKING imports count):\n" + "\n".join(cycles)


def test_the_sub_packages_of_each_package_form_a_dag():
    cycles = subpackage_cycles(import_graph())
    assert not cycles, "sub-packages that import each other:\n" + "\n".join(cycles)


def test_the_runtime_imports_no_argparse():
    """Issue 35: the command plumbing (flags, exit codes) lives in precompute.cli, not in the runtime."""
    bad = runtime_refused_imports()
    assert not bad, "the runtime (cuniform_torch) parses no flags; move this to precompute.cli:\n" + "\n".join(bad)


def test_the_graph_sees_each_kind_of_import():
    """The reader itself, on imports that exist today: a plain one, one inside a function, a package's __init__."""
    edges = import_graph()
    assert edges["cuniform_torch.common.frames"].keys() == {"cuniform_torch.common.checks"}  # systems -> frames only
    assert "cuniform_torch.common.frames" in edges["cuniform_torch.systems.protocol"]
    assert "cuniform_torch.systems" in edges["cuniform_torch.controllers.core"]  # `from cuniform_torch.systems import`
    assert "cuniform_torch.controllers.result" in edges["cuniform_torch.controllers.bank"]


# ------------------------------------------------------------------------------------------ planted bugs

def _copy_tree(tmp_path: Path) -> Path:
    """The layers' python files, copied (data files are not read by the checks)."""
    for layer in LAYERS:
        shutil.copytree(ROOT / layer, tmp_path / layer, ignore=lambda d, names: [
            n for n in names if n == "__pycache__" or not (n.endswith(".py") or (Path(d) / n).is_dir())])
    return tmp_path


def _plant(root: Path, module: str, code: str) -> None:
    path = root / (module.replace(".", "/") + ".py")
    path.write_text(path.read_text() + "\n\n" + code + "\n")


PLANTS = {
    "function-level cycle": ("cuniform_torch.controllers.checks",
                             "def _late():\n    from cuniform_torch.controllers.mppi import MPPI  # noqa: F401",
                             "cycle", {"cuniform_torch.controllers.checks", "cuniform_torch.controllers.mppi"}),
    "TYPE_CHECKING cycle": ("cuniform_torch.controllers.result",
                            "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n"
                            "    from cuniform_torch.controllers.core import MPPICore  # noqa: F401",
                            "cycle", {"cuniform_torch.controllers.result", "cuniform_torch.controllers.core"}),
    "from-package-import-module cycle": ("cuniform_torch.common.checks",
                                         "def _late():\n    from cuniform_torch.systems import models  # noqa: F401",
                                         "cycle", {"cuniform_torch.common.checks", "cuniform_torch.systems.models"}),
    # no module cycle (barn_format imports nothing, maps.dataset no world), but precompute.maps uses
    # precompute.worlds, which now uses precompute.maps
    "sub-package cycle": ("precompute.worlds.barn_format",
                          "def _late():\n    from precompute.maps import dataset  # noqa: F401",
                          "subpackage", {"precompute.worlds", "precompute.maps"}),
    "import up": ("cuniform_torch.grid.cells",
                  "def _late():\n    import eval.common.paths  # noqa: F401", "layer", {"eval.common.paths"}),
    "import up by a literal import_module": ("precompute.flow.maxflow",
                                             "def _late():\n    import importlib\n"
                                             "    importlib.import_module('training.tables.loop')",
                                             "layer", {"training.tables.loop"}),
}


@pytest.mark.parametrize("plant", sorted(PLANTS))
def test_a_planted_bad_import_is_found(tmp_path, plant):
    """The checks on a copy of the tree with one bad import added: each rule catches its own kind."""
    module, code, rule, names = PLANTS[plant]
    root = _copy_tree(tmp_path)
    edges = import_graph(root)
    assert not module_cycles(edges) and not subpackage_cycles(edges, root) and not layer_violations(edges)
    _plant(root, module, code)
    edges = import_graph(root)
    found = {"cycle": module_cycles, "subpackage": lambda e: subpackage_cycles(e, root),
             "layer": layer_violations}[rule](edges)
    assert found, f"{plant} in {module} was not found"
    if rule == "subpackage":
        assert not module_cycles(edges), "the planted sub-package cycle should not be a module cycle"
    assert any(all(n in report for n in names) for report in found), found


@pytest.mark.parametrize("code", ["import argparse", "def _late():\n    from argparse import ArgumentParser  # noqa: F401"])
def test_a_planted_argparse_import_in_the_runtime_is_found(tmp_path, code):
    root = _copy_tree(tmp_path)
    assert not runtime_refused_imports(root)
    _plant(root, "cuniform_torch.grid.cells", code)
    found = runtime_refused_imports(root)
    assert len(found) == 1 and found[0].startswith("cuniform_torch.grid.cells imports argparse"), found


# ------------------------------------------------------------------------------------------ at run time

def test_every_module_imports_on_its_own():
    """Each module first, with none of the project loaded before it (torch, numpy, matplotlib stay loaded, for
    speed): an import-order dependence or a cycle that bites at import time fails here, naming the module; so
    does a module that loads a layer above its own. A module that needs an absent optional extra is skipped."""
    names = sorted(name for name in _modules() if not name.endswith(".__main__"))  # a __main__ runs its program
    script = (
        "import importlib, sys, torch, numpy, matplotlib\n"
        "matplotlib.use('Agg')\n"
        f"layers, extras = {LAYERS!r}, {OPTIONAL_EXTRAS!r}\n"
        f"for name in {names!r}:\n"
        "    for key in [k for k in sys.modules if k.split('.')[0] in layers]:\n"
        "        del sys.modules[key]\n"
        "    try:\n"
        "        importlib.import_module(name)\n"
        "    except ImportError as exc:\n"
        "        if any(x in str(exc) or x in str(exc.__cause__) or exc.name == x for x in extras):\n"
        "            continue\n"
        "        sys.exit(f'importing {name} first fails: {type(exc).__name__}: {exc}')\n"
        "    except Exception as exc:\n"
        "        sys.exit(f'importing {name} first fails: {type(exc).__name__}: {exc}')\n"
        "    above = layers[layers.index(name.split('.')[0]) + 1:]\n"
        "    loaded = sorted(k for k in sys.modules if k.split('.')[0] in above)\n"
        "    if loaded:\n"
        "        sys.exit(f'importing {name} loads {loaded}')\n"
    )
    done = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, (done.stdout + done.stderr)[-2000:]


# ------------------------------------------------------------------------------------------ the docs' graph

_LEFT_OUT = ("cuniform_torch.common", "precompute.cli")
"""nodes almost every module imports: left out of the docs' graph to keep it readable (the page says so)"""


def _node(module: str, packages: set[str]) -> str:
    """The docs' node of a module: its package at most two levels below the layer (``eval.navigate``),
    a top-level module itself, the layer's ``__init__`` the layer."""
    parts = module.split(".")
    for depth in (3, 2):
        if len(parts) > depth and ".".join(parts[:depth]) in packages:
            return ".".join(parts[:depth])
    return ".".join(parts[:2]) if len(parts) >= 2 else module


def architecture_mermaid(root: Path = ROOT) -> str:
    """The mermaid block of ``docs/architecture.md``: one node per sub-package or top-level module, an edge
    ``A --> B`` when a module of A imports a module of B directly (any import; the package ``__init__`` files an
    import runs on the way are not edges), :data:`_LEFT_OUT` left out."""
    modules = _modules(root)
    packages = _packages(modules)
    edges: set[tuple[str, str]] = set()
    nodes: set[str] = set()
    for name, path in modules.items():
        src = _node(name, packages)
        if src in _LEFT_OUT or name.endswith(".__main__") and src == name.rpartition(".")[0] == name.split(".")[0]:
            continue
        if src.count(".") or src == "cuniform_torch":
            nodes.add(src)
        here = name if path.name == "__init__.py" else name.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            for dotted in _imported_names(node, here, modules):
                while dotted and dotted not in modules:
                    dotted = dotted.rpartition(".")[0]
                if not dotted:
                    continue
                dst = _node(dotted, packages)
                if dst != src and dst not in _LEFT_OUT and (dst.count(".") or dst == "cuniform_torch"):
                    edges.add((src, dst))
    ident = {n: n.replace(".", "_") for n in nodes}
    lines = ["```mermaid", "flowchart LR"]
    for i, layer in enumerate(LAYERS):
        lines.append(f'    subgraph L{i}["{layer}"]')
        for n in sorted(x for x in nodes if x.split(".")[0] == layer):
            label = "__init__ (public API)" if n == layer else n.split(".", 1)[1]
            lines.append(f'        {ident[n]}["{label}"]')
        lines.append("    end")
    lines += [f"    {ident[a]} --> {ident[b]}" for a, b in sorted(edges) if a in ident and b in ident]
    lines.append("```")
    return "\n".join(lines)


def test_the_architecture_page_draws_the_real_import_graph():
    """docs/architecture.md's mermaid graph is the one the source has (regenerate: python tests/test_layout.py)."""
    page = (ROOT / "docs" / "architecture.md").read_text()
    start = page.index("```mermaid")
    drawn = page[start:page.index("```", start + 3) + 3]
    assert drawn == architecture_mermaid(), "docs/architecture.md's import graph is stale: run python tests/test_layout.py"


if __name__ == "__main__":  # rewrite the graph of docs/architecture.md from the source
    page_path = ROOT / "docs" / "architecture.md"
    text = page_path.read_text()
    begin = text.index("```mermaid")
    end = text.index("```", begin + 3) + 3
    page_path.write_text(text[:begin] + architecture_mermaid() + text[end:])
    print(f"wrote the import graph of {page_path}")
