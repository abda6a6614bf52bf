"""Dataset readers: every reader yields :class:`~hoidata.datasets.frame.Frame` records; :func:`open_reader` opens
one by name and :func:`read_splits` reads the splits of a build (:mod:`hoidata.datasets.open`)."""

from hoidata.datasets.frame import Frame, Skip
from hoidata.datasets.open import DATASETS, SplitFrames, open_reader, read_splits

__all__ = ["DATASETS", "Frame", "Skip", "SplitFrames", "open_reader", "read_splits"]
