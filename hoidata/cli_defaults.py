"""Where the ``hoidata`` commands look when a folder is not given, and the lines that say what each one read.

A dataset folder comes from ``--root``, else from the environment variable of its dataset (:data:`HOMES`:
``DEX_YCB_DIR`` as the dex-ycb-toolkit reads it; ``HO3D_DIR``, ``HO3D_V3_DIR`` and ``HOT3D_CLIPS_DIR``), else it is
one error line naming both. MANO: ``--mano``, the dataset folder's own ``mano/``, ``MANO_DIR``. Object meshes:
``--models``, else where the dataset keeps them. Stores: ``shards/<pipeline>``. The table is docs/datasets.md's
"Where the data is".
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from hoidata.provenance import MANO_VARIABLE, find_recorded_mano, recorded_inputs

SHARDS = Path("shards")  # the stores' folder (relative to where the command runs)
TOY_PRESET = "toy"  # the preset that trains what was built from make-toy's data


@dataclass(frozen=True)
class Home:
    variable: str  # the environment variable naming the dataset folder
    models: str  # where the dataset keeps its object meshes, under its folder
    label: str  # the dataset's name in messages
    models_note: str  # what that folder is


HOMES = {  # (dataset.name, dataset.version) -> Home
    ("dexycb", "v2"): Home("DEX_YCB_DIR", "models", "DexYCB", "the YCB meshes DexYCB ships"),
    ("ho3d", "v2"): Home("HO3D_DIR", "models", "HO-3D v2", "HO-3D ships no meshes: the YCB models put there"),
    ("ho3d", "v3"): Home("HO3D_V3_DIR", "models", "HO-3D v3", "HO-3D ships no meshes: the YCB models put there"),
    ("hot3d_clips", "v2"): Home("HOT3D_CLIPS_DIR", "object_models_eval", "HOT3D-Clips",
                                "the GLB meshes HOT3D-Clips ships"),
}


def home(dataset) -> Home:
    """The :class:`Home` of a build's ``[dataset]`` (its ``name`` and, for HO-3D, ``version``)."""
    return HOMES[(dataset.name, dataset.version if dataset.name == "ho3d" else "v2")]


@dataclass(frozen=True)
class Chosen:
    name: str  # what it is: root, mano, models, out, source, count
    value: Path | str | int
    origin: str  # where it came from: the flag, the variable, or the default's rule
    split: str | None = None  # a default store of build-sdf: the one split it holds


def chosen_lines(items: list[Chosen]) -> str:
    """One line per choice, ``  name  value  (origin)``, printed at the start of a command."""
    width = max(len(str(c.value)) for c in items)
    return "\n".join(f"  {c.name:<7} {str(c.value):<{width}}  ({c.origin})" for c in items)


def announce(args, title: str, items: list[Chosen] = ()) -> None:
    """Print ``title`` and the choices at the start of a command (URLs masked): on stdout, or on stderr under
    ``--dry-run``, whose stdout is the sbatch line alone."""
    import sys

    from hoidata.errors import redact_urls

    text = "\n".join([title, *([chosen_lines(list(items))] if items else [])])
    print(redact_urls(text), file=sys.stderr if getattr(args, "dry_run", False) else sys.stdout, flush=True)


def _variable(name: str) -> str | None:
    value = os.environ.get(name, "").strip()
    return value or None


def dataset_folder(given: str | None, where: Home) -> Chosen:
    """``--root``, else the dataset's variable; neither is one error line naming both (nothing was read)."""
    if given is not None:
        return Chosen("root", Path(given), "--root")
    value = _variable(where.variable)
    if value is None:
        raise ValueError(f"no {where.label} folder: give --root DIR or set {where.variable} (nothing was written)")
    if not Path(value).is_dir():
        raise ValueError(f"{where.variable}={value}: not a folder; give --root DIR or set {where.variable} to the "
                         f"{where.label} folder (nothing was written)")
    return Chosen("root", Path(value), where.variable)


def mano_folder(given: str | None, root: Path, root_name: str = "ROOT") -> Chosen:
    """``--mano``, else the dataset folder's own ``mano/`` (make-toy's layout), else ``MANO_DIR``; none of them is one
    error line naming the flag and the variable."""
    if given is not None:
        return Chosen("mano", Path(given), "--mano")
    if (root / "mano").is_dir():
        return Chosen("mano", root / "mano", f"default: {root_name}/mano, the dataset folder's own")
    value = _variable(MANO_VARIABLE)
    if value is None:
        raise ValueError(f"no MANO folder: give --mano DIR or set {MANO_VARIABLE} (the folder with MANO_RIGHT.pkl; "
                         f"{root / 'mano'} does not exist; nothing was written)")
    return Chosen("mano", Path(value), MANO_VARIABLE)


