"""Evaluation: :mod:`~hoisdf.evaluation.inference` (a checkpoint over stores), :mod:`~hoisdf.scoring.metrics`
and :mod:`~hoisdf.evaluation.model_scores` (the paper's numbers), :mod:`~hoisdf.scoring.plausibility`
(with :mod:`~hoisdf.scoring.solids`; any method's files: :mod:`~hoisdf.scoring.score_contact`),
:mod:`~hoisdf.scoring.submissions` (the official evaluators' files), :mod:`~hoisdf.evaluation.outputs`
and :mod:`~hoisdf.evaluation.visualize` (what a run writes). The CLI is :mod:`hoisdf.evaluate`."""
