"""Exports: a dataset, read through our readers and a pipeline setting, as the files another codebase's loader reads.

- :mod:`hoidata.export.handoccnet`: the COCO-style annotation files of HandOccNet, H2ONet and HandBooster
  (DexYCB and HO-3D v2);
- :mod:`hoidata.export.gsdf`: gSDF's DexYCB annotation, split lists and ground-truth meshes, with the per-frame
  SDF files of :mod:`hoidata.export.sdf_files` (AlignSDF's format, which gSDF and HOISDF also read);
- :mod:`hoidata.export.job`: the resumable, parallel run (``hoidata export``), :func:`export_dataset`.

``docs/other-codebases.md`` lists, per consumer, the command, the folder it writes and the loader it serves.
"""

from hoidata.export.formats import DATASETS, FORMATS

__all__ = ["DATASETS", "FORMATS", "default_splits", "export_dataset"]


def __getattr__(name: str):
    """The job's names on first use: ``hoidata --help`` lists the formats without importing the exporters."""
    if name in ("default_splits", "export_dataset"):
        from hoidata.export import job

        return getattr(job, name)
    raise AttributeError(f"module 'hoidata.export' has no attribute {name!r}")
