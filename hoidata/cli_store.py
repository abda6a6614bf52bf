"""The ``hoidata`` commands on a built store: ``verify``, ``inspect``, ``card`` (the dataset card and the other
loaders' index files) and ``view`` (a rerun recording); :func:`add_store_commands` adds them to the parser."""

from __future__ import annotations

import argparse

from hoidata.cli_types import folder, non_negative_int, positive_int
from hoidata.store.sources import SOURCES


def cmd_verify(args: argparse.Namespace) -> int:
    from hoidata.store import verify_store

    report = verify_store(args.store)
    print(report)
    return 0 if report.ok else 1


def cmd_inspect(args: argparse.Namespace) -> int:
    from hoidata.store.inspect import inspect_store
    from hoidata.store.paths import local_store

    store = local_store(args.store, "hoidata inspect")
    print(f"wrote {inspect_store(store, n=args.n, out=folder(args, 'out'))}")
    return 0


def cmd_card(args: argparse.Namespace) -> int:
    """(Re)write a finished store's dataset card and the other loaders' index files (docs/other-loaders.md)."""
    from hoidata.store.card import CARD_NAME, write_store_files
    from hoidata.store.paths import local_store

    store = local_store(args.store, "hoidata card")
    for line in write_store_files(store, args.source):
        print(f"note: {line}")
    print(f"wrote {store / CARD_NAME} and the loader index files beside the shards")
    return 0


def cmd_view(args: argparse.Namespace) -> int:
    """Write records of a store as a rerun recording (hoidata/view.py says what it holds)."""
    from hoidata.store.paths import local_store
    from hoidata.view import write_recording

    store = local_store(args.store, "hoidata view")
    out, n = write_recording(store, folder(args, "out"), key=args.key, row=args.index, sequence=args.sequence,
                             mano_dir=folder(args, "mano"))
    print(f"wrote {out} ({n} record{'s' if n != 1 else ''}); open it with: rerun {out}")
    return 0


def add_store_commands(add) -> None:
    """The four store commands' parsers, made with ``add(name, help)`` (:func:`hoidata.cli.build_parser`'s)."""
    p = add("verify", "decode every record of a store and check counts and checksums")
    p.add_argument("store")
    p.set_defaults(func=cmd_verify)

    p = add("inspect", "PNG grid of records: image, masks, joints, heatmap, SDF samples")
    p.add_argument("store")
    p.add_argument("--n", type=positive_int, default=16, help="records to show")
    p.add_argument("--out", default="grid.png", help="output PNG")
    p.set_defaults(func=cmd_inspect)

    p = add("card", "(re)write a store's dataset card README.md and its wids / DALI index files")
    p.add_argument("store")
    p.add_argument("--source", default=None, choices=sorted(SOURCES),
                   help="the dataset the records come from (default: what the store records, else its dataset.name)")
    p.set_defaults(func=cmd_card)

    p = add("view", "write records of a store as a rerun recording (.rrd): crop, camera, meshes, joints, SDF samples")
    p.add_argument("store")
    which = p.add_mutually_exclusive_group()
    which.add_argument("--key", default=None, help="the record with this key")
    which.add_argument("--index", type=non_negative_int, default=None, help="the record at this index (default 0)")
    which.add_argument("--sequence", default=None, help="every record of a sequence (a key without its frame number)")
    p.add_argument("--mano", default=None, help="MANO folder: draws the posed hand mesh (default: joints only)")
    p.add_argument("--out", default="record.rrd", help="output .rrd file")
    p.set_defaults(func=cmd_view)
