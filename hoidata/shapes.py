"""Declared shapes of what a file holds, checked at the door (:mod:`hoidata.reading`): numbers are numbers (never
strings, booleans or null), arrays have their shape and finite values, objects the keys a reader uses. The first
mismatch is one DataError naming the file and the field's path (``left.mano_pose.thetas``, ``entry 3: frame_id``,
``xyz_list[0]``), saying what is wrong: ``got 15 numbers, 15 of them NaN``, ``got a string ('1')``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from hoidata.errors import DataError

NUMBER_KINDS = "iuf"  # numpy dtype kinds that are numbers (booleans are not)


def kind_of(value) -> str:
    """What a JSON value is, for messages: ``a string ('1')``, ``a boolean (true)``, ``null``, ``a list``, ..."""
    if isinstance(value, bool):
        return f"a boolean ({str(value).lower()})"
    if value is None:
        return "null"
    if isinstance(value, str):
        return f"a string ({value[:20]!r}{'...' if len(value) > 20 else ''})"
    if isinstance(value, float):
        return f"the number {value!r}"
    if isinstance(value, int):
        return "a number"
    if isinstance(value, dict):
        return "an object"
    if isinstance(value, (list, tuple)):
        return "a list"
    return f"a {type(value).__name__}"


def first_non_number(value, where: tuple = ()) -> tuple[tuple, object] | None:
    """(index path, value) of the first leaf of nested lists that is not a number (bool and None are not), or None."""
    if isinstance(value, (list, tuple)):
        if all(type(x) is float or type(x) is int for x in value):  # the common leaf row, in one pass
            return None
        for i, item in enumerate(value):
            found = first_non_number(item, (*where, i))
            if found is not None:
                return found
        return None
    if type(value) is float or type(value) is int:
        return None
    return where, value


def describe(shape) -> str:
    """``(15,)`` -> ``15``, ``(None, 21, 3)`` -> ``(N, 21, 3)``."""
    if shape is None:
        return "an array of"
    if len(shape) == 1 and shape[0] is not None:
        return str(shape[0])
    return "(" + ", ".join("N" if s is None else str(s) for s in shape) + ")"


def _fits(got: tuple, shape) -> bool:
    return shape is None or (len(got) == len(shape) and all(s is None or s == g for s, g in zip(shape, got)))


def not_finite(arr: np.ndarray) -> str | None:
    """``'3 of them NaN'``, ``'1 of them infinite'``, ``'2 NaN and 1 infinite'``, or None when all are finite."""
    if arr.dtype.kind != "f":
        return None
    nan, inf = int(np.isnan(arr).sum()), int(np.isinf(arr).sum())
    if not nan and not inf:
        return None
    if nan and inf:
        return f"{nan} NaN and {inf} infinite"
    return f"{nan or inf} of them {'NaN' if nan else 'infinite'}"


def numbers(value, path, field: str | None, shape: tuple | None = None, finite: bool = True, count: int | None = None,
            plain: bool = False) -> np.ndarray:
    """``value`` (nested JSON lists, a number, or a numpy array) as a float64 array.

    Args:
        shape: the array's shape, None for a free size (``(None, 21, 3)``); None: any shape.
        finite: NaN and infinity refused. count: the number of values, whatever the nesting (``shape`` None).
        plain: ``value`` is known to hold numbers only (:func:`hoidata.reading.numbers_only` of its file), so
            the per-leaf walk is skipped.

    A string, boolean or null where a number belongs, a ragged list, another shape and a NaN are each a DataError
    naming ``field`` and what was found.
    """
    want = describe(shape if count is None else (count,))
    if isinstance(value, np.ndarray):
        if value.dtype.kind not in NUMBER_KINDS:
            raise DataError(path, field, f"expected numbers, got an array of {value.dtype} values")
        arr = value.astype(np.float64, copy=False)
    else:
        bad = None if plain else first_non_number(value)
        if bad is not None:
            at = "".join(f"[{i}]" for i in bad[0])
            raise DataError(path, field, f"expected numbers, got {kind_of(bad[1])}{' at ' + at if at else ''}")
        try:
            arr = np.asarray(value, dtype=np.float64)
        except (ValueError, TypeError):
            raise DataError(path, field, f"expected {want} numbers, got a ragged list") from None
    if count is not None and arr.size != count:
        raise DataError(path, field, f"expected {count} numbers, got {arr.size}")
    if not _fits(arr.shape, shape):
        raise DataError(path, field, f"expected {want} numbers, got shape {arr.shape}")
    problem = not_finite(arr) if finite else None
    if problem:
        raise DataError(path, field, f"expected {want} finite numbers, got {arr.size} numbers, {problem}")
    return arr


# ---------------------------------------------------------------- declared shapes of JSON values


def join(parent: str | None, child: str) -> str:
    """A field path one step down: ``a`` + ``[3]`` -> ``a[3]``, ``a`` + ``b`` -> ``a.b``, ``entry 3`` + ``b`` ->
    ``entry 3: b``."""
    if not parent:
        return child
    if child.startswith("["):
        return parent + child
    return parent + (": " if " " in parent.rsplit(": ", 1)[-1] else ".") + child


@dataclass(frozen=True)
class Numbers:
    """An array of numbers of ``shape`` (None for a free size; None: any), finite unless said."""

    shape: tuple | None = None
    finite: bool = True


@dataclass(frozen=True)
class Integer:
    """A whole number (never a boolean or a float) within [lo, hi]."""

    lo: int | None = None
    hi: int | None = None


@dataclass(frozen=True)
class String:
    pass


@dataclass(frozen=True)
class ListOf:
    """A list of items of one shape; ``label`` names item i (``"[{}]"``: ``entries[3]``; ``"entry {}"``)."""

    item: object
    label: str = "[{}]"


@dataclass(frozen=True)
class MapOf:
    """An object with any keys, each value of one shape."""

    value: object


@dataclass(frozen=True)
class Record:
    """An object with ``required`` keys (missing is an error) and ``optional`` ones; other keys are let be."""

    required: dict = field(default_factory=dict)
    optional: dict = field(default_factory=dict)


ANY = object()  # any value, unchecked


def check(value, shape, path, field: str | None = None):
    """``value`` checked against the declared ``shape`` (Numbers become float64 arrays, lists and objects are
    rebuilt with their checked items); the first mismatch is a DataError naming ``path`` and the field's path."""
    if shape is ANY:
        return value
    if isinstance(shape, Numbers):
        return numbers(value, path, field, shape.shape, shape.finite)
    if isinstance(shape, Integer):
        if isinstance(value, bool) or not isinstance(value, int):
            raise DataError(path, field, f"expected a whole number, got {kind_of(value)}")
        if (shape.lo is not None and value < shape.lo) or (shape.hi is not None and value > shape.hi):
            raise DataError(path, field, f"{value} is outside [{shape.lo}, {shape.hi}]")
        return value
    if isinstance(shape, String):
        if not isinstance(value, str):
            raise DataError(path, field, f"expected a string, got {kind_of(value)}")
        return value
    if isinstance(shape, ListOf):
        if not isinstance(value, list):
            raise DataError(path, field, f"expected a list, got {kind_of(value)}")
        return [check(v, shape.item, path, join(field, shape.label.format(i))) for i, v in enumerate(value)]
    if isinstance(shape, (MapOf, Record)):
        if not isinstance(value, dict):
            raise DataError(path, field, f"expected an object, got {kind_of(value)}")
        if isinstance(shape, MapOf):
            return {k: check(v, shape.value, path, join(field, str(k))) for k, v in value.items()}
        missing = [k for k in shape.required if k not in value]
        if missing:
            raise DataError(path, join(field, missing[0]), "missing")
        out = dict(value)
        for key, sub in (*shape.required.items(), *shape.optional.items()):
            if key in value:
                out[key] = check(value[key], sub, path, join(field, key))
        return out
    raise TypeError(f"not a declared shape: {shape!r}")