def models_folder(given: str | None, root: Path, where: Home) -> Chosen:
    """``--models``, else where the dataset keeps its object meshes (``ROOT/models``; HOT3D-Clips'
    ``ROOT/object_models_eval``)."""
    if given is not None:
        return Chosen("models", Path(given), "--models")
    return Chosen("models", root / where.models, f"default: ROOT/{where.models}, {where.models_note}")


def add_dataset_flags(p) -> None:
    """--root, --mano and --models of the commands that read a dataset, their defaults from :data:`HOMES`."""
    homes = list(HOMES.values())
    p.add_argument("--root", default=None, help="dataset folder (default: " + ", ".join(
        f"${h.variable} for {h.label}" for h in homes) + ")")
    p.add_argument("--mano", default=None, help=f"folder with MANO_RIGHT.pkl / MANO_LEFT.pkl (default: ROOT/mano when "
                                                f"the dataset folder holds one, else ${MANO_VARIABLE})")
    p.add_argument("--models", default=None, help="object meshes (default: where the dataset keeps them: " + ", ".join(
        f"{h.label} ROOT/{h.models}" for h in homes) + ")")


def _flag(args, name: str) -> Path | None:
    """The folder option ``args.<name>`` as a local path (None when not given): text naming a URL is one error line
    before anything is read or written."""
    from hoidata.store.paths import local_folder

    value = getattr(args, name)
    return None if value is None else local_folder(value, f"hoidata {args.command} --{name}")


def dataset_inputs(args, dataset) -> list[Chosen]:
    """The dataset, MANO and models folders of build-sdf and export (``args``: their parsed options; ``dataset``: the
    build's ``[dataset]``). A folder taken from a variable is written into ``args``, so that an array task's command
    line names it."""
    where = home(dataset)
    root = dataset_folder(_flag(args, "root"), where)
    mano = mano_folder(_flag(args, "mano"), root.value)
    models = models_folder(_flag(args, "models"), root.value, where)
    for chosen in (root, mano):
        if not chosen.origin.startswith(("--", "default")):
            setattr(args, chosen.name, str(chosen.value))
    return [root, mano, models]


def build_outputs(args, splits) -> list[Chosen]:
    """build-sdf's stores: ``--out`` (every split in it), else :func:`split_stores`, each with its split when the
    pipeline builds several."""
    if args.out is not None:
        return [Chosen("out", _flag(args, "out"), "--out")]
    several = len(splits) > 1
    return [Chosen("out", path, f"default: shards/<pipeline>{'_' + split if i else ''}"
                   + (f", the {split} split" if several else ""), split if several else None)
            for i, (split, path) in enumerate(split_stores(args.dataset, splits))]


def store_args(args, out: Chosen):
    """``args`` for building the store ``out``: as they are for --out or a one-split pipeline; else a copy whose
    ``--out`` is that store and whose overrides select its split (the line an array task runs says the same)."""
    import argparse

    if out.split is None:
        if args.out is None:
            args.out = str(out.value)
        return args
    return argparse.Namespace(**{**vars(args), "out": str(out.value),
                                 "overrides": [*args.overrides, f'dataset.splits=["{out.split}"]']})


def pipeline_name(dataset: str) -> str:
    """A pipeline's name in store folders: ``dexycb``, or a ``.toml`` path's stem."""
    return Path(dataset).stem if dataset.endswith(".toml") else dataset


def split_stores(dataset: str, splits) -> list[tuple[str, Path]]:
    """Where ``--out`` defaults to, one store per split: the first split in ``shards/<pipeline>``, each further one
    in ``shards/<pipeline>_<split>`` (``dexycb``: train in shards/dexycb, test in shards/dexycb_test)."""
    name = pipeline_name(dataset)
    return [(split, SHARDS / (name if i == 0 else f"{name}_{split}")) for i, split in enumerate(splits)]


def training_preset(pipeline: str, data_folder: Path) -> tuple[str, str]:
    """(the preset that trains a store, why) for a store built with ``pipeline`` from ``data_folder``: the pipeline
    itself, or ``toy`` for make-toy's data (the dataset presets' ResNet-50 at 256 px needs ImageNet weights and days
    on a CPU; the toy's trains in minutes)."""
    from hoidata.toy.make import MARKER, is_toy

    if is_toy(data_folder):
        return TOY_PRESET, f"built from make-toy's toy data, {data_folder / MARKER}"
    if pipeline.endswith(".toml"):
        return str(Path(pipeline).resolve()), f"built with {pipeline}"
    return pipeline, f"built with pipelines/{pipeline}.toml"


