"""Which stores a training run reads, and with which preset and MANO folder, where the command line leaves it open.

``--shards FOLDER`` naming a folder of stores (no index.zarr of its own, stores inside): its train-split stores train,
each at weight 1 (under the global shuffle every record once per epoch: upstream's concatenation of HO-3D and its
renders), and the validation (else test) stores of the same pipelines validate. ``--config`` left out: the preset
the stores recorded when they were built (:mod:`hoidata.provenance`), or the one preset that co-trains renders with
the real stores beside them. ``--mano`` left out: the MANO folder the stores were built with, while its
MANO_RIGHT.pkl has the recorded digest. Ambiguous folders are one error line; docs/training.md, "A folder of stores".
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

from hoidata import schema
from hoidata.errors import DataError
from hoidata.provenance import MANO_VARIABLE, ManoChoice, find_recorded_mano, recorded_inputs
from hoidata.sections import read_pipeline
from hoidata.store import INDEX_NAME, read_index
from hoidata.store.remote import url_authority

BUILD_RECORD = "build.json"  # what a store folder holds from its build's first moment (hoidata.records)


@dataclass(frozen=True)
class StoreFacts:
    path: object  # a Path or a RemoteStore, as StoreSpec holds it
    split: str  # the records' split ("train", "val", "test"), "evaluation" (no hand labels) or "mixed"
    records: int
    inputs: dict  # the build's record of its inputs ({}: built before stores recorded them)
    synthetic: bool  # render-synthetic's records only
    selection: dict = field(default_factory=dict)  # the build's [dataset] without its splits ({} for renders)


def store_facts(path) -> StoreFacts:
    """What a store's index says about its records and inputs."""
    index = read_index(path)
    labels = index.labels
    splits = sorted(set(labels["split"].tolist()))
    if set(labels["kind"].tolist()) != {schema.FULL}:
        split = "evaluation"
    else:
        split = splits[0] if len(splits) == 1 else "mixed"
    dataset = index.config.get("dataset", {})
    selection = {k: v for k, v in dataset.items() if k != "splits"} if isinstance(dataset, dict) else {}
    return StoreFacts(path, split, len(index.keys), recorded_inputs(index),
                      set(labels["dataset"].tolist()) == {"synthetic"}, selection)


def folder_of_stores(text: str) -> Path | None:
    """``text`` as a folder of stores (a local folder without an index of its own holding store folders), else None."""
    if url_authority(text) is not None:
        return None
    path = Path(text)
    if not path.is_dir() or (path / INDEX_NAME).exists():
        return None
    children = [c for c in path.iterdir() if c.is_dir()]
    return path if any((c / INDEX_NAME).exists() or (c / BUILD_RECORD).is_file() for c in children) else None


def folder_facts(folder: Path) -> list[StoreFacts]:
    """Every store of ``folder``, sorted by name; a store whose build did not finish is one error line."""
    facts = []
    for child in sorted(c for c in folder.iterdir() if c.is_dir()):
        if (child / INDEX_NAME).exists():
            facts.append(store_facts(child))
        elif (child / BUILD_RECORD).is_file():
            raise DataError(child, None, f"a store whose build did not finish (no {INDEX_NAME}): rerun its build to "
                                         f"finish it, or move it out of {folder} (--shards)")
    return facts


@dataclass
class FolderChoice:
    train: list[StoreFacts]
    validation: list[StoreFacts]
    unused: list[tuple[StoreFacts, str]]  # with why


def _same_pipeline(a: StoreFacts, b: StoreFacts) -> bool:
    if a.inputs.get("pipeline") and b.inputs.get("pipeline"):
        return a.inputs["pipeline"] == b.inputs["pipeline"]
    return bool(a.selection) and a.selection == b.selection


