"""The library's building jobs as typed functions: ``from precompute import BuildConfig, build_table``.

* :func:`build_table`: one table of a system, in memory or written (atomically) with its report JSON;
* :func:`build_table_set`: a table set, one table per start (:class:`SetConfig`), into a folder.

``python -m precompute.build`` is a shell over these two: it parses its flags into the same configs and calls
them with ``progress=True``. From Python the progress bars are off by default, nothing calls ``sys.exit``, and a bad
setting is one ``ValueError`` naming the field (Ctrl-C stays a ``KeyboardInterrupt`` saying what survives).

Shapes: S starts, d state dimensions.
"""

from __future__ import annotations

import dataclasses
import os
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, TypeVar

import numpy as np

from cuniform_torch.systems import System, check_system
from cuniform_torch.tables.file import Table
from precompute.cli import CLIError
from precompute.coverage.method import CoverageConfig
from precompute.flow.builder import BuildConfig
from precompute.one_table import TableJob, run_table_job
from precompute.table_set import MAX_SET_MEMBERS, parse_starts
from precompute.table_set import build_table_set as build_members

if TYPE_CHECKING:
    from cuniform_torch.policies.table_set import TableSetPolicy

__all__ = ["BuildConfig", "CoverageConfig", "SetConfig", "build_table", "build_table_set", "library_errors"]

T = TypeVar("T")


@dataclass(frozen=True)
class SetConfig:
    """The starts of a table set and how its tables are built (``python -m precompute.build set``).

    :param starts: one table per start: a spec string (a grid ``"DIM=LO:HI:N ..."`` or a seeded sample
        ``"random:N DIM=LO:HI ..."``, :mod:`precompute.table_set`) or the starts themselves, ``[S, d]``
    :param workers: tables built in parallel processes
    :param ray: build the tables as Ray tasks: ``"local"`` or a cluster address (None: no Ray)
    :param no_limit: allow more than 10,000 tables (:data:`~precompute.table_set.MAX_SET_MEMBERS`)
    """

    starts: str | Sequence[Sequence[float]] | np.ndarray
    workers: int = 1
    ray: str | None = None
    no_limit: bool = False

    def __post_init__(self) -> None:
        if isinstance(self.workers, bool) or not isinstance(self.workers, int) or not 1 <= self.workers <= 1024:
            raise ValueError(f"SetConfig.workers must be an integer in 1..1024, got {self.workers!r}")
        if self.ray is not None and not isinstance(self.ray, str):
            raise ValueError(f"SetConfig.ray must be 'local', a cluster address or None, got {self.ray!r}")

    def start_array(self, system: System, seed: int = 0) -> np.ndarray:
        """The starts ``[S, d]`` float64 for ``system`` (a spec's ``random:N`` drawn with ``seed``)."""
        limit = None if self.no_limit else MAX_SET_MEMBERS
        if isinstance(self.starts, str):
            return parse_starts(self.starts, system, seed=seed, limit=limit)
        starts = np.asarray(self.starts, dtype=np.float64)
        d = len(system.periodic)
        if starts.ndim != 2 or starts.shape[1] != d or len(starts) == 0 or not np.isfinite(starts).all():
            raise ValueError(f"SetConfig.starts must be a spec string or finite starts [S, {d}] with S >= 1, got "
                             f"shape {list(starts.shape)}")
        if limit is not None and len(starts) > limit:
            raise ValueError(f"SetConfig.starts: {len(starts):,} starts, more than {limit:,}; set no_limit=True")
        return starts


def _job(system: System, config: BuildConfig, coverage: CoverageConfig | None, out: Path, **fields) -> TableJob:
    """The :class:`TableJob` of the public arguments; a ValueError naming the field that does not fit."""
    if isinstance(system, str):
        raise ValueError(f"system must be a System object, e.g. make_system({system!r}) "
                         "(cuniform_torch.systems.make_system), not its name")
    check_system(system)  # a user system's missing member or bad grid: one ValueError naming it, before any work
    if not isinstance(config, BuildConfig):
        raise ValueError(f"config must be a BuildConfig (horizon, seed, start, ...), got {type(config).__name__}; "
                         "the coverage method's settings go in coverage=CoverageConfig(...)")
    if coverage is not None:
        if not isinstance(coverage, CoverageConfig):
            raise ValueError(f"coverage must be a CoverageConfig or None, got {type(coverage).__name__}")
        if coverage.start != config.start:
            raise ValueError(f"coverage.start {coverage.start} differs from config.start {config.start}; give both "
                             "the same start")
        # the map belongs to the build: the coverage method prunes the same cells
        coverage = dataclasses.replace(coverage, local_map=config.local_map, radius=config.radius)
    return TableJob(system=system, out=out, build=config, coverage=coverage, **fields)


