"""The shard engine: plans, resumes, runs and reports any work cut into numbered units.

Every pipeline that writes its output in independent units (build-sdf's and render-synthetic's store shards,
export's chunks, the toy writer's sequences) hands :func:`run_task` one task object, a :class:`ShardTask`:

- ``plan``: a :class:`Plan`, the number of items (frames, samples, sequences) and the items per unit; unit k
  holds the items k*per .. (k+1)*per-1, so a unit's content depends only on its items, never on the workers,
  the part or the order it ran in;
- ``desc``: the progress bar's label;
- ``job(n)``: unit n's picklable job (made in this process, sent to the worker that runs it);
- ``worker``: a small picklable, hashable spec (a frozen dataclass) whose ``open()`` returns the worker context:
  the per-process state (models, caches, renderers) with ``run(job) -> (number, items written, skips)`` and
  ``close()``;
- ``done(numbers, starting) -> set[int]``: which of these units are already done. ``starting``: the call before
  this run's work, with this part's units only (the task may clear their leftovers of a killed run); else the
  call after it, with every unit of the plan, while other parts may still be writing (read only). The base's
  default: none (no resume; the run is complete when it ran every unit);
- ``check_kept(numbers)``: may refuse the units a resumed run keeps (inputs that changed since); the base's
  default refuses none.

:func:`run_task` returns a :class:`RunSummary`, the one summary every recipe reports (its own counts beside).

Where the jobs run: with ``workers <= 1`` and no ``executor``, here, in order, in one worker context that the
engine closes when the run ends (also on an error). Otherwise in ``executor(fn, jobs, workers, init, initargs)``
(default :func:`hoidata.engine.pool.run_pool`; :func:`hoidata.engine.ray_tasks.run_ray` has the same
contract), whose processes each open the task's worker context once, before their first job, keep it in this
module's registry (``_OPEN``, the only place a task's per-process state is kept) and close it when the process
exits normally (best effort: ``multiprocessing``'s exit finalisers in a pool worker, ``atexit`` elsewhere; a
terminated or killed process just ends, and the OS reclaims its GL contexts and memory). A context that cannot
open is one WorkerError line naming the spec's ``open``.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Protocol, runtime_checkable

from tqdm import tqdm

from hoidata.errors import WorkerError
from hoidata.engine.pool import describe_failure


@dataclass(frozen=True)
class Plan:
    """``items`` to process in units of ``per`` items (the last unit may hold fewer)."""

    items: int
    per: int

    def __post_init__(self):
        if self.items < 0 or self.per < 1:
            raise ValueError(f"a plan needs items >= 0 and per >= 1, got items={self.items}, per={self.per}")

    @property
    def units(self) -> list[int]:
        """Every unit number of the plan, 0 .. ceil(items / per) - 1."""
        return list(range((self.items + self.per - 1) // self.per))

    def size(self, number: int) -> int:
        """Items in unit ``number``."""
        return max(0, min(self.per, self.items - number * self.per))

    def owned(self, part: tuple[int, int]) -> list[int]:
        """The units of ``--part i/N``: those with number % N == i."""
        return [n for n in self.units if n % part[1] == part[0]]


@runtime_checkable
class WorkerContext(Protocol):
    """Per-process state of a task: runs its jobs, released by ``close()``."""

    def run(self, job) -> tuple[int, int, list]: ...

    def close(self) -> None: ...


class ShardTask:
    """What a recipe hands the engine (see the module docstring): a subclass sets ``plan``, ``desc`` and ``worker``
    (usually as dataclass fields) and defines ``job``; ``done`` and ``check_kept`` have no-op defaults."""

    plan: Plan
    desc: str
    worker: object  # picklable, hashable; worker.open() -> WorkerContext

    def job(self, number: int):
        """Unit ``number``'s picklable job (a dataclass), made here and sent to the worker that runs it."""
        raise NotImplementedError(f"{type(self).__name__} defines no job()")

    def done(self, numbers: list[int], starting: bool) -> set[int]:
        """The units of ``numbers`` already done (default: none; see the module docstring)."""
        return set()

    def check_kept(self, numbers: list[int]) -> None:
        """Refuse to keep these done units (a DataError), e.g. when their inputs changed; default: keep them."""


