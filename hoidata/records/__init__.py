"""The records floor: what every recipe that writes or reads records borrows.

:mod:`~hoidata.records.settings` (the ``[dataset]`` ``[record]`` ``[store]`` sections of ``pipelines/<name>.toml``),
:mod:`~hoidata.records.records` (one frame -> one record), :mod:`~hoidata.records.upstream` (upstream HOISDF's crops
and frame regions), :mod:`~hoidata.records.worker` (a process's MANO layers, objects and renderers; one shard of
records), :mod:`~hoidata.records.store_writer` (build.json, which shards are done, the skips files and the index),
:mod:`~hoidata.records.fingerprint` (the inputs a resumed build must find unchanged) and
:mod:`~hoidata.records.inputs` (readable checks of the MANO files and object folders a build reads)."""
