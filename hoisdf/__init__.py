"""hoisdf: the HOISDF model (CVPR 2024), streamed from hoidata stores into a GPU trainer.

The model, losses, data pipeline and trainer are built in later milestones; this package may import
:mod:`hoidata`'s public API (schema, hand model), never the reverse.
"""

__version__ = "0.1.0"
