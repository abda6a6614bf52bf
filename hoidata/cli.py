"""The ``hoidata`` command: thin argparse front end over the library functions.

Every subcommand parses its flags, calls one library function and prints what it did. ``main(argv)``
takes an argument list so tests can call it directly.
"""

from __future__ import annotations

import argparse
import functools
import sys
from pathlib import Path

from hoidata import __version__
from hoidata.cli_types import ArgumentParser, count_type, non_negative_int, positive_int
from hoidata.engine import add_launcher_flags, launch
from hoidata.errors import run_cli


def folder(args: argparse.Namespace, name: str, default: Path | None = None) -> Path | None:
    """The folder option ``args.<name>`` as a local path (``default`` when not given): text naming a URL is one
    error line before anything is read or written (:func:`hoidata.store.paths.local_folder`)."""
    from hoidata.store.paths import local_folder

    value = getattr(args, name)
    return default if value is None else local_folder(value, f"hoidata {args.command} --{name.replace('_', '-')}")


def cmd_make_toy(args: argparse.Namespace) -> int:
    """Write the procedural hand, objects and toy datasets in the real layouts, then check them."""
    from hoidata.records.inputs import format_rows, mano_rows, object_rows
    from hoidata.toy.make import HO3D_MAX_SEQUENCES, empty_split_notes, make_toy, split_rows

    out = folder(args, "out")
    layouts = ("dexycb", "ho3d") if args.layout == "all" else (args.layout,)
    for layout in layouts:
        root = out / layout if args.layout == "all" else out
        sequences = args.sequences
        if layout != "dexycb" and args.layout == "all" and sequences and sequences > HO3D_MAX_SEQUENCES:
            print(f"\nnote: --sequences {sequences} is DexYCB's; the toy HO-3D gets its {HO3D_MAX_SEQUENCES} training "
                  "sequences")
            sequences = HO3D_MAX_SEQUENCES
        made = make_toy(root, layout, sequences=sequences, frames=args.frames, seed=args.seed)
        print(f"\n{layout}: wrote {made} ")
        rows = split_rows(root, layout)
        print("\n".join([format_rows(rows), *empty_split_notes(rows, layout, args.sequences)]))
    first = out / layouts[0] if args.layout == "all" else out
    print("\n" + format_rows(mano_rows(first / "mano")) + "\n")
    if args.layout != "arctic":  # ARCTIC's toy objects are its templates under meta/, not a YCB models folder
        print(format_rows(object_rows(first / "models", cache_dir=args.cache_dir)))
    return 0


def cmd_check_mano(args: argparse.Namespace) -> int:
    """Load MANO_RIGHT.pkl / MANO_LEFT.pkl from a folder and report what the pipelines will see."""
    from hoidata.records.inputs import format_rows, mano_rows

    rows = mano_rows(args.mano_dir)
    print(format_rows(rows))
    return 0 if all(r["status"] == "ok" for r in rows) else 1


def cmd_check_objects(args: argparse.Namespace) -> int:
    """Load, repair and simplify every object of a YCB-layout models folder, and report."""
    from hoidata.records.inputs import format_rows, object_rows

    rows = object_rows(args.models_dir, n_vertices=args.vertices, cache_dir=args.cache_dir)
    print(format_rows(rows))
    return 0 if rows else 1


