"""argparse types shared by every command line of the project (``hoidata``, ``python -m hoisdf.train`` /
``evaluate`` / ``toy``, ``hoisdf score``), beside :func:`hoidata.errors.run_cli` which reports their errors.

A bad value is argparse's own one-line error naming the flag (exit 2), before anything is read or written. Every
command line's parser is an :class:`ArgumentParser`, whose error line masks a URL's secrets as every other error
line does (argparse quotes the value it refused: a store URL with a password).
"""

from __future__ import annotations

import argparse
from pathlib import Path


class ArgumentParser(argparse.ArgumentParser):
    """argparse's parser with :func:`hoidata.errors.redact_urls` on its error line (its sub-parsers are one too)."""

    def error(self, message: str):
        from hoidata.errors import redact_urls

        super().error(redact_urls(message))


def count_type(low: int):
    """argparse type: a whole number >= ``low``, the flag named in the error (argparse adds it)."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a whole number >= {low}, got {text!r}") from None
        if value < low:
            raise argparse.ArgumentTypeError(f"expected a whole number >= {low}, got {value}")
        return value

    parse.__name__ = f"whole number >= {low}"
    return parse


positive_int, non_negative_int = count_type(1), count_type(0)


def local_path(text: str) -> Path:
    """argparse type of an option that names a local folder or file (``python -m hoisdf.train --out``): text
    naming a URL is refused before anything runs (:func:`hoidata.store.paths.local_folder`)."""
    from hoidata.errors import DataError
    from hoidata.store.paths import local_folder

    try:
        return local_folder(text, "this option")
    except DataError as exc:
        raise argparse.ArgumentTypeError(f"{text!r}: {exc.problem}") from None  # the parser's error() masks it


local_path.__name__ = "local path"


def folder(args: argparse.Namespace, name: str, default: Path | None = None) -> Path | None:
    """The folder option ``args.<name>`` as a local path (``default`` when not given): text naming a URL is one
    error line before anything is read or written (:func:`hoidata.store.paths.local_folder`)."""
    from hoidata.store.paths import local_folder

    value = getattr(args, name)
    return default if value is None else local_folder(value, f"hoidata {args.command} --{name.replace('_', '-')}")
