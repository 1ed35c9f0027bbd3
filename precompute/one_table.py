"""One table, built and written: :class:`TableJob` (the typed job of ``python -m precompute.build maxflow``,
``coverage`` or ``safe``) and :func:`build_table_file` / :func:`run_table_job`, what the library's
:func:`precompute.build_table` (and so the command), the table set (one job per member start,
:mod:`precompute.table_set`) and the evaluations call.
"""

from __future__ import annotations

import dataclasses
import math
import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cuniform_torch.common.fileio import exclusive_lock, write_json
from cuniform_torch.systems import System
from cuniform_torch.tables.file import Table, write_table
from precompute.cli import CLIError, check_output_file
from precompute.coverage.method import CoverageConfig
from precompute.flow.builder import BuildConfig, SizeGuide, available_memory_bytes, build_table, check_resume
from precompute.report import format_report, uniformity_report

__all__ = ["TableJob", "build_table_file", "run_table_job", "check_device"]


@dataclass(frozen=True)
class TableJob:
    """One table to build and write (every field has the meaning of the ``precompute.build`` flag of its name)."""

    system: System
    out: Path
    """the table file (``.npz``) to write; ``<out stem>.report.json`` is written beside it"""
    build: BuildConfig = dataclasses.field(default_factory=BuildConfig)
    """horizon, points, seed, ties, start, local map: everything that changes a max-flow table's bytes"""
    coverage: CoverageConfig | None = None
    """the coverage method's settings (``--method coverage``); None: the max-flow method"""
    report: bool = True
    """measure the table's uniformity on real rollouts and print it (``--no-report``: False)"""
    rollouts: int | None = None
    """rollouts of the report (None: 10 x the largest level)"""
    device: str = "cpu"
    """torch device of the report's rollouts"""
    resume: bool = False
    """continue an interrupted max-flow build from ``<out>.partial/``"""
    max_memory_gb: float | None = None
    """memory budget of the size guidance (None: the available memory)"""
    quiet: bool = False
    """no progress bar and no report printed (warnings still are)"""

    def __post_init__(self) -> None:
        object.__setattr__(self, "out", Path(self.out))
        if self.coverage is not None:
            if self.coverage.horizon != self.build.horizon:
                raise ValueError(f"the coverage config's horizon {self.coverage.horizon} differs from the build's "
                                 f"{self.build.horizon}")
            if self.resume:
                raise ValueError("--resume continues a max-flow build; the coverage method has no checkpoints")
        if self.max_memory_gb is not None and not (math.isfinite(self.max_memory_gb) and self.max_memory_gb > 0):
            raise ValueError(f"--max-memory must be a positive number of GB, got {self.max_memory_gb}")
        if self.rollouts is not None and (isinstance(self.rollouts, bool) or self.rollouts < 1):
            raise ValueError(f"--rollouts must be positive, got {self.rollouts}")
        if self.rollouts is not None and not self.report:
            raise ValueError("--rollouts sets the report's rollouts, but --no-report skips the report")

    @property
    def method(self) -> str:
        """``"maxflow"`` or ``"coverage"``."""
        return "maxflow" if self.coverage is None else "coverage"

    def from_start(self, start: tuple[float, ...], out: Path) -> TableJob:
        """This job built from ``start`` into ``out``, quietly and without a report (a member of a table set)."""
        build = dataclasses.replace(self.build, start=start)
        coverage = None if self.coverage is None else dataclasses.replace(self.coverage, start=start)
        return dataclasses.replace(self, build=build, coverage=coverage, out=Path(out), report=False, rollouts=None,
                                   quiet=True)


def check_device(device: str) -> None:
    """A clear ValueError unless ``device`` names a torch device this machine has."""
    import torch

    try:
        dev = torch.device(device)
    except RuntimeError:
        raise ValueError(f"--device {device!r} is not a torch device (cpu, cuda, cuda:1, ...)") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"--device {device}: CUDA is not available on this machine")


def _build_coverage(system, config, bar):
    """The coverage method (precompute/coverage/method.py), with the bar counting levels, then iterations."""
    from precompute.coverage.method import build_coverage_table
    from precompute.flow.builder import BuildStats

    if bar is not None:
        bar.reset(total=config.horizon + config.steps)
        bar.set_description("levels, then ascent")

    def progress(stage: str, i: int, value: float) -> None:
        if bar is not None:
            bar.set_postfix({"states" if stage == "enumerate" else "objective": f"{value:.0f}"})
            bar.update(1)

    table, facts = build_coverage_table(system, config, progress)
    if bar is not None and bar.n < bar.total:  # the ascent stopped early (--tol): the bar ends full, not short
        bar.total = bar.n
        bar.refresh()
    stats = BuildStats(seconds={**facts["seconds"], "write": 0.0})
    return table, stats, {"coverage_method": {k: v for k, v in facts.items() if k != "seconds"}}


