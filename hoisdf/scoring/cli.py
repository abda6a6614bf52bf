"""``hoisdf score SUBCOMMAND ...`` (also ``python -m hoisdf.scoring``): result files of any method scored offline,
with no model and no store.

    hoisdf score ho3d   --pred pred.json|pred.zip --gt DIR [--version v2|v3] [--subset PREFIX | --ids FILE]
    hoisdf score dexycb --pred RESULT.txt --root DEXYCB_DIR --split s0_test
    hoisdf score contact --pred pred.json|pred.zip|hands.npz [--order evaluation.txt] --store STORE --mano DIR
    hoisdf score recon  --pred SDF_MESH_DIR --gt GT_MESH_DIR [--protocol gsdf|exact] [--seed S] [--repeats K]
    hoisdf score hot3d  --pred DIR|SUBMISSION.tar --gt DIR [--mano DIR] [--track pose|shape]
    hoisdf score arctic --pred DIR|ZIP --gt DIR --meta DIR [--mano DIR] [--task pose|field] [--setup p1|p2]

Each subcommand prints a table and, with ``--out FILE.json``, writes the numbers under the same names. A
malformed file is one ``error:`` line naming the file, the entry and the field (exit 2; ``--debug`` for the
traceback). docs/scoring.md describes the inputs, score names and units; docs/plausibility.md the contact metrics.

A subcommand is a module listed in :data:`SUBCOMMANDS` (name -> module path, imported when the parser is built)
that defines ``HELP`` (one line), ``add_arguments(parser)`` (its own options; ``--out`` and ``--debug`` are added
here), ``score(args) -> dict`` (the numbers and ``samples`` / ``official`` / ``note``; NaN becomes null in the JSON)
and ``format_result(result) -> str`` (the printed table). Errors the user can act on are raised as
:class:`hoidata.errors.DataError` naming the file, the entry and the field.
"""

from __future__ import annotations

import argparse
import importlib
import json
import sys

from hoidata.atomic import write_atomic
from hoidata.cli_types import ArgumentParser, local_path
from hoidata.errors import run_cli
from hoisdf.scoring.results_json import json_safe

SUBCOMMANDS = {
    "ho3d": "hoisdf.scoring.score_ho3d",
    "dexycb": "hoisdf.scoring.score_dexycb",
    "contact": "hoisdf.scoring.score_contact",
    "recon": "hoisdf.scoring.score_recon",
    "hot3d": "hoisdf.scoring.score_hot3d",
    "arctic": "hoisdf.scoring.score_arctic",
}


def build_parser() -> argparse.ArgumentParser:
    p = ArgumentParser(prog="hoisdf score", description="Score result files of any method offline, with "
                                "no model and no store (docs/scoring.md).")
    sub = p.add_subparsers(dest="command", required=True, metavar="{" + ",".join(SUBCOMMANDS) + "}")
    for name, module_name in SUBCOMMANDS.items():
        module = importlib.import_module(module_name)
        sp = sub.add_parser(name, help=module.HELP, description=module.HELP)
        module.add_arguments(sp)
        sp.add_argument("--out", type=local_path, default=None, metavar="FILE.json", help="also write the numbers here")
        sp.add_argument("--debug", action="store_true", help="on an error, show the traceback instead of one line")
        sp.set_defaults(module=module)
    return p


def _run(args) -> int:
    result = args.module.score(args)
    print(args.module.format_result(result))
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        write_atomic(args.out, (json.dumps(json_safe({"command": args.command, **result}), indent=2) + "\n").encode())
        print(f"wrote {args.out}")
    return 0


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return run_cli(f"hoisdf score {args.command}", lambda: _run(args), args.debug)


if __name__ == "__main__":
    sys.exit(main())
