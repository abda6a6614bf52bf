"""Pipeline settings files on the ground floor: ``pipelines/<name>.toml`` -> a dict of sections, ``section.key=value``
overrides, and each section checked against the dataclass that reads it.

A pipeline file is shared by its readers: the build reads ``[dataset]``, ``[record]`` and ``[store]``
(:mod:`hoidata.records.settings`), training its own sections (``hoisdf.config``). This module names no section:
every reader passes the sections it reads, and those of the other readers it knows of. Nothing here reads a
settings object: the readers turn the checked sections into their dataclasses and pass explicit values on.

(Not ``hoidata.presets``: an installed wheel already uses that name for the ``pipelines/`` folder, see setup.py.)
"""

from __future__ import annotations

import difflib
import math
from dataclasses import fields
from pathlib import Path

import tomllib

from hoidata.errors import DataError
from hoidata.reading import read_toml

# A checkout's pipelines/ folder; an installed wheel carries the same files as the regular package hoidata.presets
# (pipelines/__init__.py makes it one; setup.py maps the folder to that name).
CHECKOUT_PIPELINES = Path(__file__).resolve().parents[1] / "pipelines"


def pipelines_dir():
    """Where the named pipelines live: the checkout's ``pipelines/`` when there is one, else the installed copy.

    The installed copy is reached through ``importlib.resources`` and returned as its Traversable (a ``Path`` for
    an ordinary install, something else for a zipped or namespace one): callers only use ``joinpath``,
    ``is_file``, ``read_text`` and ``str``, which every Traversable has. ``Path(str(...))`` would break on the
    others (a namespace package's ``MultiplexedPath`` prints as ``MultiplexedPath('...')``).
    """
    if CHECKOUT_PIPELINES.is_dir():
        return CHECKOUT_PIPELINES
    from importlib.resources import files

    return files("hoidata.presets")


def pipeline_names() -> tuple[str, ...]:
    """The named pipelines, sorted: every ``<name>.toml`` of :func:`pipelines_dir` (what the commands' help lists,
    so a new file is listed without another edit)."""
    return tuple(sorted(p.name[:-len(".toml")] for p in pipelines_dir().iterdir() if p.name.endswith(".toml")))


_SCALARS = {"bool": (bool,), "int": (int,), "float": (int, float), "str": (str,)}
_WORDS = {"bool": "true or false", "int": "an integer", "float": "a number", "str": "a string"}


def value_problem(annotation: str, value) -> str | None:
    """Why ``value`` does not fit a settings field annotated ``annotation`` (None when it fits).

    Understands the annotations the settings dataclasses use: bool, int, float (an int is accepted), str, and
    tuples of them, either ``tuple[T, ...]`` or a fixed ``tuple[T, T]``; others are not checked. A bool is
    not an int here. A ``tuple[str, ...]`` is a list of names (splits, hand sides): each may appear once.
    """
    if annotation in _SCALARS:
        ok = isinstance(value, _SCALARS[annotation]) and (annotation == "bool" or not isinstance(value, bool))
        if ok and annotation == "float" and not math.isfinite(value):
            return f"must be a finite number, got {value!r}"
        return None if ok else f"must be {_WORDS[annotation]}, got {value!r}"
    if annotation.startswith("tuple[") and annotation.endswith("]"):
        items = [a.strip() for a in annotation[6:-1].split(",")]
        if not isinstance(value, (list, tuple)):
            return f"must be a list ({annotation}), got {value!r}"
        if items[-1] != "..." and len(value) != len(items):
            return f"must hold {len(items)} values ({annotation}), got {len(value)}"
        for v in value:
            problem = value_problem(items[0], v)
            if problem:
                return f"every item {problem}"
        twice = [v for i, v in enumerate(value) if v in value[:i]]
        if items == ["str", "..."] and twice:  # a list of names (splits, sides): a repeat would count its frames twice
            return f"names {twice[0]!r} more than once; give each name once, got {list(value)!r}"
    return None


