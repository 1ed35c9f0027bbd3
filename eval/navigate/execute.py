"""Running navigation episodes: in this process, in local worker processes, or as Ray tasks.

Episodes are independent and :func:`eval.navigate.episode.run_nav_episode` is a pure function of its job, so the
three executors return the same records (in completion order; callers sort by key). Every executor calls
``on_record`` in this process as each record arrives, so the caller appends it to the run's file at once and an
interrupted run loses at most the episodes in flight. A progress bar counts episodes in every mode.

Serial (``workers=1``, no Ray), ``workers=N`` spawned processes (each caching the files it loaded), or Ray tasks
(``ray_address``: ``"local"``, ``"auto"``, ``"ray://host:10001"``; the cluster's nodes need this package):
:func:`precompute.parallel.run_jobs`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

from eval.navigate.episode import NavContext, NavJob, run_nav_episode
from precompute.parallel import RAY_MISSING, ray_available, run_jobs

__all__ = ["execute"]


def execute(jobs: Sequence[NavJob], ctx: NavContext, on_record: Callable[[dict], None], workers: int = 1,
            ray_address: str | None = None, progress: bool = True, desc: str = "episodes") -> None:
    """Run every job, calling ``on_record(record)`` for each as it finishes (module docstring)."""
    from tqdm.auto import tqdm

    if ray_address is not None and not ray_available():
        raise RuntimeError(RAY_MISSING)
    with tqdm(total=len(jobs), desc=desc, unit="episode", disable=not progress, smoothing=0.05) as bar:
        def keep(_: int, record: dict) -> None:
            on_record(record)
            bar.update()

        run_jobs(run_nav_episode, [(job, ctx) for job in jobs], workers, ray_address, keep)
