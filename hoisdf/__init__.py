"""hoisdf: the HOISDF model (CVPR 2024), streamed from hoidata stores into a GPU trainer.

Modules: data (store streaming), augment (GPU batched augmentation), model/ (the network), losses, trainer +
train (the CLI), evaluate, metrics, export, plausibility, visualize. This package may import
:mod:`hoidata`'s public API (schema, hand model), never the reverse.
"""

__version__ = "0.1.0"