@dataclass(slots=True)  # a misspelt field is an error, not a new attribute
class RunSummary:
    """What one run of a recipe did (this part's units), and whether its output is complete: the engine fills the
    counts, the recipe its own fields (``out``, the reader's skips, the last step's state and files).

    Units are what the recipe writes independently (store shards, export chunks, toy sequences), items what a
    unit holds (frames, samples, sequences)."""

    out: Path | None = None  # the store or folder written
    units: list[int] = field(default_factory=list)  # every unit number of the plan, all parts
    items: int = 0  # items of the whole plan
    written: int = 0  # items the units of this run wrote (records, exported frames, images)
    skipped: list = field(default_factory=list)  # items skipped (by this run's units; every unit's once finished)
    reader_skipped: list = field(default_factory=list)  # frames the dataset reader left out, with their reasons
    units_written: int = 0
    empty_units: int = 0  # units that wrote no item (this run's; every unit's once finished)
    units_kept: int = 0  # units of this part already done before the run
    seconds: float = 0.0
    all_done: bool = False  # every unit of the plan is done (this part's and the others')
    finished: bool = False  # ... and the recipe's last step is written (a store's index, an export's annotations)
    finish_kept: bool = False  # ... by an earlier run or another part: this run found it so and wrote nothing
    empty_splits: tuple = ()  # splits asked for without a frame: the output holds none of them
    files: list = field(default_factory=list)  # what the last step wrote (relative to ``out``)
    notes: list = field(default_factory=list)  # lines for the user
    extra: dict = field(default_factory=dict)  # the recipe's own counts (export: {"sdf_sources": ...})

    @property
    def items_per_second(self) -> float:
        return self.written / self.seconds if self.seconds else 0.0


def run_task(task: ShardTask, workers: int = 1, part: tuple[int, int] = (0, 1), progress: bool = True,
             executor: Callable | None = None) -> RunSummary:
    """Run the units of ``task`` that ``part`` owns and that are not done yet; returns what the run did.

    Args:
        task: the pipeline's task (see the module docstring).
        workers: worker processes (``<= 1``: this process, unless an ``executor`` is given).
        part: ``(i, N)``: this run does the units with number % N == i.
        progress: show a progress bar (the plan's items, with the rate of items written per second).
        executor: ``executor(fn, jobs, workers, init, initargs)`` yielding ``fn(job)`` per job (default
            :func:`hoidata.engine.pool.run_pool`).
    """
    start = time.perf_counter()
    plan = task.plan
    owned = plan.owned(part)
    kept = task.done(owned, True)
    mine = [n for n in owned if n not in kept]
    task.check_kept([n for n in owned if n in kept])
    result = RunSummary(units=plan.units, items=plan.items, units_kept=len(owned) - len(mine))
    bar = tqdm(total=sum(plan.size(n) for n in mine), desc=task.desc, unit="item", disable=not progress)
    results = _results(task, [task.job(n) for n in mine], workers, executor) if mine else iter(())
    try:
        _tally(results, plan, result, bar, start)
    finally:
        bar.close()
        if hasattr(results, "close"):
            results.close()  # an interrupted run: the serial context is closed now, the pool's workers stopped
    result.seconds = time.perf_counter() - start
    # done before, written now, or reported done now (another part's): a task without done() is complete when this
    # run wrote every unit
    result.all_done = set(kept) | set(mine) | task.done(plan.units, False) >= set(plan.units)
    return result


def _results(task: ShardTask, jobs: list, workers: int, executor: Callable | None):
    """Every job's result: here in one context (closed at the end), or from the executor's processes."""
    if workers <= 1 and executor is None:
        context = open_worker(task.worker)
        try:
            for job in jobs:
                yield context.run(job)
        finally:
            context.close()
        return
    if executor is None:
        from hoidata.engine.pool import run_pool as executor
    yield from executor(partial(_run_in_process, task.worker), jobs, workers, _open_in_process, (task.worker,))


def open_worker(spec) -> WorkerContext:
    """``spec.open()``; a failure is one WorkerError line naming it (what a worker process reports too)."""
    try:
        return spec.open()
    except WorkerError:
        raise
    except Exception as exc:
        raise WorkerError(None, None, describe_failure(type(spec).open, exc)) from exc


def _tally(results, plan: Plan, result: RunSummary, bar, start: float) -> None:
    for number, written, skips in results:
        result.written += written
        result.units_written += 1
        result.empty_units += written == 0
        result.skipped += skips
        bar.update(plan.size(number))
        bar.set_postfix(per_s=f"{result.written / max(time.perf_counter() - start, 1e-9):.2f}")


# --- worker process side -------------------------------------------------------------------------------------------

# In a worker process: spec -> its open context. The one place a task's per-process state is kept (the executors
# keep only their own bookkeeping: which initialisers ran or failed).
_OPEN: dict = {}


def _open_in_process(spec) -> None:
    """Open ``spec``'s context in this process, once; it is closed when the process exits."""
    if spec in _OPEN:
        return
    _OPEN[spec] = open_worker(spec)
    if len(_OPEN) == 1:
        import atexit
        from multiprocessing import util

        util.Finalize(None, _close_all, exitpriority=10)  # a pool worker exits through these, not atexit
        atexit.register(_close_all)


def _run_in_process(spec, job):
    _open_in_process(spec)  # an executor without initialisers opens it on the first job
    return _OPEN[spec].run(job)


def _close_all() -> None:
    while _OPEN:
        _, context = _OPEN.popitem()
        try:
            context.close()
        except Exception:  # noqa: BLE001, S110 - the process is ending; a failing close must not hide its result
            pass
