"""MkDocs hook: the settings reference is generated from the settings dataclasses at build time.

A page containing the marker ``<!-- settings-reference -->`` gets, in its place, one table per section of
a pipeline TOML (``[dataset]``, ``[record]``, ``[store]`` from :class:`hoidata.records.settings.BuildConfig`;
``[model]``, ``[train]``, ``[augment]``, ``[loss]`` from :class:`hoisdf.config.TrainConfig`): every key, its
type, its default and the comment written beside the field in the source. A field added to a dataclass
appears here at the next build, so the page cannot drift from the code.
"""

from __future__ import annotations

import dataclasses
import inspect
import io
import re
import tokenize
import typing
from pathlib import Path

MARKER = "<!-- settings-reference -->"
INCLUDE = re.compile(r"<!-- include: (\S+) -->")  # a file of the repository, inlined (its headings demoted)
ROOT = Path(__file__).resolve().parents[1]


def _field_comments(cls) -> dict[str, str]:
    """{field name: the ``# comment`` on its line, else a whole-line comment right above it} from the source."""
    source = inspect.getsource(cls)
    comments, line_field = {}, {}
    for lineno, line in enumerate(source.splitlines(), 1):
        head = line.strip().split(":", 1)[0]
        if head.isidentifier() and ":" in line and not line.strip().startswith(("def ", "class ", "#", '"')):
            line_field[lineno] = head
    above = {}
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type != tokenize.COMMENT:
            continue
        text = tok.string.lstrip("#").strip()
        if tok.start[0] in line_field:
            comments[line_field[tok.start[0]]] = text
        elif tok.start[0] + 1 in line_field and tok.line.strip().startswith("#"):
            above[line_field[tok.start[0] + 1]] = text
    return {**above, **comments}


def _default(f: dataclasses.Field) -> str:
    if f.default is not dataclasses.MISSING:
        value = f.default
    elif f.default_factory is not dataclasses.MISSING:
        value = f.default_factory()
    else:
        return "(required)"
    if isinstance(value, tuple):
        value = list(value)
    if isinstance(value, str):
        return f'`"{value}"`'
    if isinstance(value, bool):
        return f"`{str(value).lower()}`"
    return f"`{value}`"


def _type_name(cls, f: dataclasses.Field) -> str:
    hint = typing.get_type_hints(cls).get(f.name, f.type)
    text = getattr(hint, "__name__", None) if not typing.get_args(hint) else None
    return (text or str(hint).replace("typing.", "")).replace("|", "or")


def _section_table(name: str, cls) -> str:
    comments = _field_comments(cls)
    doc = cls.__doc__ or ""
    doc = "" if doc.startswith(f"{cls.__name__}(") else inspect.cleandoc(doc)  # not the generated signature
    lines = [f"### `[{name}]`", "", f"From `{cls.__module__}.{cls.__qualname__}`. {doc.splitlines()[0] if doc else ''}",
             "", "| key | type | default | allowed | meaning |", "|---|---|---|---|---|"]
    limits = getattr(cls, "LIMITS", {})  # the ranges hoidata.sections.section checks (floats must also be finite)
    for f in dataclasses.fields(cls):
        meaning = comments.get(f.name, "").replace("|", "\\|")
        allowed = ", ".join(limits.get(f.name, ())).replace(">", "&gt;").replace("<", "&lt;")
        lines.append(f"| `{name}.{f.name}` | {_type_name(cls, f)} | {_default(f)} | {allowed} | {meaning} |")
    return "\n".join(lines) + "\n"


def settings_reference() -> str:
    from hoidata.records.settings import BuildConfig
    from hoisdf.config import TrainConfig

    parts = []
    for root in (BuildConfig, TrainConfig):
        hints = typing.get_type_hints(root)
        for f in dataclasses.fields(root):
            parts.append(_section_table(f.name, hints[f.name]))
    return "\n".join(parts)


def on_page_markdown(markdown: str, page, config, files) -> str:
    if MARKER in markdown:
        markdown = markdown.replace(MARKER, settings_reference())
    return INCLUDE.sub(lambda m: _included(m.group(1)), markdown)


def _included(relative: str) -> str:
    """The text of a repository file, its first heading dropped and the others demoted one level."""
    lines = (ROOT / relative).read_text().splitlines()
    if lines and lines[0].startswith("# "):
        lines = lines[1:]
    out, fenced = [], False
    for line in lines:
        fenced ^= line.startswith("```")
        out.append("#" + line if line.startswith("#") and not fenced else line)
    return "\n".join(out)
