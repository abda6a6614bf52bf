"""hoisdf: the HOISDF model (CVPR 2024), streamed from hoidata stores into a GPU trainer.

Packages: scoring/ (result files of any method scored offline: ``hoisdf score``; it imports no model code),
model/ (the network), data/ (store streaming, GPU batched augmentation), training/ (losses, trainer, checkpoints),
evaluation/ (a checkpoint run over stores, on top of scoring/); the commands train, evaluate, toy, ablation,
import_upstream. This package may import
:mod:`hoidata`'s public API (schema, hand model), never the reverse.
"""

__version__ = "0.1.0"
