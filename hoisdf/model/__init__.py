"""The HOISDF model (see :mod:`hoisdf.model.hoisdf`), its parts and its builder from
:class:`hoisdf.config.ModelSettings` (:mod:`hoisdf.model.build`)."""

from __future__ import annotations

from hoisdf.model.build import build_model
from hoisdf.model.hoisdf import HOISDF

__all__ = ["HOISDF", "build_model"]
