"""Independent jobs in this process, in spawned worker processes, or as Ray tasks: one helper for the table farm
(``precompute.build --starts``) and the navigation benchmark (``eval.navigate.run``).

Spawned, not forked, processes: a forked torch with threads started is unsafe. Each worker dies with the process
that started it (:func:`_die_with_parent`): a parent killed hard (``kill -9``, out of memory) runs no cleanup,
and its workers would otherwise run on, orphaned, and keep the multiprocessing resource tracker alive.

Ray is an optional extra (``pip install -e ".[ray]"``): ``ray_address="local"`` starts a local runtime for the
call (``workers`` caps its CPUs when > 1), any other address is passed to ``ray.init(address=...)``; one CPU per
job.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import signal
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from typing import Any

__all__ = ["RAY_MISSING", "ray_available", "run_jobs", "WorkerDiedError"]

RAY_MISSING = 'the --ray executor needs Ray: pip install -e ".[ray]"'

PARENT_POLL_S = 0.25
"""s between a worker's checks that its parent is alive"""


class WorkerDiedError(ChildProcessError):
    """A worker process died before it finished its job (SIGKILL by the out-of-memory killer, a crash): one clear
    error (an ``OSError``) instead of ``BrokenProcessPool``'s traceback; the jobs finished before it were kept."""


def ray_available() -> bool:
    """Whether ``import ray`` works."""
    try:
        import ray  # noqa: F401
    except ImportError:
        return False
    return True


def run_jobs(fn: Callable[..., Any], jobs: Sequence[tuple], workers: int = 1, ray_address: str | None = None,
             on_done: Callable[[int, Any], None] | None = None) -> list[Any]:
    """``fn(*job)`` for every job (a picklable module-level ``fn``); the results in job order. ``on_done(i,
    result)`` runs in this process as each job finishes (in completion order), so a caller can save it at once.
    On an error or Ctrl-C the queued jobs are dropped and the exception propagates."""
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ValueError(f"workers must be an integer >= 1, got {workers!r}")
    results: list[Any] = [None] * len(jobs)

    def done(i: int, result: Any) -> None:
        results[i] = result
        if on_done is not None:
            on_done(i, result)

    if ray_address is not None:
        _ray(fn, jobs, ray_address, workers, done)
    elif workers > 1 and len(jobs) > 1:
        _processes(fn, jobs, min(workers, len(jobs)), done)
    else:
        for i, job in enumerate(jobs):
            done(i, fn(*job))
    return results


def _watch_parent(parent: int) -> None:
    while os.getppid() == parent:  # an orphan is re-parented (to init or a subreaper): its parent id changes
        time.sleep(PARENT_POLL_S)
    os._exit(1)  # no cleanup: the job's half-done work has no one to report to


def _die_with_parent(parent: int) -> None:
    """A pool worker's initializer: a daemon thread ends the worker once ``parent`` (the pid that started it) is
    gone. Polling rather than Linux's PR_SET_PDEATHSIG, which fires when the *thread* that started the worker
    exits (a pool started from a short-lived thread) and exists on Linux only. The resource tracker follows by
    itself: it exits when the last process holding its pipe (the parent and the workers) is gone."""
    threading.Thread(target=_watch_parent, args=(parent,), name="die-with-parent", daemon=True).start()


@contextlib.contextmanager
def _sigint_blocked() -> Iterator[None]:
    """SIGINT blocked in this thread while the block runs (a Ctrl-C meanwhile is delivered after it). Processes
    started meanwhile inherit the blocked mask across exec and never see a Ctrl-C: the terminal sends it to the whole
    process group, and each spawned worker printed its own KeyboardInterrupt traceback (most often from importing
    the main module); the parent alone handles it and ends them (:func:`_processes`)."""
    if threading.current_thread() is not threading.main_thread() or not hasattr(signal, "pthread_sigmask"):
        yield  # Python runs signal handlers in the main thread only: no Ctrl-C to keep from workers started here
        return
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


class _Terminated(BaseException):
    """SIGTERM arrived while a pool ran (:func:`_sigterm_ends_the_pool`)."""


@contextlib.contextmanager
def _sigterm_ends_the_pool() -> Iterator[None]:
    """While the block runs (in the main thread, SIGTERM at its default), a SIGTERM ends the pool's workers before
    the process dies of it: killed at once, the parent left its workers mid-handshake (a ``ConnectionResetError``
    traceback each) and the resource tracker warning about leaked semaphores. The process still ends by SIGTERM,
    re-raised once the pool is shut down, as its sender expects."""
    if (threading.current_thread() is not threading.main_thread()
            or signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL):
        yield  # another handler, or ignored: not ours to change
        return

    def terminated(signum: int, frame: Any) -> None:
        raise _Terminated

    signal.signal(signal.SIGTERM, terminated)
    try:
        yield
    except _Terminated:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        signal.raise_signal(signal.SIGTERM)  # dies here, as it would have without the pool
        raise
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)


def _processes(fn: Callable[..., Any], jobs: Sequence[tuple], workers: int, done: Callable[[int, Any], None]) -> None:
    with _sigterm_ends_the_pool():
        _pool(fn, jobs, workers, done)


def _pool(fn: Callable[..., Any], jobs: Sequence[tuple], workers: int, done: Callable[[int, Any], None]) -> None:
    pool = ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn"),
                               initializer=_die_with_parent, initargs=(os.getpid(),))
    try:
        with _sigint_blocked():  # the workers start (at the first submit) with Ctrl-C blocked
            pending = {pool.submit(fn, *job): i for i, job in enumerate(jobs)}
        while pending:
            finished, _ = wait(pending, return_when=FIRST_COMPLETED)
            for future in finished:
                try:
                    result = future.result()
                except BrokenProcessPool:
                    raise WorkerDiedError(
                        f"a worker process died before finishing its job ({workers} workers; killed, e.g. by the "
                        "out-of-memory killer, or crashed); the jobs finished before were kept: rerun to resume, "
                        "with fewer --workers if memory ran out") from None
                done(pending.pop(future), result)
    except (KeyboardInterrupt, _Terminated):  # Ctrl-C (the workers never see it: blocked) or SIGTERM: end their
        # jobs now, not at their end
        for process in list((getattr(pool, "_processes", None) or {}).values()):
            process.terminate()
        raise
    finally:  # on an error or Ctrl-C: drop the queued jobs, keep what was done
        pool.shutdown(wait=True, cancel_futures=True)


def _ray(fn: Callable[..., Any], jobs: Sequence[tuple], address: str, workers: int,
         done: Callable[[int, Any], None]) -> None:
    try:
        import ray
    except ImportError:
        raise RuntimeError(RAY_MISSING) from None
    started = not ray.is_initialized()
    if started:
        kwargs: dict[str, Any] = dict(include_dashboard=False, log_to_driver=False, configure_logging=False)
        if address == "local":
            kwargs["num_cpus"] = workers if workers > 1 else None
        else:
            kwargs["address"] = address
        ray.init(**kwargs)
    try:
        remote = ray.remote(num_cpus=1)(fn)
        refs = {remote.remote(*job): i for i, job in enumerate(jobs)}
        pending = list(refs)
        while pending:
            finished, pending = ray.wait(pending, num_returns=1)
            for ref in finished:
                done(refs[ref], ray.get(ref))
    finally:
        if started:
            ray.shutdown()
