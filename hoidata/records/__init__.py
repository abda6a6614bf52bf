"""Building stores: :mod:`~hoidata.pipeline.settings` (``pipelines/<name>.toml``), :mod:`~hoidata.pipeline.records`
(one frame -> one record), :mod:`~hoidata.pipeline.engine` (work in numbered units: plan, resume, run in parallel),
:mod:`~hoidata.pipeline.worker` (a process's MANO layers, objects and renderers; one shard of records),
:mod:`~hoidata.pipeline.runner` (build-sdf: frames -> shards, a recipe on the engine) and
:mod:`~hoidata.pipeline.inputs` (readable checks of the MANO files and object folders a build reads)."""