def limit_problem(rules: tuple[str, ...], value) -> str | None:
    """Why ``value`` (a number or a list of numbers) breaks one of ``rules`` such as (">= 1",) or ("> 0", "<= 1")."""
    ops = {">": lambda a, b: a > b, ">=": lambda a, b: a >= b, "<": lambda a, b: a < b, "<=": lambda a, b: a <= b}
    for item in value if isinstance(value, (list, tuple)) else [value]:
        for rule in rules:
            op, bound = rule.split()
            if not ops[op](item, float(bound)):
                return f"must be {' and '.join(rules)}{' (every item)' if isinstance(value, (list, tuple)) else ''}, got {value!r}"
    return None


def section(cls, values: dict, path: Path, name: str, overrides=()):
    """``cls(**values)`` after checking every key is a field of ``cls``, every value fits its annotation and the
    range the class declares for it (``LIMITS``: field -> rules like (">= 1",); the defaults obey them too); a key
    the class renamed (``RENAMED``: old name -> new name) is one line naming the new key.

    ``values`` is the section's table, ``path`` the file named in an error and ``name`` the section's name (an
    error names the key as ``name.key``, and the command line's ``overrides`` of it with the file, see :func:`origin`)."""
    if not isinstance(values, dict):
        raise DataError(path, name, f"must be a table of settings, got {values!r}")
    known = {f.name: f for f in fields(cls)}
    limits = getattr(cls, "LIMITS", {})
    refuse_renamed(cls, values, path, name, overrides)
    kwargs = {}
    for key, value in values.items():
        if key not in known:
            raise DataError(path, f"{name}.{key}", f"unknown setting; expected one of {sorted(known)}")
        problem = value_problem(known[key].type, value) or (key in limits and limit_problem(limits[key], value))
        if problem:
            raise DataError(origin(path, overrides, f"{name}.{key}"), f"{name}.{key}", problem)
        kwargs[key] = tuple(value) if isinstance(value, list) else value
    try:
        return cls(**kwargs)
    except ValueError as err:  # a rule between keys the class checks itself (``__post_init__``)
        text = str(err).removeprefix(f"{name}.")
        field = next((f"{name}.{k}" for k in sorted(known, key=len, reverse=True) if text.startswith(k)), name)
        raise DataError(path, field, str(err)) from None


def refuse_renamed(cls, values: dict, path: Path, name: str, overrides=()) -> None:
    """A key of ``values`` that ``cls`` renamed (``RENAMED``: old name -> new name) is a DataError naming the new
    key, and the command line where an override set it (see :func:`origin`)."""
    renamed = getattr(cls, "RENAMED", {})
    for key in values:
        if key in renamed:
            raise DataError(origin(path, overrides, f"{name}.{key}"), f"{name}.{key}",
                            f"an old name: this setting is now {name}.{renamed[key]} (same meaning; rename the key)")


def current_names(values: dict, renamed: dict[str, str]) -> dict:
    """A section's stored ``values`` (a store's build.json, a checkpoint's config) with the keys renamed since
    (``renamed``: old name -> new name) under their new names, so that what was written before a rename reads as
    today's settings; a new name already present wins. ``values`` is left as it is."""
    out = dict(values)
    for old, new in renamed.items():
        if old in out:
            value = out.pop(old)
            out.setdefault(new, value)
    return out


def toml_value(value) -> str:
    """A setting's value as it is written in a TOML file (``true``, ``"text"``, ``[1, 2]``, ``0.5``)."""
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, str):
        return f'"{value}"'
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    return repr(value)


def section_names(config_cls) -> tuple[str, ...]:
    """The sections a reader's top-level config dataclass reads: its field names, in order."""
    return tuple(f.name for f in fields(config_cls))


