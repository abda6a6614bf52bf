"""One error type for bad input files, so every message names the file and the field."""

from __future__ import annotations

import os


class DataError(ValueError):
    """A file the user gave us is missing, malformed or inconsistent.

    The message always starts with the file path, then the field (key, member, column) that is
    wrong, then what is wrong with it, e.g. ``MANO_RIGHT.pkl: 'posedirs': expected shape (778, 3, 135), got (778, 3)``.
    """

    def __init__(self, path: str | os.PathLike | None, field: str | None, problem: str):
        self.path = None if path is None else os.fspath(path)
        self.field = field
        self.problem = problem
        parts = [p for p in (self.path, None if field is None else repr(field)) if p]
        super().__init__(": ".join(parts + [problem]))
