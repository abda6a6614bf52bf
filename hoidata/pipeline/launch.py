"""Where the shard jobs of a part-splittable command run: ``--launcher local | slurm | ray``.

- ``local`` (default): this process and a pool of ``--workers`` processes; ``--part`` explicit, else taken from a
  Slurm array task's environment (:func:`hoidata.pipeline.slurm.array_part`), else the whole job.
- ``slurm``: ``--slurm-array N`` parts submitted as one job array through submitit, each task a pool of
  ``--slurm-cpus`` workers; waits for them, or with ``--dry-run`` prints the equivalent ``sbatch`` line.
- ``ray``: every shard job a Ray task on the cluster at ``--ray-address`` (a local Ray instance of ``--workers``
  CPUs without it); ``--part`` works as with ``local``.

The commands give :func:`launch` a ``task(workers=, part=, progress=, engine=)``; the shards do not depend on the
launcher, and every launcher resumes the same way.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import time
from collections.abc import Callable, Sequence

from hoidata.pipeline import slurm

LAUNCHERS = ("local", "slurm", "ray")
_VALUED = ("--launcher", "--ray-address", "--slurm-partition", "--slurm-array", "--slurm-cpus", "--slurm-time",
           "--slurm-extra", "--slurm-executor", "--part", "--workers")
_FLAGS = ("--dry-run",)
_SUMMED = ("records", "shards_written", "shards_kept", "chunks_written", "chunks_kept")  # this run's counts


def add_launcher_flags(parser: argparse.ArgumentParser, count_type) -> None:
    """The ``--launcher`` options of a command (see the module docstring)."""
    g = parser.add_argument_group("where the jobs run (docs/cluster.md)")
    g.add_argument("--launcher", choices=LAUNCHERS, default="local",
                   help="local pool (default), a Slurm array through submitit, or Ray tasks")
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


def without_launcher(argv: Sequence[str]) -> list[str]:
    """A command line without its launcher options, ``--part`` and ``--workers`` (the array task's line)."""
    out, skip = [], 0
    for item in argv:
        if skip:
            skip -= 1
        elif item in _VALUED:
            skip = 1
        elif item not in _FLAGS and not item.startswith(tuple(f"{v}=" for v in _VALUED)):
            out.append(item)
    return out


def merge(summaries: list):
    """One summary of an array's parts: the finisher's (whole-store skips, index state) with this run's counts
    summed over the parts."""
    base = next((s for s in summaries if getattr(s, "index_written", False) or getattr(s, "finished", False)),
                summaries[-1])
    counts = {f.name: sum(getattr(s, f.name) for s in summaries) for f in dataclasses.fields(base) if f.name in _SUMMED}
    return dataclasses.replace(base, **counts)


def launch(args, task: Callable, command: str, finished: Callable = lambda s: s.index_written):
    """Run ``task`` where ``args`` says; returns its summary (None after ``--dry-run``)."""
    if args.launcher != "slurm":
        part = slurm.resolve_part(args.part)
        engine = None
        if args.launcher == "ray":
            from hoidata.pipeline.ray_tasks import run_ray

            engine = functools.partial(run_ray, address=args.ray_address)
        return task(workers=args.workers, part=part, engine=engine)
    options = _slurm_options(args)
    if args.dry_run:
        line = ["hoidata", command, *without_launcher(args.argv[1:]), "--workers", str(options.cpus)]
        print(slurm.sbatch_command(line, options, args.out, f"hoidata-{command}"))
        return None
    start = time.perf_counter()
    summary = merge(slurm.submit_parts(task, options, args.out, f"hoidata-{command}"))
    if not finished(summary):  # every part ran, yet none saw the others' files (a lagging shared filesystem)
        print("every part finished; checking the store and writing the index here", flush=True)
        final = task(workers=options.cpus, part=(0, 1), engine=None)
        summary = dataclasses.replace(final, **{k: getattr(summary, k) for k in _SUMMED if hasattr(summary, k)})
    summary.seconds = time.perf_counter() - start
    return summary
