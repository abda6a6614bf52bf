"""Evaluation of a checkpoint, on top of :mod:`hoisdf.scoring` (which scores any method's files and imports no
model code): :mod:`~hoisdf.evaluation.inference` (the model over stores), :mod:`~hoisdf.evaluation.model_scores`
(the paper's numbers of the collected predictions, the mean-pose baseline, plausibility of the model's hands),
:mod:`~hoisdf.evaluation.outputs` and :mod:`~hoisdf.evaluation.visualize` (what a run writes). The CLI is
:mod:`hoisdf.evaluate`."""
