"""Slurm job arrays for the part-splittable commands (``build-sdf``, ``render-synthetic``, ``export``).

A build is cut into parts (``--part i/N``: shards k with k % N == i); an array of N tasks runs one part each. Three
ways in, all giving the same shards as one local run:

- a hand-written ``sbatch`` script (``scripts/sbatch_build.sh``) or ``--dry-run``'s line: the command runs in each
  task without ``--part``, which :func:`array_part` reads from the task's environment;
- ``--launcher slurm``: :func:`submit_parts` submits the array through submitit (the ``cluster`` extra) and waits
  for every task; with ``--slurm-executor local`` the same tasks run as processes on this machine (a trial run).

Whichever task finishes last writes the index (:func:`hoidata.records.store_writer.finish_store`, serialised by a
lock, so tasks may finish in any order, and a rerun task or the launcher finds the index written and writes
nothing).
"""

from __future__ import annotations

import os
import re
import shlex
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from hoidata.errors import DataError, WorkerError

PARTS_VARIABLE = "HOIDATA_PARTS"  # the array's part count, set by the templates so one task can be resubmitted
LOG_FOLDER = ".slurm"  # inside the output folder: submitit's pickles and every task's log


def array_part(environ: Mapping[str, str] = os.environ) -> tuple[int, int] | None:
    """(i, N) of this Slurm array task, or None outside an array.

    With ``HOIDATA_PARTS=N`` set (the templates and ``--dry-run``'s line set it): part ``SLURM_ARRAY_TASK_ID``
    of N, so resubmitting one task (``sbatch --array=5 ...``) builds part 5 of N. Otherwise the array's own
    shape: tasks MIN, MIN+STEP, ... (``SLURM_ARRAY_TASK_MIN`` / ``_STEP``, default 0 / 1) are parts 0, 1, ... of
    ``SLURM_ARRAY_TASK_COUNT``, so ``--array=1-8`` and ``--array=0-14:2`` work too. A task that fits neither
    (``--array=1,4,9``) is an error asking for ``--part``.
    """
    if "SLURM_ARRAY_TASK_ID" not in environ:
        return None
    try:
        task = int(environ["SLURM_ARRAY_TASK_ID"])
        if environ.get(PARTS_VARIABLE):
            index, count = task, int(environ[PARTS_VARIABLE])
            shape = f"{PARTS_VARIABLE}={count}"
        else:
            low, step = int(environ.get("SLURM_ARRAY_TASK_MIN", "0")), int(environ.get("SLURM_ARRAY_TASK_STEP", "1"))
            count = int(environ["SLURM_ARRAY_TASK_COUNT"])
            index, rest = divmod(task - low, max(step, 1))
            index = index if rest == 0 else -1
            shape = f"an array of {count} tasks from {low} in steps of {step}"
    except (KeyError, ValueError) as exc:
        raise DataError(None, "SLURM_ARRAY_TASK_ID", f"cannot read the array task ({exc}); pass --part i/N") from None
    if not 0 <= index < count:
        raise DataError(None, "SLURM_ARRAY_TASK_ID", f"task {task} is not one of {shape}; pass --part i/N")
    return index, count


def resolve_part(explicit: tuple[int, int] | None, environ: Mapping[str, str] = os.environ) -> tuple[int, int]:
    """The part to run: an explicit ``--part`` wins, then the Slurm array task's, else the whole job (0/1)."""
    return explicit or array_part(environ) or (0, 1)


def slurm_minutes(text: str) -> int:
    """A Slurm ``--time`` (``MM``, ``MM:SS``, ``HH:MM:SS``, ``D-HH``, ``D-HH:MM``, ``D-HH:MM:SS``) in whole minutes."""
    match = re.fullmatch(r"(?:(\d+)-)?(\d+)(?::(\d+))?(?::(\d+))?", text.strip())
    if not match:
        raise ValueError(f"--slurm-time: expected minutes or D-HH:MM:SS, got {text!r}")
    days, a, b, c = (int(g) if g else None for g in match.groups())
    if days is None:  # MM, MM:SS, HH:MM:SS
        hours, minutes, seconds = (a, b, c) if c is not None else (0, a, b or 0)
    else:  # D-HH, D-HH:MM, D-HH:MM:SS
        hours, minutes, seconds = a, b or 0, c or 0
    total = ((days or 0) * 24 + hours) * 60 + minutes + (1 if seconds else 0)
    if total < 1:
        raise ValueError(f"--slurm-time: at least one minute, got {text!r}")
    return total


