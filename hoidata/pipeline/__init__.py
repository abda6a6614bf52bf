"""Building stores: :mod:`~hoidata.pipeline.settings` (``pipelines/<name>.toml``), :mod:`~hoidata.pipeline.records`
(one frame -> one record), :mod:`~hoidata.pipeline.runner` (frames -> shards, parallel and resumable) and
:mod:`~hoidata.pipeline.inputs` (readable checks of the MANO files and object folders a build reads)."""
