"""Where the evaluation reads and writes: every ``out/...`` and ``runs/...`` default of ``eval`` in one place.

:class:`OutputPaths` names the files under one output folder (``out/`` by default, ``precompute.cli.OUT``):
the tables and the distilled policy the experiments read, their JSON results, the figures and the report.
``python -m eval.report --out DIR`` uses ``OutputPaths(DIR)`` (``--quick``: ``OutputPaths(DIR / "quick",
quick=True)``); every experiment's ``--table`` / ``--coverage-table`` / ``--policy`` defaults to
:data:`DEFAULT`'s files, so a report run leaves exactly what the experiments read by default.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from precompute.cli import OUT, RUNS

__all__ = ["OutputPaths", "DEFAULT", "RUNS_EVAL"]

RUNS_EVAL = RUNS / "eval"
"""TensorBoard runs of ``python -m eval.report`` (one per method, plus ``figures`` and ``distill``)"""


@dataclass(frozen=True)
class OutputPaths:
    """The files of one evaluation output folder."""

    root: Path = OUT
    quick: bool = False
    """the quick report's layout: the closed loop on the 2 s tables, a policy distilled from the 2 s table"""

    @property
    def table(self) -> Path:
        """the default Dubins table (max-flow, T = 10 steps = 2 s): coverage and uniformity experiments"""
        return self.root / "dubins.npz"

    @property
    def coverage_table(self) -> Path:
        """the same preset built by ``--method coverage``"""
        return self.root / "dubins_cov.npz"

    @property
    def table_cl(self) -> Path:
        """the closed-loop max-flow table: horizon 15 (3 s, the paper's controller horizon); quick: the 2 s one"""
        return self.table if self.quick else self.root / "dubins15.npz"

    @property
    def coverage_table_cl(self) -> Path:
        return self.coverage_table if self.quick else self.root / "dubins15_cov.npz"

    @property
    def policy(self) -> Path:
        """the MLP distilled from ``table_cl`` (its first 10 levels are ``table``'s): every experiment's
        ``cu_mlp``"""
        return self.root / ("dubins.policy.pt" if self.quick else "dubins15.policy.pt")

    @property
    def results(self) -> Path:
        """folder of the experiments' JSON results"""
        return self.root / "eval"

    def result(self, experiment: str) -> Path:
        return self.results / f"{experiment}.json"

    @property
    def figures(self) -> Path:
        return self.root / "figures"

    @property
    def report(self) -> Path:
        return self.root / "report.md"

    def bench_table(self, horizon: int) -> Path:
        """a Dubins table of ``horizon`` steps that ``python -m eval.bench`` builds when missing"""
        return self.root / f"dubins_h{horizon}.npz"

    @property
    def bench_json(self) -> Path:
        return self.root / "bench.json"


DEFAULT = OutputPaths()
