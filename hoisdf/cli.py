"""The ``hoisdf`` console script: ``hoisdf score ...`` (:mod:`hoisdf.scoring.cli`), ``hoisdf check ...``
(:mod:`hoisdf.scoring.check_cli`). Training and evaluation keep their
``python -m hoisdf.train`` / ``python -m hoisdf.evaluate`` entry points."""

from __future__ import annotations

import sys

# command -> module with main(argv) -> exit code
COMMANDS = {"score": "hoisdf.scoring.cli", "check": "hoisdf.scoring.check_cli"}


def main(argv: list[str] | None = None) -> int:
    import importlib

    argv = sys.argv[1:] if argv is None else list(argv)
    if not argv or argv[0] not in COMMANDS:
        names = ", ".join(COMMANDS)
        print(f"usage: hoisdf {{{names}}} ...\n  score   score result files of any method offline (hoisdf score -h)\n"
              "  check   check a leaderboard submission before upload (hoisdf check -h)",
              file=sys.stderr if argv and argv[0] not in ("-h", "--help") else sys.stdout)
        return 0 if argv and argv[0] in ("-h", "--help") else 2
    return importlib.import_module(COMMANDS[argv[0]]).main(argv[1:])


if __name__ == "__main__":
    sys.exit(main())