@dataclass
class SlurmOptions:
    """What one array is submitted with: tasks (= parts), CPUs per task (= pool workers), time limit in minutes,
    partition, extra sbatch options (``{"account": "lab"}`` -> ``--account=lab``), submitit's executor."""

    array: int
    cpus: int = 1
    minutes: int = 240
    partition: str | None = None
    extra: dict = field(default_factory=dict)
    executor: str = "slurm"  # or "local" (processes on this machine) / "debug" (in this process)


def sbatch_command(command: Sequence[str], options: SlurmOptions, out: Path, job_name: str) -> str:
    """The one ``sbatch`` line that runs ``command`` (without ``--part``) as an array of ``options.array`` parts."""
    flags = [f"--job-name={job_name}", f"--array=0-{options.array - 1}", f"--cpus-per-task={options.cpus}",
             f"--time={options.minutes}", f"--output={Path(out) / LOG_FOLDER / '%A_%a.log'}",
             f"--export=ALL,{PARTS_VARIABLE}={options.array}"]
    flags += [f"--partition={options.partition}"] if options.partition else []
    flags += [f"--{key}={value}" for key, value in options.extra.items()]
    return shlex.join(["sbatch", *flags, f"--wrap={shlex.join(command)}"])


def run_part(task: Callable, index: int, count: int, workers: int):
    """One array task: ``task(workers=..., part=(index, count), progress=False)`` (module level: submitit pickles
    it)."""
    return task(workers=workers, part=(index, count), progress=False)


def submit_parts(task: Callable, options: SlurmOptions, out: Path, job_name: str) -> list:
    """Submit ``options.array`` parts of ``task`` as one array through submitit, wait for all, return their results
    in part order. Failed parts are one WorkerError naming each part, its job id and its log (the others ran to
    the end; rerunning the same command resumes)."""
    try:
        import submitit
    except ImportError as exc:
        raise ImportError(f"{exc}; --launcher slurm needs submitit (pip install 'hoisdf[cluster]')") from None
    executor = submitit.AutoExecutor(folder=Path(out) / LOG_FOLDER / "%j", cluster=options.executor)
    executor.update_parameters(name=job_name, timeout_min=options.minutes, cpus_per_task=options.cpus,
                               slurm_array_parallelism=options.array, slurm_partition=options.partition,
                               slurm_additional_parameters=dict(options.extra))
    n = options.array
    jobs = executor.map_array(run_part, [task] * n, list(range(n)), [n] * n, [options.cpus] * n)
    job = jobs[0].job_id.split("_")[0]
    print(f"submitted {n} parts as {options.executor} job {job}; logs in {Path(out) / LOG_FOLDER}", flush=True)
    results, failed = [], []
    for index, job in enumerate(jobs):
        try:
            results.append(job.result())
        except Exception as exc:  # noqa: BLE001 - submitit's FailedJobError holds the task's traceback as text
            failed.append(f"part {index}/{n} (job {job.job_id}, log {job.paths.stderr}): {_last_line(exc)}")
    if failed:
        raise WorkerError(None, None, f"{len(failed)} of {n} parts failed; rerun to resume: " + "; ".join(failed))
    return results


def _last_line(exc: BaseException) -> str:
    """The exception line of the task's traceback that submitit's error holds (``hoidata.errors.DataError: x`` ->
    ``DataError: x``), else the error's first line."""
    lines = [line.rstrip() for line in str(exc).splitlines()]
    found = [line for line in lines if re.match(r"^(?:\w+\.)*\w+(?:Error|Exception|Interrupt|Exit)\b", line)]
    text = found[-1] if found else next((line for line in lines if line.strip()), type(exc).__name__)
    return re.sub(r"^(?:\w+\.)+(\w+)", r"\1", text)
