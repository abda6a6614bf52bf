"""Issue 44, part 2: every reader of the project fed one corpus of damaged files (tests/reading_corpus.py: missing,
a folder, empty, random bytes, not UTF-8, cut in half, JSON nested 100,000 deep, a number as a string, a boolean or
NaN, a bad CRC, a duplicate member), each answered by one DataError line naming the file (and the member), never a
traceback, and taken without a word only where the reader's contract is lenient (docs/reliability.md,
section 22).

The walk is checked from both sides: a file read outside the door (:mod:`hoidata.reading`) fails
test_reading.py's source scan, and a reader through the door that no case here feeds fails the coverage check
below (every function that calls the door, found in the source, must have been seen calling it: the door's entries
are wrapped, wherever they were imported, by a recorder of their caller).
"""

from __future__ import annotations

import functools
import re
import sys

import pytest
from door_walk import DOOR, READER_ENTRIES, door_readers
from reading_cases import arctic_cases, data_cases, hot3d_cases, scorer_cases, store_cases, training_cases
from reading_corpus import DAMAGES

from hoidata.errors import DataError


def _names_the_file(message: str, path, damage: str) -> bool:
    places = [path] + (list(path.parents)[:3] if damage in ("missing", "folder") else [])
    return any(str(p) in message for p in places)


def outcome(case, damage, folder) -> str | None:
    """What went wrong when ``case`` read ``damage`` (None: refused in one line naming the file and member, or a
    damage its contract lets it take); "n/a" where the damage does not apply to the format."""
    path = case.place(folder, damage)
    if path is None:
        return "n/a"
    try:
        case.read(path)
    except DataError as exc:
        text = str(exc)
        shown = case.shows or case.member
        if "\n" in text or not _names_the_file(text, path, damage) or (shown and shown not in text):
            return f"refused without naming {path.name}{' and ' + shown if shown else ''}: {text}"
        return None
    except Exception as exc:  # noqa: BLE001 - the defect this test exists for
        return f"traceback: {type(exc).__name__}: {str(exc)[:300]}"
    if damage is not None and damage not in case.accepts:
        return "taken without a word"
    return None


def _record_callers(monkeypatch) -> set:
    """Every door entry replaced, in the door and in every module of the project that imported it, by a wrapper
    that records (module, function) of its caller; returns the set it fills."""
    from hoidata import reading, reading_media

    seen = set()

    def wrap(fn):
        @functools.wraps(fn)
        def recorded(*args, **kwargs):
            caller = sys._getframe(1)
            module = caller.f_globals.get("__name__", "")
            if module not in DOOR:  # a comprehension or lambda is its function's
                seen.add((module, re.sub(r"(\.<locals>\.<(listcomp|dictcomp|setcomp|genexpr|lambda)>)+$", "",
                                         caller.f_code.co_qualname)))
            return fn(*args, **kwargs)
        return recorded

    entries = {getattr(m, n): wrap(getattr(m, n)) for m in (reading, reading_media) for n in READER_ENTRIES
               if hasattr(m, n)}
    for module in list(sys.modules.values()):
        if getattr(module, "__name__", "").split(".")[0] in ("hoidata", "hoisdf"):
            for name in READER_ENTRIES:
                value = getattr(module, name, None)
                if callable(value) and value in entries:
                    monkeypatch.setattr(module, name, entries[value])
    return seen


@pytest.fixture(scope="module")
def manos(mano_dir):
    import torch

    from hoidata.hand import load_mano

    return {side: load_mano(mano_dir, side=side, fix_left_shapedirs=True, dtype=torch.float64)
            for side in ("left", "right")}


def test_every_reader_refuses_the_corpus_in_one_line(tmp_path, mano_dir, manos, monkeypatch):
    cases = (scorer_cases() + hot3d_cases(mano_dir, manos) + store_cases(tmp_path / "setup") +
             data_cases(tmp_path / "setup") + training_cases(tmp_path / "setup") + arctic_cases(tmp_path / "setup"))
    for name in ("hoisdf.scoring.arctic_files", "hoisdf.scoring.torch_files", "hoidata.safe_pickle"):
        __import__(name)  # every reader's module loaded before the door's entries are wrapped
    seen = _record_callers(monkeypatch)
    problems, applied = [], 0
    for i, case in enumerate(cases):
        for damage in (None, *DAMAGES):
            problem = outcome(case, damage, tmp_path / f"{i}-{damage or 'valid'}")
            applied += problem != "n/a"
            if problem not in (None, "n/a"):
                problems.append(f"{case.name} / {damage or 'valid file'}: {problem}")
    assert not problems, f"{len(problems)} of {applied}:\n" + "\n".join(problems)
    unfed = sorted(door_readers() - seen)
    assert not unfed, f"readers through the door that no corpus case reached: {unfed}"