def _part(text: str) -> tuple[int, int]:
    try:
        i, n = (int(x) for x in text.split("/"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"--part must look like i/N, got {text!r}") from None
    if not 0 <= i < n:
        raise argparse.ArgumentTypeError(f"--part i/N needs 0 <= i < N, got {text!r}")
    return i, n


def cmd_build_sdf(args: argparse.Namespace) -> int:
    """Build (or resume) a training store from a dataset, as pipelines/<dataset>.toml says."""
    from hoidata.build_sdf import build_store, estimate_build
    from hoidata.records.settings import load_build_config

    root, out = folder(args, "root"), folder(args, "out")
    mano, models = folder(args, "mano", root / "mano"), folder(args, "models", root / "models")
    cfg = load_build_config(args.dataset, args.overrides)
    if args.estimate:
        for k, v in estimate_build(cfg, root, mano, models, workers=args.workers).items():
            print(f"{k:>30}: {v}")
        return 0
    s = launch(args, functools.partial(build_store, cfg, root, mano, models, out), "build-sdf")
    if s is None:  # --dry-run
        return 0
    empty = f" ({s.empty_units} empty: every frame skipped)" if s.empty_units else ""
    print(f"{s.out}: {s.written} records written in {s.seconds:.1f} s ({s.items_per_second:.2f} frames/s), "
          f"{s.units_written} shards written{empty}, {s.units_kept} kept from an earlier run")
    print(f"skipped: {len(s.reader_skipped)} by the dataset reader (each a frame, or a whole camera or sequence), "
          f"{len(s.skipped)} frames while building")
    print_skips(s.reader_skipped, "reader")
    print_skips(s.skipped, "build")
    if s.empty_splits:  # a split asked for but without a frame: say so, the store holds none of its records
        print(f"note: no frames in split(s) {', '.join(s.empty_splits)} of {root}: the store holds none of them")
    print("index.zarr already lists every shard: nothing written" if s.finish_kept else "index.zarr written"
          if s.finished else "index not written yet: other parts still have shards to build")
    if s.finished or s.finish_kept:
        from hoidata.build_sdf import mask_iou_line, supervision_line

        line = mask_iou_line(s.out)
        print(line or "", end="\n" if line else "")
        print(supervision_line(s.out))
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    """Write a dataset's frames as another codebase's files (docs/other-codebases.md)."""
    from hoidata.export import export_dataset
    from hoidata.records.settings import load_build_config
    from hoidata.store.verify import opened_store

    root, out = folder(args, "root"), folder(args, "out")
    mano, models = folder(args, "mano", root / "mano"), folder(args, "models", root / "models")
    store = opened_store(args.store, "hoidata export --store") if args.store else None  # before anything is written
    cfg = load_build_config(args.dataset, args.overrides)
    task = functools.partial(export_dataset, args.format, cfg, root, mano, models, out, splits=args.splits,
                             store=store)
    s = launch(args, task, "export")
    if s is None:  # --dry-run
        return 0
    print(f"{s.out}: {s.written} of {s.items} frames exported as {args.format} in {s.seconds:.1f} s "
          f"({s.items_per_second:.2f} frames/s), {s.units_written} chunks written, {s.units_kept} kept from an "
          f"earlier run, {len(s.reader_skipped) + len(s.skipped)} frames skipped")
    for skip in (s.reader_skipped + s.skipped)[:10]:
        print(f"  skipped {skip['frame_id']}: {skip['reason']}")
    if s.extra.get("sdf_sources"):
        print("SDF rows: " + ", ".join(f"{n} frames {k}" for k, n in sorted(s.extra["sdf_sources"].items())))
    for line in s.notes:
        print(line)
    print("annotation files written" if s.finished else "annotation files not written yet: other parts still have work")
    return 0


def print_skips(skips: list, who: str, limit: int = 10) -> None:
    """The reasons of a skips list, most frequent first, one line each with a count and an example file."""
    from hoidata.records import skip_groups

    groups = skip_groups(skips)
    for reason, n, path in groups[:limit]:
        print(f"  skipped ({who}) {n} x {reason}" + (f"  e.g. {path}" if path else ""))
    if len(groups) > limit:
        print(f"  ... {len(groups) - limit} more reasons (all are listed in the store's index)")


def cmd_render_synthetic(args: argparse.Namespace) -> int:
    """Render perturbed grasps of a store or dataset from new views into a training store."""
    from hoidata.records import RecordSettings
    from hoidata.render_synthetic import check_count, render_synthetic

    check_count(args.count)  # here, not in each array task
    source, out = folder(args, "source"), folder(args, "out")
    mano, models = folder(args, "mano", source / "mano"), folder(args, "models", source / "models")
    record = RecordSettings(crop_size=args.crop_size)
    task = functools.partial(render_synthetic, source, out, args.count, mano, models, seed=args.seed,
                             backgrounds=folder(args, "backgrounds"), record=record,
                             records_per_shard=args.records_per_shard)
    s = launch(args, task, "render-synthetic")
    if s is None:  # --dry-run
        return 0
    print(f"{s.out}: {s.written} synthetic records in {s.seconds:.1f} s ({s.items_per_second:.2f} renders/s), "
          f"{len(s.skipped)} samples skipped")
    print_skips(s.skipped, "render")
    if s.finished:
        from hoidata.store import read_index

        print(f"physical check: {read_index(s.out).provenance['synthetic']}")
    return 0


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


def cmd_toy_pipeline(args: argparse.Namespace) -> int:
    """The data half of the main job: toy datasets -> verified train and test stores -> inspection PNG."""
    from hoidata.toy.make import check_chain_size

    out = folder(args, "out")
    check_chain_size(args.sequences)  # a size that leaves the test store empty: refused before anything is written
    size = [*(["--sequences", str(args.sequences)] if args.sequences is not None else []),
            *(["--frames", str(args.frames)] if args.frames is not None else [])]
    root = out / "data" / "dexycb"
    made = out / "data" / f"made-seed{args.seed}{''.join(size)}.ok"  # make-toy finished with these settings
    steps = [] if made.is_file() else [["make-toy", "--out", str(out / "data"), "--seed", str(args.seed), *size]]
    if made.is_file():
        print(f"{out / 'data'}: toy data made earlier with these settings; make-toy skipped")
    for split in ("train", "test"):  # the whole store: a Slurm array task's part is not this command's (a seed
        # sweep runs as an array), so --part 0/1 overrides what build-sdf would read from SLURM_ARRAY_TASK_ID
        steps.append(["build-sdf", "--dataset", "toy", "--root", str(root), "--out", str(out / "store" / split),
                      "--workers", str(args.workers), "--part", "0/1", f'dataset.splits=["{split}"]'])
    steps += [["verify", str(out / "store" / split)] for split in ("train", "test")]
    steps.append(["inspect", str(out / "store" / "train"), "--out", str(out / "store_grid.png")])
    for argv in steps:
        print(f"\n$ hoidata {' '.join(argv)}", flush=True)
        status = main(argv)
        if status:
            return status
        if argv[0] == "make-toy":
            made.touch()
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = ArgumentParser(prog="hoidata", description="Hand-object datasets -> training-ready stores.")
    parser.add_argument("--version", action="version", version=f"hoidata {__version__}")
    common = ArgumentParser(add_help=False)
    common.add_argument("--debug", action="store_true", help="on an error, show the traceback instead of one line")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    parser.commands = sub.choices  # name -> subcommand parser (main parses the subcommand's own arguments)

    def add(name: str, text: str) -> argparse.ArgumentParser:
        return sub.add_parser(name, help=text, parents=[common])

    p = add("make-toy", "write toy DexYCB / HO-3D datasets with procedural MANO files and objects")
    p.add_argument("--out", required=True, help="output folder; with --layout all it gets dexycb/ and ho3d/")
    p.add_argument("--layout", choices=("dexycb", "ho3d", "ho3d_v3", "hot3d", "arctic", "all"), default="all",
                   help="dataset layout (default: all = dexycb and ho3d; ho3d_v3: HO-3D v3's JPEG layout; hot3d: "
                        "HOT3D-Clips tars; arctic: ARCTIC's arctic_data/data, no images)")
    p.add_argument("--sequences", type=positive_int, default=None,
                   help="sequences per subject (DexYCB; val and test need 5 or more) / training sequences (HO-3D) / clips (HOT3D: 3 by default, up to 90; multiples of 10 are val)")
    p.add_argument("--frames", type=positive_int, default=None, help="frames per sequence and camera (per clip: HOT3D)")
    p.add_argument("--seed", type=non_negative_int, default=0, help="random seed; the same seed gives the same files")
    p.add_argument("--cache-dir", default=None, help="cache for simplified meshes (default $HOIDATA_CACHE/objects or ~/.cache/hoidata/objects)")
    p.set_defaults(func=cmd_make_toy)

    p = add("build-sdf", "build a verified training store (SDF samples, masks, crops, labels)")
    p.add_argument("--dataset", required=True, help="pipeline name (pipelines/<name>.toml: dexycb, dexycb_full, ho3d, ho3d_eval, ho3d_v3, ho3d_v3_eval, toy) or a .toml")
    p.add_argument("--root", required=True, help="dataset folder (DexYCB or HO-3D layout)")
    p.add_argument("--mano", default=None, help="folder with MANO_RIGHT.pkl / MANO_LEFT.pkl (default ROOT/mano)")
    p.add_argument("--models", default=None, help="YCB models folder (default ROOT/models)")
    p.add_argument("--out", required=True, help="store folder (resumes if it holds an interrupted build)")
    p.add_argument("--workers", type=positive_int, default=1, help="worker processes (1: build in this process)")
    p.add_argument("--part", type=_part, default=None,
                   help="i/N: build only shards k with k %% N == i (default: a Slurm array task's, else all)")
    add_launcher_flags(p, count_type)
    p.add_argument("--estimate", action="store_true", help="time and disk estimate from a few frames; writes nothing")
    p.add_argument("overrides", nargs="*", help="section.key=value overrides, e.g. record.sdf_samples_hand=2048")
    p.set_defaults(func=cmd_build_sdf)

    p = add("export", "write a dataset as another codebase's files (HandOccNet family, gSDF)")
    p.add_argument("--format", required=True, choices=("handoccnet", "gsdf"), help="the consumer's layout")
    p.add_argument("--dataset", required=True, help="pipeline name (its [dataset] selects the frames) or a .toml")
    p.add_argument("--root", required=True, help="dataset folder (DexYCB or HO-3D layout)")
    p.add_argument("--mano", default=None, help="folder with MANO_RIGHT.pkl / MANO_LEFT.pkl (default ROOT/mano)")
    p.add_argument("--models", default=None, help="YCB models folder (default ROOT/models)")
    p.add_argument("--out", required=True, help="the folder the consumer reads (resumes an interrupted export)")
    p.add_argument("--store", default=None, help="gsdf: a built store whose SDF rows are re-used where they fit")
    p.add_argument("--splits", type=lambda text: tuple(text.split(",")), default=None,
                   help="comma-separated splits to export (default: HO-3D train,evaluation; DexYCB the pipeline's)")
    p.add_argument("--workers", type=positive_int, default=1, help="worker processes (1: export in this process)")
    p.add_argument("--part", type=_part, default=None,
                   help="i/N: export only chunks k with k %% N == i (default: a Slurm array task's, else all)")
    add_launcher_flags(p, count_type)
    p.add_argument("overrides", nargs="*", help="section.key=value overrides, e.g. dataset.box_splits=[\"train\"]")
    p.set_defaults(func=cmd_export)

    p = add("render-synthetic", "render perturbed grasps from new views into a training store")
    p.add_argument("--source", required=True, help="a store, or an HO-3D / DexYCB / toy dataset folder, to take grasps from")
    p.add_argument("--out", required=True, help="store folder (resumes an interrupted run)")
    p.add_argument("--count", type=positive_int, required=True, help="samples to render")
    p.add_argument("--mano", default=None, help="MANO folder (default SOURCE/mano)")
    p.add_argument("--models", default=None, help="YCB models folder (default SOURCE/models)")
    p.add_argument("--backgrounds", default=None, help="folder of background images (default: procedural)")
    p.add_argument("--seed", type=non_negative_int, default=0)
    p.add_argument("--workers", type=positive_int, default=1, help="worker processes (1: render in this process)")
    p.add_argument("--part", type=_part, default=None,
                   help="i/N: render only shards k with k %% N == i (default: a Slurm array task's, else all)")
    p.add_argument("--crop-size", type=count_type(32), default=512, help="record crop size, pixels (>= 32)")
    p.add_argument("--records-per-shard", type=positive_int, default=256)
    add_launcher_flags(p, count_type)
    p.set_defaults(func=cmd_render_synthetic)

    p = add("verify", "decode every record of a store and check counts and checksums")
    p.add_argument("store")
    p.set_defaults(func=cmd_verify)

    p = add("inspect", "PNG grid of records: image, masks, joints, heatmap, SDF samples")
    p.add_argument("store")
    p.add_argument("--n", type=positive_int, default=16, help="records to show")
    p.add_argument("--out", default="grid.png", help="output PNG")
    p.set_defaults(func=cmd_inspect)

    p = add("toy-pipeline", "toy data -> verified train/test stores (the data half of python -m hoisdf.toy)")
    p.add_argument("--out", default="toy_run", help="output folder (data/, store/train, store/test, store_grid.png)")
    p.add_argument("--workers", type=positive_int, default=2, help="worker processes for the store build")
    p.add_argument("--seed", type=non_negative_int, default=0)
    p.add_argument("--sequences", type=positive_int, default=None, help="toy size: sequences per subject, 5 or more (the test split is every 5th)")
    p.add_argument("--frames", type=positive_int, default=None, help="toy size: frames per sequence and camera")
    p.set_defaults(func=cmd_toy_pipeline)

    p = add("check-mano", "load and check MANO_RIGHT.pkl / MANO_LEFT.pkl")
    p.add_argument("mano_dir", help="folder holding MANO_RIGHT.pkl and/or MANO_LEFT.pkl")
    p.set_defaults(func=cmd_check_mano)

    p = add("check-objects", "load, repair and simplify the objects of a YCB models folder")
    p.add_argument("models_dir", help="folder with <name>/textured_simple.obj per object")
    p.add_argument("--vertices", type=count_type(4), default=1000, help="vertex count of the evaluation meshes")
    p.add_argument("--cache-dir", default=None, help="cache for simplified meshes (default $HOIDATA_CACHE/objects or ~/.cache/hoidata/objects)")
    p.set_defaults(func=cmd_check_objects)
    return parser


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The subcommand's arguments, parsed intermixed: ``section.key=value`` overrides may stand before and after
    other options (``build-sdf a=1 --out S b=2``)."""
    parser = build_parser()
    argv = sys.argv[1:] if argv is None else list(argv)
    if not argv or argv[0] not in parser.commands:
        return parser.parse_args(argv)  # --help, --version, a missing or unknown command: argparse says it
    args = parser.commands[argv[0]].parse_intermixed_args(argv[1:])
    args.command, args.argv, args.command_parser = argv[0], argv, parser.commands[argv[0]]
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    # bad files, settings or arguments, a full or read-only disk, a worker that cannot start: one line, exit 2
    return run_cli(f"hoidata {args.command}", lambda: args.func(args), args.debug)


if __name__ == "__main__":
    sys.exit(main())
