"""Scoring result files of any method: the package a user who only scores files reads. It imports no model,
trainer or data-loading code (``tests/test_layout.py`` holds it to that); :mod:`hoisdf.evaluation` (running a
checkpoint, its per-run outputs and pictures) stands above it and uses it.

- the command: :mod:`~hoisdf.scoring.cli` (``hoisdf score``; ``python -m hoisdf.scoring``), one module per
  subcommand: :mod:`~hoisdf.scoring.score_ho3d`, :mod:`~hoisdf.scoring.score_dexycb`,
  :mod:`~hoisdf.scoring.score_contact`, :mod:`~hoisdf.scoring.score_recon`, :mod:`~hoisdf.scoring.score_hot3d`,
  :mod:`~hoisdf.scoring.score_arctic`; ``hoisdf check``: :mod:`~hoisdf.scoring.check_cli`;
- pose metrics as the official evaluators compute them: :mod:`~hoisdf.scoring.metrics`,
  :mod:`~hoisdf.scoring.official`;
- ARCTIC's leaderboard: :mod:`~hoisdf.scoring.arctic_metrics` (its metrics), :mod:`~hoisdf.scoring.arctic_files`
  (submissions and ground truth, checked), :mod:`~hoisdf.scoring.torch_files` (``.pt`` files read without torch);
- the official result files, read and written: :mod:`~hoisdf.scoring.submissions`,
  :mod:`~hoisdf.scoring.ho3d_list` (HO-3D's evaluation list), :mod:`~hoisdf.scoring.results_json`;
- contact and penetration: :mod:`~hoisdf.scoring.plausibility` on :mod:`~hoisdf.scoring.solids` and
  :mod:`~hoisdf.scoring.cell_volume` (exact volumes), :mod:`~hoisdf.scoring.contact_legacy` (older papers'
  definitions);
- reconstruction: :mod:`~hoisdf.scoring.recon_files` (mesh folders), :mod:`~hoisdf.scoring.recon_gsdf` (gSDF's
  sampled protocol), :mod:`~hoisdf.scoring.recon_exact` (surface integrals with proven bounds).
"""
