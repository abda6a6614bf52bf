"""Worker pools that end with one clear error instead of hanging: every process pool of the project uses this.

``multiprocessing.Pool`` respawns a worker whose initialiser raises, forever (a missing package or no EGL
then prints a traceback per respawn and never returns), and waits forever for the task of a worker that
was killed (out of memory). :func:`run_pool` instead:

- runs the initialiser under a guard: a failure is remembered in the worker, not raised, and the worker's
  first task raises :class:`~hoidata.errors.WorkerError` naming the initialiser and the original error;
- uses ``concurrent.futures.ProcessPoolExecutor`` (spawn), which reports a worker that died abruptly;
- on the first error, cancels what has not started, terminates the workers and raises that error in
  the parent (DataErrors arrive as they were raised).

With ``workers <= 1`` everything runs in this process, and a failing initialiser is a WorkerError too.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator

from hoidata.errors import WorkerError

_START_FAILURE: list[str] = []  # in a worker process: why its initialiser failed


def describe_failure(init: Callable, exc: BaseException) -> str:
    """One line saying that a worker process could not start: the set-up that failed (``init``, by its qualified
    name) and the error's first line; a WorkerError's own line as it is (it already says so)."""
    if isinstance(exc, WorkerError):
        return exc.problem
    where = f"{getattr(init, '__module__', '?')}.{getattr(init, '__qualname__', init)}"
    text = str(exc).strip().splitlines()
    return f"could not start a worker process ({where}): {type(exc).__name__}: {text[0] if text else ''}".rstrip(": ")


def _guarded_init(init: Callable, initargs: tuple) -> None:
    """Worker side: run the initialiser; keep its failure for the first task instead of raising."""
    try:
        init(*initargs)
    except BaseException as exc:  # noqa: BLE001 - any failure, SystemExit from a C library included
        _START_FAILURE.append(describe_failure(init, exc))


def _guarded_call(fn: Callable, job):
    if _START_FAILURE:
        raise WorkerError(None, None, _START_FAILURE[0])
    return fn(job)


def _terminate(executor) -> None:
    """Stop every worker now (the executor has no public call for it) and release the executor."""
    for process in list((getattr(executor, "_processes", None) or {}).values()):
        if process.is_alive():
            process.terminate()
    executor.shutdown(wait=True, cancel_futures=True)


def run_pool(fn: Callable, jobs: Iterable, workers: int, init: Callable, initargs: tuple = ()) -> Iterator:
    """``fn(job)`` for every job, yielded in completion order, from ``workers`` spawned processes set up by
    ``init(*initargs)``; ``fn`` and ``init`` must be module-level functions (they are pickled by name).

    Raises the first task's error (after stopping the other workers), a WorkerError when a worker could not
    start or died. With ``workers <= 1`` the jobs run here, in order, after ``init``.
    """
    jobs = list(jobs)
    if workers <= 1:
        try:
            init(*initargs)
        except Exception as exc:  # noqa: BLE001 - the same one line as from a worker process
            raise WorkerError(None, None, describe_failure(init, exc)) from exc
        for job in jobs:
            yield fn(job)
        return
    if not jobs:
        return
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor, as_completed
    from concurrent.futures.process import BrokenProcessPool

    executor = ProcessPoolExecutor(min(workers, len(jobs)), mp_context=mp.get_context("spawn"),
                                   initializer=_guarded_init, initargs=(init, initargs))
    try:
        futures = [executor.submit(_guarded_call, fn, job) for job in jobs]
        for future in as_completed(futures):
            try:
                result = future.result()
            except BrokenProcessPool:
                raise WorkerError(None, None, "a worker process died unexpectedly (killed, or out of memory?)") from None
            yield result
    except BaseException:
        _terminate(executor)
        raise
    executor.shutdown(wait=True)
