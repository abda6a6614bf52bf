"""``hoisdf check arctic``: a leaderboard submission checked before upload, nothing uploaded (docs/scoring.md,
"ARCTIC"). Every problem is one line naming the file and the key (exit 1); what the server tolerates is a
``note:`` line; a clean submission prints ``ok`` (exit 0).

    hoisdf check arctic --pred DIR|ZIP [--gt DIR] [--meta DIR] [--task pose|field] [--setup p1|p2]
"""

from __future__ import annotations

import sys
from pathlib import Path

from hoidata.cli_types import ArgumentParser
from hoidata.errors import run_cli


def build_parser():
    from hoisdf.scoring.score_arctic import add_task_arguments

    p = ArgumentParser(prog="hoisdf check", description="Check a leaderboard submission offline before upload "
                                                        "(docs/scoring.md).")
    sub = p.add_subparsers(dest="command", required=True, metavar="{arctic}")
    sp = sub.add_parser("arctic", help="ARCTIC pose or field submission: files, keys, dtypes, shapes, frames",
                        description="ARCTIC pose or field submission: files, keys, dtypes, shapes, frame counts")
    sp.add_argument("--pred", required=True, type=Path, metavar="DIR|ZIP", help="the submission (<task>_<setup>_test)")
    sp.add_argument("--gt", type=Path, default=None, metavar="DIR",
                    help="a ground-truth folder or a submission known to be accepted: its sequences and frame counts "
                         "are the reference")
    sp.add_argument("--meta", type=Path, default=None, metavar="DIR",
                    help="ARCTIC's meta folder: the field task's object vertex counts")
    add_task_arguments(sp)
    sp.add_argument("--debug", action="store_true", help="on an error, show the traceback instead of one line")
    return p


def _run(args) -> int:
    from hoisdf.scoring.score_arctic import check

    problems, notes, preds, reference, task, setup = check(args)
    for line in problems:
        print(f"problem: {line}")
    for line in notes:
        print(f"note: {line}")
    print(f"{'ok' if not problems else f'{len(problems)} problem(s)'}: {task}_{setup} submission {args.pred}, "
          f"{len(preds)} sequence view(s) without problems" + ("" if reference is None else f" of {len(reference)}"))
    return 1 if problems else 0


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return run_cli(f"hoisdf check {args.command}", lambda: _run(args), args.debug)


if __name__ == "__main__":
    sys.exit(main())