def resolve_pipeline(name_or_path: str) -> Path:
    """'dexycb' -> pipelines/dexycb.toml (a Traversable of the installed presets outside a checkout, see
    :func:`pipelines_dir`); a path is used as it is."""
    path = Path(name_or_path)
    if path.suffix != ".toml":
        path = pipelines_dir().joinpath(f"{name_or_path}.toml")
    if not path.is_file():
        raise DataError(path, None, "pipeline config not found")
    return path


def apply_overrides(data: dict, overrides: list[str], path: Path) -> dict:
    """Set ``section.key=value`` items (values parsed as TOML, else kept as bare strings) in ``data``; returns it.

    Only the syntax is checked here; which sections a command may override is :func:`refuse_unused`'s rule."""
    for item in overrides:
        key, sep, raw = item.partition("=")
        section_name, dot, name = key.partition(".")
        if not sep or not dot:
            raise DataError(path, item, "overrides look like section.key=value, e.g. record.sdf_samples_hand=2048")
        table = data.setdefault(section_name, {})
        if not isinstance(table, dict):
            raise DataError(path, key, f"[{section_name}] is not a table of settings")
        try:
            table[name] = tomllib.loads(f"v = {raw}")["v"]
        except tomllib.TOMLDecodeError:
            table[name] = raw  # a bare string
    return data


def read_pipeline(name_or_path: str, overrides: list[str] = ()) -> tuple[Path, dict]:
    """A pipeline TOML (a name under :func:`pipelines_dir` or a path) as a dict of sections with
    ``section.key=value`` overrides applied; the file is returned with it, for errors that name it."""
    path = resolve_pipeline(name_or_path)
    data = read_toml(path, "pipeline file")
    return path, apply_overrides(data, list(overrides), path)


def _listed(sections) -> str:
    return ", ".join(f"[{s}]" for s in sections)


def refuse_unused(overrides: list[str], used: tuple[str, ...], command: str, path: Path,
                  others: dict[str, str] | None = None) -> None:
    """An override of a section ``command`` does not read is an error, not silently ignored.

    ``used``: the sections the command reads; ``others``: section -> the command that reads it, for the sections
    of the file's other readers that ``command`` knows of (the error then says who reads it); ``path``: the file
    (or checkpoint) named in the error."""
    others = others or {}
    for item in overrides:
        key = item.partition("=")[0]
        name = key.partition(".")[0]
        if name in used:
            continue
        who = f"{others[name]} reads them" if name in others else f"it reads {_listed(used)}"
        raise DataError(path, key, f"{command} does not use [{name}] settings ({who}); leave this override out")


def check_sections(data: dict, path: Path, used: tuple[str, ...], others: tuple[str, ...] | None) -> None:
    """Every top-level entry of a pipeline file is a section some reader reads.

    ``used``: the reader's own sections; ``others``: the sections of every other reader of the file, or None when
    the reader cannot know them (the build stands below training and does not know its sections). With None a
    table whose name is close to one of ``used`` is still refused (a misspelt ``[recrod]`` would otherwise leave
    the record settings at their defaults without a word); the others are left to the readers that know them."""
    for name, value in data.items():
        if not isinstance(value, dict):
            raise DataError(path, name, f"expected a [section] table of settings, got {value!r}")
        if name in used or (others is not None and name in others):
            continue
        if others is not None:
            raise DataError(path, name, f"unknown section; expected one of {_listed((*used, *others))}")
        close = difflib.get_close_matches(name, used, n=1, cutoff=0.7)
        if close:
            raise DataError(path, name, f"unknown section; did you mean [{close[0]}]?")


def origin(path: Path, overrides, *keys: str) -> str:
    """Who set ``keys`` (``section.key``), for an error about them: the pipeline file, and the command line's
    overrides of them where there are any (an error caused by an override does not blame the file alone)."""
    given = [item for item in overrides if item.partition("=")[0].strip() in keys]
    return f"{path} with the command line's {' '.join(given)}" if given else str(path)
