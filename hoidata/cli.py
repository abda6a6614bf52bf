"""The ``hoidata`` command: thin argparse front end over the library functions.

Every subcommand parses its flags, calls one library function and prints what it did. ``main(argv)``
takes an argument list so tests can call it directly.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from hoidata import __version__
from hoidata.errors import DataError


def cmd_make_toy(args: argparse.Namespace) -> int:
    """Write the procedural hand, objects and toy datasets in the real layouts, then check them."""
    from hoidata.datasets.toy import make_toy, split_rows
    from hoidata.summary import format_rows, mano_rows, object_rows

    out = Path(args.out)
    layouts = ("dexycb", "ho3d") if args.layout == "all" else (args.layout,)
    for layout in layouts:
        root = out / layout if args.layout == "all" else out
        made = make_toy(root, layout, sequences=args.sequences, frames=args.frames, seed=args.seed)
        print(f"\n{layout}: wrote {made} ")
        print(format_rows(split_rows(root, layout)))
    first = out / layouts[0] if args.layout == "all" else out
    print("\n" + format_rows(mano_rows(first / "mano")) + "\n")
    print(format_rows(object_rows(first / "models", cache_dir=args.cache_dir)))
    return 0


def cmd_check_mano(args: argparse.Namespace) -> int:
    """Load MANO_RIGHT.pkl / MANO_LEFT.pkl from a folder and report what the pipelines will see."""
    from hoidata.summary import format_rows, mano_rows

    rows = mano_rows(args.mano_dir)
    print(format_rows(rows))
    return 0 if all(r["status"] == "ok" for r in rows) else 1


def cmd_check_objects(args: argparse.Namespace) -> int:
    """Load, repair and simplify every object of a YCB-layout models folder, and report."""
    from hoidata.summary import format_rows, object_rows

    rows = object_rows(args.models_dir, n_vertices=args.vertices, cache_dir=args.cache_dir)
    print(format_rows(rows))
    return 0 if rows else 1


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="hoidata", description="Hand-object datasets -> training-ready stores.")
    parser.add_argument("--version", action="version", version=f"hoidata {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("make-toy", help="write toy DexYCB / HO-3D datasets with procedural MANO files and objects")
    p.add_argument("--out", required=True, help="output folder; with --layout all it gets dexycb/ and ho3d/")
    p.add_argument("--layout", choices=("dexycb", "ho3d", "all"), default="all", help="dataset layout (default: all)")
    p.add_argument("--sequences", type=int, default=None, help="sequences per subject (DexYCB) / training sequences (HO-3D)")
    p.add_argument("--frames", type=int, default=None, help="frames per sequence and camera")
    p.add_argument("--seed", type=int, default=0, help="random seed; the same seed gives the same files")
    p.add_argument("--cache-dir", default=None, help="cache for simplified meshes (default $HOIDATA_CACHE/objects or ~/.cache/hoidata/objects)")
    p.set_defaults(func=cmd_make_toy)

    p = sub.add_parser("check-mano", help="load and check MANO_RIGHT.pkl / MANO_LEFT.pkl")
    p.add_argument("mano_dir", help="folder holding MANO_RIGHT.pkl and/or MANO_LEFT.pkl")
    p.set_defaults(func=cmd_check_mano)

    p = sub.add_parser("check-objects", help="load, repair and simplify the objects of a YCB models folder")
    p.add_argument("models_dir", help="folder with <name>/textured_simple.obj per object")
    p.add_argument("--vertices", type=int, default=1000, help="vertex count of the evaluation meshes")
    p.add_argument("--cache-dir", default=None, help="cache for simplified meshes (default $HOIDATA_CACHE/objects or ~/.cache/hoidata/objects)")
    p.set_defaults(func=cmd_check_objects)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except DataError as e:
        print(f"hoidata {args.command}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