def choose_stores(folder: Path, facts: list[StoreFacts]) -> FolderChoice:
    """The train stores of a folder and the validation stores beside them (val stores of the same pipelines, else
    test ones); a store of several splits, or no train store, is one DataError naming the folder and --shards."""
    listed = ", ".join(f"{Path(str(f.path)).name} ({f.split})" for f in facts) or "none"
    mixed = [f for f in facts if f.split == "mixed"]
    if mixed:
        raise DataError(mixed[0].path, "split", "holds records of several splits: training on it would train on its "
                                                "test records; build one store per split (build-sdf without --out "
                                                "does) or name the stores to train on with --shards")
    train = [f for f in facts if f.split == "train"]
    if not train:
        raise DataError(folder, None, f"a folder of stores without a train store (stores: {listed}): build one "
                                      "(hoidata build-sdf --dataset NAME) or name the stores with --shards")
    real = [f for f in train if not f.synthetic]
    beside = [f for f in facts if f.split in ("val", "test") and any(_same_pipeline(f, r) for r in real)]
    validation = [f for f in beside if f.split == "val"] or beside
    unused = []
    for f in facts:
        if f in train or f in validation:
            continue
        why = {"evaluation": "an evaluation split (no hand labels): for python -m hoisdf.evaluate"}.get(
            f.split, "val stores validate" if f in beside else "another pipeline than the train stores")
        unused.append((f, why))
    return FolderChoice(train, validation, unused)


def _selection_of(preset: str) -> dict:
    return read_pipeline(preset)[1].get("dataset", {})


def stores_preset(train: list[StoreFacts]) -> tuple[str, str] | None:
    """(preset, why) the train stores recorded at build time: their one preset, or the renders' preset when it
    co-trains them with the real stores (its ``[dataset]`` is theirs: pipelines/ho3d_render.toml for shards/ho3d +
    shards/ho3d_render). None when a store records none (built before stores recorded it). Presets that cannot share
    one model setting are one DataError naming the stores, --shards and --config."""
    groups: dict[str, list[StoreFacts]] = {}
    for f in train:
        if not f.inputs.get("train_preset"):
            return None
        groups.setdefault(f.inputs["train_preset"], []).append(f)
    if len(groups) == 1:
        (preset, stores), = groups.items()
        return preset, f"{stores[0].path}: {stores[0].inputs.get('preset_why', 'its build record')}"
    if len(groups) == 2:
        (a, sa), (b, sb) = groups.items()
        for renders, rs, real, es in ((a, sa, b, sb), (b, sb, a, sa)):
            if all(f.synthetic for f in rs) and not any(f.synthetic for f in es) and \
                    _selection_of(renders) == _selection_of(real):
                return renders, (f"{rs[0].path} holds renders, which pipelines/{renders}.toml co-trains with "
                                 f"{es[0].path} ({real})")
    named = "; ".join(f"{', '.join(str(f.path) for f in stores)}: {preset}" for preset, stores in groups.items())
    raise DataError(train[0].path, "inputs.train_preset", f"the train stores were built for presets that train "
                                                          f"different models ({named}): train them apart (--shards "
                                                          "STORE ...) or choose one with --config")


def folder_lines(folder: Path, choice: FolderChoice) -> list[str]:
    """The resolved table of a folder of stores: store, split, records, weight and role."""
    rows = [("store", "split", "records", "weight", "")]
    rows += [(str(f.path), f.split, str(f.records), "1.0", "train") for f in choice.train]
    rows += [(str(f.path), f.split, str(f.records), "-", "validation") for f in choice.validation]
    rows += [(str(f.path), f.split, str(f.records), "-", f"not used: {why}") for f, why in choice.unused]
    widths = [max(len(r[i]) for r in rows) for i in range(4)]
    return [f"--shards {folder}: a folder of stores"] + [
        "  " + "  ".join(r[i].ljust(widths[i]) if i in (0, 1) else r[i].rjust(widths[i]) for i in range(4))
        + (f"  {r[4]}" if r[4] else "") for r in rows]


def training_mano(given: Path | None, facts: list[StoreFacts]) -> ManoChoice:
    """``--mano``, else the MANO folder the stores were built with (:func:`hoidata.provenance.find_recorded_mano`),
    else ``MANO_DIR``; none is one error line naming the store, --mano and the variable."""
    if given is not None:
        return ManoChoice(Path(given), "--mano")
    variable = os.environ.get(MANO_VARIABLE, "").strip() or None
    found = find_recorded_mano([(f.path, f.inputs) for f in facts], variable)
    if found is not None:
        return found
    if variable:
        return ManoChoice(Path(variable), f"{MANO_VARIABLE} (the stores do not record their MANO folder)")
    raise DataError(facts[0].path if facts else None, "inputs.mano",
                    f"the store does not record its MANO folder (built before stores recorded it): pass --mano DIR "
                    f"or set {MANO_VARIABLE}")