def toy_overrides(root: Path, cfg) -> list[str]:
    """The overrides a dataset preset needs on make-toy's data (``cfg``: the build's settings): its DexYCB subjects
    hold 5 sequences, not the 100 ``dataset.complete_subjects`` asks for; and its store trains under the toy preset
    (:func:`training_preset`), whose augmentation takes the project's crops, not upstream's frame regions."""
    from hoidata.toy.make import is_toy

    if not is_toy(root):
        return []
    out = ["dataset.complete_subjects=false"] if cfg.dataset.name == "dexycb" and cfg.dataset.complete_subjects else []
    return out + (["record.upstream_region=[]"] if cfg.record.upstream_region else [])


def inputs_record(pipeline: str, preset: tuple[str, str], **folders: Path) -> dict:
    """What a store records of its inputs (:mod:`hoidata.provenance`): the pipeline, the preset that trains it and
    why, and each folder, absolute."""
    return {"pipeline": pipeline, "train_preset": preset[0], "preset_why": preset[1],
            **{name: str(Path(folder).resolve()) for name, folder in folders.items()}}


# --- render-synthetic: the grasp source and the files that render it --------------------------------------------

SYNTH_SOURCE, SYNTH_OUT, SYNTH_PIPELINE = SHARDS / "ho3d", SHARDS / "ho3d_render", "ho3d_render"


def synth_source(given: str | None) -> Chosen:
    """``--source``, else ``shards/ho3d`` when it is a store, else the HO-3D folder ``HO3D_DIR`` names (render-synthetic
    reads grasps from a dataset too); none of them is one error line naming the flag and the variable."""
    if given is not None:
        return Chosen("source", Path(given), "--source")
    if (SYNTH_SOURCE / "index.zarr").exists():
        return Chosen("source", SYNTH_SOURCE, "default: shards/ho3d, the HO-3D store")
    variable = HOMES[("ho3d", "v2")].variable
    value = _variable(variable)
    if value is None:
        raise ValueError(f"no grasp source: {SYNTH_SOURCE} (the default) is not a store and {variable} is not set: "
                         f"give --source STORE_OR_DATASET, set {variable}, or build {SYNTH_SOURCE} first "
                         "(hoidata build-sdf --dataset ho3d); nothing was written")
    return Chosen("source", Path(value), f"{variable}; {SYNTH_SOURCE}, the default, is not a store")


def source_inputs(source: Path) -> dict:
    """The source store's record of its inputs ({} for a dataset folder or a store built before the record)."""
    if not (source / "index.zarr").exists():
        return {}
    from hoidata.store import read_index

    return recorded_inputs(read_index(source))


def synth_files(given_mano: str | None, given_models: str | None, source: Path, recorded: dict) -> list[Chosen]:
    """render-synthetic's MANO and models folders: the flags, else what the source store was built with (its MANO
    while its digest is the recorded one, :func:`hoidata.provenance.find_recorded_mano`), else a dataset source's
    own ``mano/`` and ``models/``, with ``MANO_DIR`` for MANO."""
    if given_mano is not None:
        mano = Chosen("mano", Path(given_mano), "--mano")
    elif (found := find_recorded_mano([(source, recorded)], _variable(MANO_VARIABLE))) is not None:
        mano = Chosen("mano", found.folder, found.origin)
    else:
        mano = mano_folder(None, source, "SOURCE")
    if given_models is not None:
        models = Chosen("models", Path(given_models), "--models")
    elif recorded.get("models"):
        models = Chosen("models", Path(recorded["models"]), f"the build record of {source}")
    else:
        models = Chosen("models", source / "models", "default: SOURCE/models")
    return [mano, models]


def synth_preset(source: Path, recorded: dict) -> tuple[str, str]:
    """The preset that trains renders of ``source``: ``ho3d_render`` (HO-3D co-trained with renders), or ``toy`` when
    the source is make-toy's data or a store built from it."""
    from hoidata.toy.make import MARKER, is_toy

    if recorded.get("train_preset") == TOY_PRESET:
        return TOY_PRESET, f"rendered from {source}, a store of make-toy's toy data"
    if is_toy(source):
        return TOY_PRESET, f"rendered from make-toy's toy data, {source / MARKER}"
    return SYNTH_PIPELINE, f"renders: pipelines/{SYNTH_PIPELINE}.toml co-trains them with HO-3D"
