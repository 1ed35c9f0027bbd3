"""Running navigation episodes: in this process, in local worker processes, or as Ray tasks.

Episodes are independent and :func:`eval.navigate.episode.run_nav_episode` is a pure function of its job, so the
three executors return the same records (in completion order; callers sort by key). Every executor calls
``on_record`` in this process as each record arrives, so the caller appends it to the run's file at once and an
interrupted run loses at most the episodes in flight. A progress bar counts episodes in every mode.

Serial (``workers=1``, no Ray), ``workers=N`` spawned processes (each caching the files it loaded), or Ray tasks
(``ray_address``: ``"local"``, ``"auto"``, ``"ray://host:10001"``; the cluster's nodes need this package):
:func:`precompute.parallel.run_jobs`.

``lockstep=N``: the jobs of each (method, K) in batches of up to N episodes, each batch one controller of N robots
stepped together (:mod:`eval.navigate.lockstep`); the executors then run batches (a worker or Ray task per batch),
and a batch's records arrive together when its last episode ends.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

from eval.navigate.episode import NavContext, NavJob, run_nav_episode
from eval.navigate.lockstep import lockstep_batches, run_lockstep
from precompute.parallel import RAY_MISSING, ray_available, run_jobs

__all__ = ["execute"]


def execute(jobs: Sequence[NavJob], ctx: NavContext, on_record: Callable[[dict], None], workers: int = 1,
            ray_address: str | None = None, progress: bool = True, desc: str = "episodes",
            lockstep: int | None = None) -> None:
    """Run every job, calling ``on_record(record)`` for each as it finishes (module docstring); ``lockstep``: batches
    of up to that many episodes of one (method, K) stepped together (None: one episode at a time)."""
    from tqdm.auto import tqdm

    if ray_address is not None and not ray_available():
        raise RuntimeError(RAY_MISSING)
    with tqdm(total=len(jobs), desc=desc, unit="episode", disable=not progress, smoothing=0.05) as bar:
        def keep(_: int, record: dict) -> None:
            on_record(record)
            bar.update()

        if lockstep is None:
            run_jobs(run_nav_episode, [(job, ctx) for job in jobs], workers, ray_address, keep)
            return

        def keep_batch(i: int, records: list[dict]) -> None:
            for record in records:
                keep(i, record)

        run_jobs(run_lockstep, [(batch, ctx) for batch in lockstep_batches(jobs, lockstep)], workers, ray_address,
                 keep_batch)