def build_table_file(job: TableJob) -> Path:
    """Build the table ``job`` describes, write it (atomically) and its report JSON; return the table's path.
    A bad setting, an unusable ``out`` or a refused resume is a ValueError / CLIError; Ctrl-C a KeyboardInterrupt
    saying what survives."""
    run_table_job(job)
    return job.out


def run_table_job(job: TableJob) -> Table:
    """:func:`build_table_file`, returning the table it wrote (what :func:`precompute.build_table` returns)."""
    check_output_file(job.out, "--out", example="table.npz")
    if job.report:
        check_device(job.device)
    with exclusive_lock(job.out.with_name(job.out.name + ".lock"), what=f"--out {job.out}"):
        return _build(job)


def _build(job: TableJob) -> Table:
    """Build, write and report, holding the lock of ``job.out``."""
    system, config, coverage_config, out = job.system, job.build, job.coverage, job.out
    horizon = config.horizon
    ckpt = out.with_name(out.name + ".partial")
    if ckpt.exists() and not job.resume:
        shutil.rmtree(ckpt)
    if job.method == "maxflow":
        if job.resume and ckpt.is_dir():
            check_resume(ckpt, system, config)
        ckpt.mkdir(parents=True, exist_ok=True)
    say = (lambda *a: None) if job.quiet else (lambda *a: print(*a, flush=True))
    detail = (f"points={config.points.value}" if coverage_config is None
              else f"target N={coverage_config.target_samples}")
    say(f"building {system.name} table ({job.method}): {system.params()} horizon={horizon} {detail}")

    bar = None
    if not job.quiet:
        from tqdm import tqdm

        bar = tqdm(total=horizon, desc="levels", unit="level", file=sys.stdout)

    budget = job.max_memory_gb * 1e9 if job.max_memory_gb is not None else available_memory_bytes()
    guide = SizeGuide(horizon, system.action_set().shape[0], len(system.periodic), budget, report=job.report)

    def progress(t: int, step) -> None:
        for line in guide.update(step):
            loud = line.startswith(("warning", "the projection now fits"))
            stream = sys.stderr if loud else sys.stdout
            if loud or not job.quiet:
                (bar.write(line, file=stream) if bar is not None else print(line, file=stream, flush=True))
        if bar is not None:
            bar.set_postfix(cells=len(step.next_cells), flow=f"{step.flow_value / (len(step.probs) * len(step.next_cells)):.4f}")
            bar.update(1)

    t_start = time.perf_counter()
    extra: dict[str, Any] = {}
    try:
        if coverage_config is not None:
            table, stats, extra = _build_coverage(system, coverage_config, bar)
        else:
            table, stats = build_table(system, config, checkpoint_dir=ckpt, resume=job.resume, progress=progress)
    except KeyboardInterrupt:
        if coverage_config is not None:
            raise
        raise KeyboardInterrupt("interrupted: no table written; rerun with --resume to continue from the last "
                                "finished level") from None
    finally:
        if bar is not None:
            bar.close()
    t0 = time.perf_counter()
    try:
        write_table(out, table)
    except OSError as exc:
        kept = f"; the finished levels stay in {ckpt} (rerun with --resume)" if coverage_config is None else ""
        raise CLIError(f"cannot write the table {out}: {exc.strerror or exc}{kept}") from None
    stats.seconds["write"] = time.perf_counter() - t0
    shutil.rmtree(ckpt, ignore_errors=True)
    total = time.perf_counter() - t_start
    if stats.resumed_steps:
        say(f"resumed {stats.resumed_steps} of {horizon} levels from checkpoints")
    graph = f"{len(table.arcs)} arcs" if table.arcs is not None else f"{len(table.transitions)} transitions"
    say(f"level sizes: {table.level_sizes}  ({len(table.cells)} cells, {graph})")
    say("stage times: " + ", ".join(f"{k} {v:.2f}s" for k, v in stats.seconds.items()) + f"; total {total:.2f}s")
    say(f"wrote {out}")

    report_path = out.with_name(out.stem + ".report.json")
    summary: dict[str, Any] = {
        "table": str(out),
        "system": system.name,
        "params": system.params(),
        "horizon": horizon,
        "points": config.points.value,
        "level_sizes": table.level_sizes,
        "flow_ratio": (table.flow_value / table.flow_target).tolist() if coverage_config is None else None,
        "seconds": {**stats.seconds, "total": total},
        "method": job.method,
        "zero_outflow_cells": stats.zero_outflow,
        "kept_point_fraction": stats.kept_fraction,
        "size_guide": {"projected_level_sizes": guide.projection, "estimated_peak_bytes": guide.estimate_bytes,
                       "budget_bytes": budget, "warned": guide.warned},
        **extra,
    }
    if job.report:
        t0 = time.perf_counter()
        report = uniformity_report(table, num_rollouts=job.rollouts, seed=config.seed, device=job.device)
        summary["report_seconds"] = time.perf_counter() - t0
        summary["uniformity"] = report.to_dict()
        say(format_report(report))
        say(f"report: {report.num_rollouts} rollouts in {summary['report_seconds']:.2f}s")
    write_json(report_path, summary)
    say(f"wrote {report_path}")
    return table
