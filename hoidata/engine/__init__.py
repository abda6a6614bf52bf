"""The engine floor: work cut into numbered units, planned, resumed and run in parallel, whatever the work is.

:mod:`~hoidata.engine.engine` (plan, resume, run, progress, the run's summary), :mod:`~hoidata.engine.pool`
(process pools that cannot hang), :mod:`~hoidata.engine.ray_tasks` (Ray tasks with the pool's contract),
:mod:`~hoidata.engine.launch` and :mod:`~hoidata.engine.slurm` (``--launcher``: local, a Slurm array, Ray).
It knows nothing of records, stores or datasets: the recipes (build-sdf, render-synthetic, export, the toy writer)
hand it a task.
"""