def library_errors(run: Callable[[], T]) -> T:
    """``run()`` with the command layer's :class:`CLIError` (an unusable output path, a held lock) as the
    ValueError a library call raises (the training jobs use it too)."""
    try:
        return run()
    except CLIError as exc:
        raise ValueError(str(exc)) from None


def build_table(system: System, config: BuildConfig | None = None, *, coverage: CoverageConfig | None = None,
                out: str | os.PathLike | None = None, report: bool = False, rollouts: int | None = None,
                device: str = "cpu", resume: bool = False, max_memory_gb: float | None = None,
                progress: bool = False) -> Table:
    """Build the C-Uniform table of ``system`` with ``config`` (max-flow; None: ``BuildConfig()``), or with ``coverage`` (the coverage
    method; its horizon and start must be ``config``'s).

    With ``out`` the table is written atomically (``.npz``) with ``<out stem>.report.json`` beside it, checkpoints
    in ``<out>.partial/`` (``resume=True`` continues them), a lock against a second build to the same file, the
    size guidance (``max_memory_gb``) and, with ``report=True``, the uniformity report on ``rollouts`` rollouts on
    ``device``: byte for byte the file of ``python -m precompute.build`` with the same settings. Without ``out``
    nothing is written. ``progress``: a bar per level and the build's summary lines on stdout.

    :return: the table (``table.level_sizes``, ``table.cells`` [C, d], ``table.action_probs`` [C, A], ...)
    """
    config = BuildConfig() if config is None else config
    quiet = not progress
    if out is None:
        job = _job(system, config, coverage, Path("unwritten.npz"), report=False, quiet=quiet)
        if report or resume or rollouts is not None or max_memory_gb is not None:
            raise ValueError("report, rollouts, resume and max_memory_gb need out=FILE (they write or read files "
                             "beside it)")
        return _in_memory(job)
    job = _job(system, config, coverage, Path(out), report=report, rollouts=rollouts, device=device, resume=resume,
               max_memory_gb=max_memory_gb, quiet=quiet)
    return library_errors(lambda: run_table_job(job))


def _in_memory(job: TableJob) -> Table:
    """The table of ``job`` built without files (the same builders as :func:`run_table_job`)."""
    from precompute.flow.builder import build_table as build_maxflow
    from precompute.one_table import _build_coverage

    bar = None
    if not job.quiet:
        from tqdm import tqdm

        bar = tqdm(total=job.build.horizon, desc="levels", unit="level", file=sys.stdout)
    try:
        if job.coverage is not None:
            return _build_coverage(job.system, job.coverage, bar)[0]
        return build_maxflow(job.system, job.build, progress=None if bar is None else (lambda t, s: bar.update(1)))[0]
    finally:
        if bar is not None:
            bar.close()


def build_table_set(system: System, config: SetConfig, build: BuildConfig | None = None, *,
                    coverage: CoverageConfig | None = None, out: str | os.PathLike,
                    progress: bool = False) -> TableSetPolicy:
    """Build one table of ``system`` per start of ``config`` into the folder ``out`` (``start_0000.npz``, ...,
    ``tables.json``): each member is :func:`build_table` with ``build`` (and ``coverage``) from its start, so
    byte-identical to that table built alone. Members already there with these settings are kept (a rerun resumes;
    a complete set is only re-indexed); one built with other settings is a ValueError naming what differs.
    ``random:N`` starts are drawn with ``build.seed``.

    :return: the set as a policy (:class:`~cuniform_torch.policies.table_set.TableSetPolicy`, its tables read on
        first use)
    """
    from cuniform_torch.policies.table_set import load_table_set

    build = BuildConfig() if build is None else build
    if not isinstance(config, SetConfig):
        raise ValueError(f"config must be a SetConfig (starts, workers, ...), got {type(config).__name__}")
    folder = Path(out)
    template = _job(system, build, coverage, folder / "start_0000.npz", report=False, quiet=not progress)
    starts = config.start_array(system, seed=build.seed)
    library_errors(lambda: build_members(template, starts, folder, config.workers, config.ray))
    return load_table_set(folder)
