"""The navigation benchmark's layering in numbers: the longest import chain among ``eval/navigate`` modules, the
lines of each part, and what importing the records costs.

    python .ci/nav_layers.py [ROOT]     (ROOT: a checkout, default the current folder)

Before the records layer (issue 35 item 4), on the commit it started from:
``mkdir -p /tmp/base && git archive d8f3f1a eval precompute cuniform_torch | tar -x -C /tmp/base &&
python .ci/nav_layers.py /tmp/base``. Imports are read with ``ast``: the chain of top-level imports, and of all
imports (in functions too, as ``tests/test_layout.py`` counts them). The records module is
``eval.navigate.records`` where it exists, else ``eval.navigate.store`` (what the reports read records with
before); its import time is the median of 5 fresh interpreters, with the 1-minute load beside it.
"""

from __future__ import annotations

import ast
import functools
import os
import statistics
import subprocess
import sys
from pathlib import Path

PARTS = {
    "records": ("records",),
    "runner": ("run", "episode", "execute", "robot_files", "cost_to_go", "dynamics", "gym_env"),
    "reports": ("results", "budget", "compare", "failures", "replay", "figures", "score"),
    "commands": ("__init__", "__main__", "commands", "subcommands"),
}
"""the parts (module names under eval/navigate; ``records`` the package), as the records layer splits them"""


def modules(root: Path) -> dict[str, Path]:
    pkg = root / "eval" / "navigate"
    return {".".join(p.relative_to(root).with_suffix("").parts).removesuffix(".__init__"): p for p in pkg.rglob("*.py")}


def imports(path: Path, known: dict[str, Path], top_only: bool) -> set[str]:
    tree = ast.parse(path.read_text())
    out = set()
    for node in (tree.body if top_only else ast.walk(tree)):
        if isinstance(node, ast.ImportFrom) and node.module:
            names = [node.module]
        elif isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        else:
            continue
        for name in names:
            while name and name not in known:
                name = name.rpartition(".")[0]
            if name and name != "eval.navigate":
                out.add(name)
    return out


def longest_chain(root: Path, top_only: bool) -> tuple[str, ...]:
    known = modules(root)
    graph = {m: imports(p, known, top_only) - {m} for m, p in known.items()}

    @functools.cache
    def chain(m: str) -> tuple[str, ...]:
        return (m, *max((chain(d) for d in graph[m]), key=len, default=()))

    return max((chain(m) for m in graph), key=len)


def import_time(root: Path, module: str) -> tuple[float, bool]:
    code = f"import sys, time; t = time.perf_counter(); import {module}; print(time.perf_counter() - t, 'torch' in sys.modules)"
    runs = [subprocess.run([sys.executable, "-c", code], cwd=root, capture_output=True, text=True,
                           check=True).stdout.split() for _ in range(5)]
    return 1000 * statistics.median(float(r[0]) for r in runs), runs[0][1] == "True"


def main() -> int:
    root = Path(sys.argv[1] if len(sys.argv) > 1 else ".").resolve()
    known = modules(root)
    for top_only in (True, False):
        chain = longest_chain(root, top_only)
        print(f"longest chain of {'top-level' if top_only else 'all'} imports: {len(chain) - 1} edges: "
              + " -> ".join(m.removeprefix("eval.navigate.") for m in chain))
    print(f"{len(known)} modules, {sum(len(p.read_text().splitlines()) for p in known.values())} lines")
    if (root / "eval" / "navigate" / "records").is_dir():
        for part, names in PARTS.items():
            paths = [p for m, p in known.items() if m.removeprefix("eval.navigate.").split(".")[0] in names
                     or (m == "eval.navigate" and "__init__" in names)]
            print(f"  {part}: {len(paths)} modules, {sum(len(p.read_text().splitlines()) for p in paths)} lines")
    module = "eval.navigate.records" if "eval.navigate.records" in known else "eval.navigate.store"
    load = os.getloadavg()[0]
    ms, torch = import_time(root, module)
    print(f"import {module}: {ms:.0f} ms (median of 5), torch loaded: {torch} (1-min load {load:.1f})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
