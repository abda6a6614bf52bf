"""Where the shard jobs of a part-splittable command run: ``--launcher local | slurm | ray``.

- ``local`` (default): this process and a pool of ``--workers`` processes; ``--part`` explicit, else taken from a
  Slurm array task's environment (:func:`hoidata.engine.slurm.array_part`), else the whole job.
- ``slurm``: ``--slurm-array N`` parts submitted as one job array through submitit, each task a pool of
  ``--slurm-cpus`` workers; waits for them, or with ``--dry-run`` prints the equivalent ``sbatch`` line.
- ``ray``: every shard job a Ray task on the cluster at ``--ray-address`` (a local Ray instance of ``--workers``
  CPUs without it); ``--part`` works as with ``local``.

The commands give :func:`launch` a ``task(workers=, part=, progress=, executor=)``; the shards do not depend on the
launcher, and every launcher resumes the same way.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import os
import shutil
import time
from collections.abc import Callable

from hoidata.errors import DataError
from hoidata.engine import slurm
from hoidata.engine.engine import RunSummary

LAUNCHERS = {  # name -> where the jobs run (--launcher's choices and help are made from this table)
    "local": "a process pool on this machine (default)",
    "slurm": "a Slurm job array, through submitit",
    "ray": "Ray tasks on a Ray cluster",
}
# what an array task's command line leaves out: where the jobs run, and the part and workers (the task's own)
_NOT_FORWARDED = {"launcher", "ray_address", "slurm_array", "slurm_partition", "slurm_cpus", "slurm_time",
                  "slurm_extra", "slurm_executor", "dry_run", "part", "workers", "help"}
_SUMMED = ("written", "units_written", "units_kept")  # this run's counts (RunSummary)


def add_launcher_flags(parser: argparse.ArgumentParser, count_type) -> None:
    """The ``--launcher`` options of a command (see the module docstring)."""
    g = parser.add_argument_group("where the jobs run (docs/cluster.md)")
    g.add_argument("--launcher", choices=tuple(LAUNCHERS), default="local",
                   help="; ".join(f"{name}: {text}" for name, text in LAUNCHERS.items()))
    g.add_argument("--ray-address", default=None, help="ray: the cluster to join (default: start a local Ray)")
    g.add_argument("--slurm-array", type=count_type(1), default=None, metavar="N", help="slurm: array tasks (parts)")
    g.add_argument("--slurm-partition", default=None, metavar="P", help="slurm: the partition to submit to")
    g.add_argument("--slurm-cpus", type=count_type(1), default=None, metavar="C",
                   help="slurm: CPUs per task, the task's worker processes (default --workers)")
    g.add_argument("--slurm-time", default="240", metavar="T", help="slurm: time limit per task, minutes or D-HH:MM:SS")
    g.add_argument("--slurm-extra", action="append", default=[], metavar="KEY=VALUE",
                   help="slurm: another sbatch option, e.g. account=lab (repeatable)")
    g.add_argument("--slurm-executor", choices=("slurm", "local", "debug"), default="slurm",
                   help="slurm: submitit's executor; 'local' runs the array's tasks as processes here (a trial run)")
    g.add_argument("--dry-run", action="store_true", help="slurm: print the sbatch line instead of submitting")


def _slurm_options(args) -> slurm.SlurmOptions:
    if args.slurm_array is None:
        raise ValueError("--launcher slurm needs --slurm-array N (the number of parts)")
    if args.part is not None:
        raise ValueError("--part is not used with --launcher slurm: the array's N tasks are the parts")
    extra = {}
    for item in args.slurm_extra:
        key, sep, value = item.partition("=")
        if not sep or not key.strip("-"):
            raise ValueError(f"--slurm-extra: expected KEY=VALUE, got {item!r}")
        extra[key.strip("-")] = value
    return slurm.SlurmOptions(args.slurm_array, args.slurm_cpus or args.workers, slurm.slurm_minutes(args.slurm_time),
                              args.slurm_partition, extra, args.slurm_executor)


def task_command(parser: argparse.ArgumentParser, args: argparse.Namespace, command: str, workers: int) -> list[str]:
    """The command line an array task runs, rebuilt from the PARSED values of ``args`` (never from the typed
    text: argparse takes abbreviations such as ``--launch`` or ``--slurm-arr``, which a filter of exact names
    would let through, and every task would submit an array again).

    Every option of ``parser`` but the launcher's, ``--part`` and ``--workers`` is written under its full name as
    ``--name=value`` (a value may start with ``-``), flags by name, values equal to the default left out;
    then ``--workers N`` and the positional overrides. ``hoidata`` parses it back to the same values.
    """
    line, positional = ["hoidata", command], []
    for action in parser._actions:  # noqa: SLF001 - argparse has no public list of a parser's arguments
        if action.dest in _NOT_FORWARDED or action.dest == argparse.SUPPRESS:
            continue
        value = getattr(args, action.dest, action.default)
        if not action.option_strings:
            positional += [str(v) for v in (value or [])]
        elif value != action.default:
            flag = max(action.option_strings, key=len)
            if action.nargs == 0:  # store_true / store_const
                line.append(flag)
            else:
                text = ",".join(map(str, value)) if isinstance(value, (tuple, list)) else str(value)
                line.append(f"{flag}={text}")
    separator = ["--"] if any(p.startswith("-") for p in positional) else []
    return [*line, "--workers", str(workers), *separator, *positional]


def refuse_nested_array(environ=os.environ) -> None:
    """Refuse to submit an array from inside a Slurm array task: with N tasks each submitting N more, only the
    cluster's job limits would stop it (the array's own tasks take their part from the environment instead)."""
    task = environ.get("SLURM_ARRAY_TASK_ID")
    if task is not None:
        raise DataError(None, None, f"--launcher slurm: this process runs inside Slurm array task {task} "
                                    "(SLURM_ARRAY_TASK_ID); a task does not submit another array (run the command "
                                    "without --launcher in the array's tasks)")


def require_sbatch(executor: str) -> None:
    """One line, before anything is submitted or written, where ``--launcher slurm`` cannot submit to Slurm."""
    if executor == "slurm" and shutil.which("sbatch") is None:
        raise DataError(None, None, "--launcher slurm: no sbatch on this machine's PATH (not a Slurm login node?); "
                                    "--dry-run prints the sbatch line to run where Slurm is, --slurm-executor "
                                    "local runs the parts here")


def merge(summaries: list[RunSummary]) -> RunSummary:
    """One summary of an array's parts: the finisher's (whole-output skips, the last step's state) with this run's
    counts summed over the parts. Parts that finish together all end finished, but only one writes the last step
    (the others find it written: ``finish_kept``); that one is the finisher, whatever the parts' order."""
    finishers = [s for s in summaries if s.finished]
    base = next((s for s in finishers if not s.finish_kept), finishers[0] if finishers else summaries[-1])
    return dataclasses.replace(base, **{name: sum(getattr(s, name) for s in summaries) for name in _SUMMED})


def launch(args, task: Callable, command: str) -> RunSummary | None:
    """Run ``task`` where ``args`` says; returns its summary (None after ``--dry-run``)."""
    if args.launcher != "slurm":
        part = slurm.resolve_part(args.part)
        executor = None
        if args.launcher == "ray":
            from hoidata.engine.ray_tasks import run_ray

            executor = functools.partial(run_ray, address=args.ray_address)
        return task(workers=args.workers, part=part, executor=executor)
    options = _slurm_options(args)
    if args.dry_run:
        line = task_command(args.command_parser, args, command, options.cpus)
        print(slurm.sbatch_command(line, options, args.out, f"hoidata-{command}"))
        return None
    refuse_nested_array()
    require_sbatch(options.executor)
    start = time.perf_counter()
    summary = merge(slurm.submit_parts(task, options, args.out, f"hoidata-{command}"))
    if not summary.finished:  # every part ran, yet none saw the others' files (a lagging shared filesystem)
        print("every part finished; checking the store and writing the index here", flush=True)
        final = task(workers=options.cpus, part=(0, 1), executor=None)
        summary = dataclasses.replace(final, **{k: getattr(summary, k) for k in _SUMMED})
    summary.seconds = time.perf_counter() - start
    return summary
