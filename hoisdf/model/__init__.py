"""The HOISDF model (see :mod:`hoisdf.model.hoisdf`) and its builder from :class:`hoisdf.config.ModelSettings`."""

from __future__ import annotations

from dataclasses import asdict

from hoisdf.model.hoisdf import HOISDF


def build_model(settings, mano) -> HOISDF:
    """HOISDF from a ModelSettings dataclass (its fields are the constructor's keyword arguments)."""
    return HOISDF(mano, **asdict(settings))


__all__ = ["HOISDF", "build_model"]
