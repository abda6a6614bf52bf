"""hoidata: offline pipelines that turn hand-object datasets into training-ready stores.

The offline half of the project: MANO hand model, object meshes, dataset readers, SDF sampling,
rendering and shard writing. It never imports :mod:`hoisdf`.
"""

__version__ = "0.1.0"
