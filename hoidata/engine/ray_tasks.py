"""Ray as the executor of a build: every shard job a Ray task, on an existing cluster or a local Ray instance.

:func:`run_ray` has :func:`hoidata.engine.pool.run_pool`'s signature and contract, so
:func:`hoidata.engine.engine.run_task` hands it the same jobs: a shard's bytes depend only on its job, so a
Ray build writes the same shards as a local one, and resume (which shards to build) is decided before any task
is submitted, the same way. Each task takes one CPU; a Ray worker process runs the job's initialiser (the engine
opens the task's worker context: MANO, objects, renderer) once, before its first job. Ray is an optional
dependency (the ``cluster`` extra); the package must be importable on every node of the cluster (installed
there, or on a shared filesystem).

Errors are the pool's: the first failing job's exception (a DataError as it was raised), after cancelling the
tasks not yet finished; an initialiser that fails is a WorkerError naming it; a worker or node that dies is
retried by Ray (the job is idempotent), and a WorkerError when retries run out.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator

from hoidata.errors import WorkerError
from hoidata.engine.pool import describe_failure

_STARTED: set[str] = set()  # in a Ray worker process: the initialisers already run here
TASKS_PER_CPU = 2  # tasks kept in flight per cluster CPU (jobs carry their frames: not all at once)
RETRIES = 2  # Ray re-runs a task whose worker process or node died


def _call(fn: Callable, init: Callable, initargs: tuple, job):
    """Worker side: run ``init(*initargs)`` once per process (a failure is a WorkerError), then ``fn(job)``."""
    key = f"{getattr(init, '__module__', '?')}.{getattr(init, '__qualname__', init)}{initargs!r}"
    if key not in _STARTED:
        try:
            init(*initargs)
        except Exception as exc:  # noqa: BLE001 - the pool's one line, whatever the failure
            raise WorkerError(None, None, describe_failure(init, exc)) from None
        _STARTED.add(key)
    return fn(job)


def _first_line(exc: BaseException) -> str:
    lines = [line for line in str(exc).splitlines() if line.strip()]
    return lines[-1].strip() if lines else type(exc).__name__


def run_ray(fn: Callable, jobs: Iterable, workers: int, init: Callable, initargs: tuple = (),
            address: str | None = None) -> Iterator:
    """``fn(job)`` for every job as Ray tasks, yielded in completion order.

    Uses the Ray instance this process is connected to; otherwise connects to ``address`` (``"auto"``, or
    ``"ray://host:10001"`` for Ray Client), or starts a local instance with ``workers`` CPUs when ``address`` is
    None, and disconnects at the end. ``fn`` and ``init`` must be module-level functions.
    """
    import logging

    import ray

    jobs = list(jobs)
    if not jobs:
        return
    started = not ray.is_initialized()
    if started:
        ray.init(address=address, num_cpus=None if address else max(1, workers), include_dashboard=False,
                 logging_level=logging.WARNING, log_to_driver=False)
    remote = ray.remote(num_cpus=1, max_retries=RETRIES)(_call)
    pending, queue = [], iter(jobs)
    try:
        window = max(1, TASKS_PER_CPU * int(ray.cluster_resources().get("CPU", 1)))
        for job in queue:
            pending.append(remote.remote(fn, init, initargs, job))
            if len(pending) >= window:
                break
        while pending:
            (ready,), pending = ray.wait(pending, num_returns=1)
            yield _result(ray, ready)
            for job in queue:  # one new task for each one finished
                pending.append(remote.remote(fn, init, initargs, job))
                break
    finally:
        for ref in pending:  # an error, or the consumer stopped: nothing more runs
            ray.cancel(ref, force=True)
        if started:
            ray.shutdown()


def _result(ray, ref):
    """The task's result; its own exception as it was raised, or a WorkerError for a task Ray could not run."""
    try:
        return ray.get(ref)
    except ray.exceptions.RayTaskError as exc:
        cause = getattr(exc, "cause", None)
        if isinstance(cause, Exception):
            raise cause from None
        raise WorkerError(None, None, f"a Ray task failed: {_first_line(exc)}") from None
    except ray.exceptions.RayError as exc:  # a worker or node died and the retries ran out, or a lost object
        raise WorkerError(None, None, f"a Ray worker failed ({type(exc).__name__}): {_first_line(exc)}") from None
