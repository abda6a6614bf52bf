"""Dataset readers: every reader yields :class:`~hoidata.datasets.frame.Frame` records."""

from hoidata.datasets.frame import Frame, Skip

__all__ = ["Frame", "Skip"]
