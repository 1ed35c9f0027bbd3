"""Running navigation episodes: in this process, in local worker processes, or as Ray tasks.

Episodes are independent and :func:`eval.nav_episode.run_nav_episode` is a pure function of its job, so the
three executors return the same records (in completion order; callers sort by key). Every executor calls
``on_record`` in this process as each record arrives, so the caller appends it to the run's file at once and an
interrupted run loses at most the episodes in flight. A progress bar counts episodes in every mode.

* serial (``workers=1``, no Ray);
* ``workers=N``: a ``concurrent.futures.ProcessPoolExecutor`` of N spawned processes (spawn, not fork: a forked
  torch with threads started is unsafe), each caching the files it loaded;
* Ray (``ray_address``): ``"local"`` starts a local Ray runtime for the run (``ray.init()``; ``workers`` caps its
  CPUs when > 1); any other value is passed to ``ray.init(address=...)`` (``"auto"``, ``"ray://host:10001"``) to
  run on a cluster whose nodes have this package installed. One CPU per episode. Ray is an optional extra:
  ``pip install -e ".[ray]"``.
"""

from __future__ import annotations

import multiprocessing
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from typing import Callable, Sequence

from .nav_episode import NavContext, NavJob, run_nav_episode

__all__ = ["execute", "ray_available", "RAY_MISSING"]

RAY_MISSING = 'the --ray executor needs Ray: pip install -e ".[ray]"'


def ray_available() -> bool:
    """Whether ``import ray`` works."""
    try:
        import ray  # noqa: F401
    except ImportError:
        return False
    return True


def _bar(total: int, progress: bool, desc: str):
    from tqdm.auto import tqdm

    return tqdm(total=total, desc=desc, unit="episode", disable=not progress, smoothing=0.05)


def _serial(jobs: Sequence[NavJob], ctx: NavContext, on_record: Callable[[dict], None], bar) -> None:
    for job in jobs:
        on_record(run_nav_episode(job, ctx))
        bar.update()


def _processes(jobs: Sequence[NavJob], ctx: NavContext, workers: int, on_record: Callable[[dict], None],
               bar) -> None:
    pool = ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn"))
    try:
        pending = {pool.submit(run_nav_episode, job, ctx) for job in jobs}
        while pending:
            done, pending = wait(pending, return_when=FIRST_COMPLETED)
            for future in done:
                on_record(future.result())
                bar.update()
    finally:  # on an error or Ctrl-C: drop the queued episodes, keep what was recorded
        pool.shutdown(wait=True, cancel_futures=True)


def _ray(jobs: Sequence[NavJob], ctx: NavContext, address: str, workers: int,
         on_record: Callable[[dict], None], bar) -> None:
    try:
        import ray
    except ImportError:
        raise RuntimeError(RAY_MISSING) from None
    started = not ray.is_initialized()
    if started:
        kwargs = dict(include_dashboard=False, log_to_driver=False, configure_logging=False)
        if address == "local":
            ray.init(num_cpus=workers if workers > 1 else None, **kwargs)
        else:
            ray.init(address=address, **kwargs)
    try:
        remote = ray.remote(num_cpus=1)(run_nav_episode)
        ctx_ref = ray.put(ctx)
        pending = [remote.remote(job, ctx_ref) for job in jobs]
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            for ref in done:
                on_record(ray.get(ref))
                bar.update()
    finally:
        if started:
            ray.shutdown()


def execute(jobs: Sequence[NavJob], ctx: NavContext, on_record: Callable[[dict], None], workers: int = 1,
            ray_address: str | None = None, progress: bool = True, desc: str = "episodes") -> None:
    """Run every job, calling ``on_record(record)`` for each as it finishes (module docstring)."""
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ValueError(f"workers must be an integer >= 1, got {workers!r}")
    if ray_address is not None and not ray_available():
        raise RuntimeError(RAY_MISSING)
    with _bar(len(jobs), progress, desc) as bar:
        if not jobs:
            return
        if ray_address is not None:
            _ray(jobs, ctx, ray_address, workers, on_record, bar)
        elif workers > 1:
            _processes(jobs, ctx, min(workers, len(jobs)), on_record, bar)
        else:
            _serial(jobs, ctx, on_record, bar)
