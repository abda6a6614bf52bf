"""The engine floor: work cut into numbered units, planned, resumed and run in parallel, whatever the work is.

:mod:`~hoidata.engine.engine` (plan, resume, run, progress, the run's summary), :mod:`~hoidata.engine.pool`
(process pools that cannot hang), :mod:`~hoidata.engine.ray_tasks` (Ray tasks with the pool's contract),
:mod:`~hoidata.engine.launch` and :mod:`~hoidata.engine.slurm` (``--launcher``: local, a Slurm array, Ray).
It knows nothing of records, stores or datasets: the recipes (build-sdf, render-synthetic, export, the toy writer)
hand it a task.
"""

from hoidata.engine.engine import Plan, RunSummary, ShardTask, WorkerContext, open_worker, run_task
from hoidata.engine.launch import LAUNCHERS, add_launcher_flags, launch
from hoidata.engine.pool import describe_failure, run_pool

__all__ = ["LAUNCHERS", "Plan", "RunSummary", "ShardTask", "WorkerContext", "add_launcher_flags", "describe_failure",
           "launch", "open_worker", "run_pool", "run_task"]
