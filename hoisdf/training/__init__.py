"""Training: :mod:`~hoisdf.training.losses` (one method per term), :mod:`~hoisdf.training.trainer` (the
loop, validation, logs) and :mod:`~hoisdf.training.checkpoint` (exact resume). The CLI is
:mod:`hoisdf.train`."""
