"""Evaluation: :mod:`~hoisdf.evaluation.inference` (a checkpoint over stores), :mod:`~hoisdf.evaluation.metrics`
and :mod:`~hoisdf.evaluation.scoring` (the paper's numbers), :mod:`~hoisdf.evaluation.plausibility`
(with :mod:`~hoisdf.evaluation.solids`; any method's files: :mod:`~hoisdf.evaluation.score_contact`),
:mod:`~hoisdf.evaluation.submissions` (the official evaluators' files), :mod:`~hoisdf.evaluation.outputs`
and :mod:`~hoisdf.evaluation.visualize` (what a run writes). The CLI is :mod:`hoisdf.evaluate`."""
