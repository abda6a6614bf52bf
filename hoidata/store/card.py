"""A store's dataset card (``README.md``): what it holds, for a person and for Hugging Face ``datasets``.

The YAML header is what ``datasets.load_dataset(STORE)`` reads: ``configs`` maps each split to its ``shard-*.tar``
files (so the webdataset builder is picked, not the JSON one the index's files would suggest), and ``dataset_info``
declares every member's type (``sdf.npy`` an int16 array of (N, 6), the images, each ``meta.json`` field, a field
a record lacks arriving as None) and each split's record count, which ``datasets`` checks. The text below it says
where the records come from, their licence and citation, the build settings, the counts and the digests.

:func:`write_store_files` writes the card with the other loaders' files (:mod:`hoidata.store.loader_files`); the
build calls it right after the index, ``hoidata card STORE`` for a store built before. Everything is taken from
the index and the shards, so the same store gives the same bytes.
"""

from __future__ import annotations

import hashlib
import re
from collections import Counter
from pathlib import Path

import yaml

from hoidata.atomic import write_atomic
from hoidata.schema import (
    CROP_FIELDS,
    FRAME_JPG,
    FRAME_PNG,
    HEATMAP,
    IMG,
    IMG_LOSSLESS,
    META,
    META_FIELDS,
    META_TYPES,
    REGION_FIELDS,
    SDF,
    SDF_COLUMNS,
    SEG,
    WRITE_ORDER,
)
from hoidata.sections import toml_value
from hoidata.store.index import StoreIndex, read_index
from hoidata.store.loader_files import ShardMembers, record_metas, store_members, write_loader_files
from hoidata.store.sources import HOISDF_CITATION, MANO_CITATION, SOURCES, source_of

CARD_NAME = "README.md"
SHARD_GLOB = "shard-*.tar"
MIXED_SPLIT = "records"  # the one split of a store whose shards mix source splits
SHARDS_LISTED = 20  # shard rows in the card's digest table; the index and shardindex.json list every one
_FIELD_SHAPES = {**META_FIELDS, **CROP_FIELDS, **REGION_FIELDS}
_SPLIT_NAME = re.compile(r"^\w+(\.\w+)*$")  # what datasets accepts as a split name
MEMBER_TEXT = {
    IMG: "RGB crop, square, JPEG (decodes to uint8 (S, S, 3))",
    IMG_LOSSLESS: "RGB crop, square, lossless PNG: upstream HOISDF's test crop (or an older upstream-region square)",
    FRAME_JPG: "the original frame's JPEG file as the dataset ships it (upstream-region records; `meta.json` "
               "`region_origin` places the square its labels use, flipped first when `mirrored`)",
    FRAME_PNG: "the original frame's PNG file as the dataset ships it (as `frame.jpg`)",
    SEG: "uint8 (S/2, S/2) mask bits: 1 visible hand, 2 visible object, 4 amodal hand, 8 amodal object",
    HEATMAP: "uint8 (S/2, S/2): the 21 joint Gaussians summed, clipped to 1, x255",
    SDF: f"int16 (N, {len(SDF_COLUMNS)}): {', '.join(SDF_COLUMNS)}; x, y, z relative to `hand_root` and both signed "
         "distances in units of 2e-5 m (negative inside); part 0-15 or -1",
    META: "labels: intrinsics, joints, MANO parameters, object pose, boxes (metres, crop pixels)",
}


def _meta_feature(name: str) -> dict:
    """The datasets feature of one meta.json field: float64 arrays by shape, typed scalars, JSON for ``source``."""
    shape = _FIELD_SHAPES.get(name, (None,))[0]
    if name == "source" or name not in _FIELD_SHAPES:
        return {"name": name, "dtype": "json"}
    if shape is None:
        kind = META_TYPES.get(name, str)
        return {"name": name, "dtype": {int: "int64", bool: "bool"}.get(kind, "string")}
    if len(shape) == 1:
        return {"name": name, "list": "int64" if name == "sdf_counts" else "float64", "length": shape[0]}
    return {"name": name, "dtype": {"array2_d": {"shape": list(shape), "dtype": "float64"}}}


def hf_features(members: set[str], meta_fields: set[str]) -> list[dict]:
    """The ``dataset_info.features`` list of a store whose records hold ``members`` and ``meta_fields`` (any
    record: the others get None), in the YAML form ``datasets.Features._from_yaml_list`` reads."""
    features = [{"name": "__key__", "dtype": "string"}, {"name": "__url__", "dtype": "string"}]
    for member in [m for m in WRITE_ORDER if m in members] + sorted(members - set(WRITE_ORDER)):
        if member == SDF:
            features.append({"name": member, "dtype": {"array2_d": {"shape": [None, len(SDF_COLUMNS)],
                                                                    "dtype": "int16"}}})
        elif member == META:
            order = [f for f in _FIELD_SHAPES if f in meta_fields] + sorted(meta_fields - set(_FIELD_SHAPES))
            features.append({"name": member, "struct": [_meta_feature(f) for f in order]})
        elif member.rsplit(".", 1)[-1] in ("jpg", "png"):
            features.append({"name": member, "dtype": "image"})
        else:
            features.append({"name": member, "dtype": "binary"})
    return features


def hf_splits(index: StoreIndex) -> dict[str, list[str]]:
    """Split name -> its shard files: the source splits when no shard mixes two (and their names suit datasets),
    else one split (:data:`MIXED_SPLIT`) of every shard. Empty shards belong to no split."""
    splits, shard_column = index.labels["split"].tolist(), index.labels["shard"].tolist()
    of_shard: dict[int, set] = {}
    for split, shard in zip(splits, shard_column):
        of_shard.setdefault(int(shard), set()).add(split)
    names = sorted(set(splits))
    if any(len(s) > 1 for s in of_shard.values()) or not all(_SPLIT_NAME.match(n) for n in names):
        return {MIXED_SPLIT: [s.name for s in index.shards if s.count]}
    return {name: [s.name for s in index.shards if of_shard.get(s.number) == {name}] for name in names}


def card_header(index: StoreIndex, shards: list[ShardMembers], metas: list[dict], source: str) -> dict:
    """The card's YAML header (see the module docstring)."""
    info, splits = SOURCES[source], hf_splits(index)
    members = {member for s in shards for record in s.members for member, _, _ in record}
    fields = {name for meta in metas for name in meta}
    by_name = {s.name: s for s in index.shards}
    everything = len(splits) == 1 and len(next(iter(splits.values()))) == sum(s.count > 0 for s in index.shards)
    header = {"pretty_name": pretty_name(index, source), "license": info.license}
    if info.license == "other":
        header.update({"license_name": info.license_name, "license_link": info.license_link})
    header["tags"] = ["hand-object", "3d-hand-pose", "signed-distance-field", "webdataset", "hoidata"]
    header["configs"] = [{"config_name": "default", "data_files": [
        {"split": name, "path": SHARD_GLOB if everything else files} for name, files in splits.items()]}]
    counts = Counter(index.labels["split"].tolist())
    header["dataset_info"] = {
        "config_name": "default", "features": hf_features(members, fields),
        "splits": [{"name": name, "num_bytes": sum(by_name[f].size for f in files),
                    "num_examples": sum(by_name[f].count for f in files) if name == MIXED_SPLIT else counts[name]}
                   for name, files in splits.items()],
        "download_size": sum(s.size for s in index.shards)}
    return header


def pretty_name(index: StoreIndex, source: str) -> str:
    splits = ", ".join(sorted(set(index.labels["split"].tolist())))
    synthetic = " synthetic renders" if "synthetic" in index.provenance else ""
    return f"hoidata store: {SOURCES[source].name.split(' (')[0]}{synthetic} ({splits})"


def store_digest(index: StoreIndex) -> str:
    """sha256 over the shard list (``<name> <sha256>`` lines): one number for the store's shard bytes."""
    return hashlib.sha256("".join(f"{s.name} {s.sha256}\n" for s in index.shards).encode()).hexdigest()


def _settings(config: dict, prefix: str = "") -> list[str]:
    """The build settings as ``section.key = value`` lines (TOML values), nested tables flattened."""
    lines = []
    for key, value in config.items():
        if isinstance(value, dict) and value:
            lines += _settings(value, f"{prefix}{key}.")
        else:
            lines.append(f"{prefix}{key} = {toml_value(value)}")
    return lines


def _counts(index: StoreIndex) -> list[str]:
    labels, skipped = index.labels, index.skipped
    splits = Counter(labels["split"].tolist())
    kinds = Counter(labels["kind"].tolist())
    lines = [f"- {len(index.keys)} records in {len(index.shards)} shards "
             f"({sum(s.count == 0 for s in index.shards)} empty), {sum(s.size for s in index.shards):,} bytes",
             "- per split: " + ", ".join(f"{k} {v}" for k, v in sorted(splits.items())),
             "- record kinds: " + ", ".join(f"{k} {v}" for k, v in sorted(kinds.items()))]
    if "mirrored" in labels:
        lines.append(f"- left hands mirrored to right ones: {int(labels['mirrored'].astype(bool).sum())}")
    reasons = Counter(str(s.get("reason", "")).rpartition(": ")[2] for s in skipped).most_common(3)
    lines.append(f"- frames skipped: {len(skipped)}" + (" (" + "; ".join(f"{n} x {r}" for r, n in reasons) + ")"
                                                        if reasons else ""))
    return lines


def _digests(index: StoreIndex) -> list[str]:
    rows = ["| shard | records | bytes | sha256 |", "|---|---|---|---|"]
    rows += [f"| {s.name} | {s.count} | {s.size} | `{s.sha256}` |" for s in index.shards[:SHARDS_LISTED]]
    if len(index.shards) > SHARDS_LISTED:
        rows.append(f"| ... {len(index.shards) - SHARDS_LISTED} more | | | (`index.zarr` lists every shard) |")
    return [f"Store digest (sha256 of the `<shard> <sha256>` lines of every shard): `{store_digest(index)}`", "",
            *rows]


def card_text(index: StoreIndex, shards: list[ShardMembers], metas: list[dict], source: str,
              notes: list[str] = ()) -> str:
    """The whole README.md: YAML header, then the text."""
    info, header = SOURCES[source], card_header(index, shards, metas, source)
    split = header["configs"][0]["data_files"][0]["split"]
    members = [f["name"] for f in header["dataset_info"]["features"][2:]]
    provenance = index.provenance
    version = f"{provenance.get('hoidata_version', '?')}, git {provenance.get('git_commit') or 'unknown'}"
    mano = ("The hand labels are parameters of the MANO model, whose licence (non-commercial research, "
            "https://mano.is.tue.mpg.de) governs the model itself: the store holds no MANO file. "
            if info.made_with_mano else "")
    share = ("Its terms let a derived store be shared under the same terms (with attribution): see the source's "
             "licence before `push_to_hub`." if info.shareable else
             "Its terms do not allow redistribution: keep the store private (do not `push_to_hub` it).")
    text = [
        f"# {header['pretty_name']}", "",
        f"Training records for 3D hand-object pose estimation, written by `hoidata` ({version}) from {info.name}: "
        f"{len(index.keys)} records in {len(index.shards)} WebDataset tar shards, with a zarr index "
        "(`index.zarr`: every label as a column, the object meshes, the build settings, the skipped frames).", "",
        "## Loading", "", "```python", "from datasets import load_dataset", "",
        f'records = load_dataset("path/to/this/store", split="{split}")  # or streaming=True',
        'records = records.with_format("numpy", dtype=None)  # arrays in their stored dtypes (sdf.npy int16)',
        "```", "",
        "The folder also opens with plain `webdataset`, `wids` (`shardindex.json`), NVIDIA DALI (`shard-*.idx`) and "
        "Megatron-Energon (after `energon prepare`), and with the project's own loader (`python -m hoisdf.train "
        "--shards STORE`): see the hoisdf documentation, page \"Other loaders\".", "",
        "## Members", "", "| member | content |", "|---|---|",
        *[f"| `{m}` | {MEMBER_TEXT.get(m, '')} |" for m in members], "",
        "## Source data and licence", "",
        f"{info.name} ({info.homepage or 'source not recorded'}), licence: {info.license_name}"
        + (f" ({info.license_link})" if info.license_link else "") + f". {info.terms} {mano}{share}", "",
        "## Citation", "", "```bibtex", *([info.citation] if info.citation else []),
        *([MANO_CITATION] if info.made_with_mano else []), HOISDF_CITATION, "```", "",
        "## Build settings", "", "```toml", *_settings(index.config), "```", "",
        "## Counts", "", *_counts(index), "", "## Digests", "", *_digests(index), "",
        "`hoidata verify STORE` checks every shard's size and sha256 and decodes every record.",
        *(["", "## Notes", "", *[f"- {n}" for n in notes]] if notes else []), ""]
    return "---\n" + yaml.safe_dump(header, sort_keys=False, width=1 << 16) + "---\n\n" + "\n".join(text)


def write_store_files(store_dir, source: str | None = None) -> list[str]:
    """Write the dataset card and the other loaders' index files of a finished store (its index read and its
    shards' headers walked); ``source`` overrides the source dataset the store records. Returns notes (files not
    written, and why)."""
    store_dir = Path(store_dir)
    index = read_index(store_dir)
    source = source or source_of(index.config, index.provenance)
    shards = store_members(store_dir, index)
    notes = write_loader_files(store_dir, shards, pretty_name(index, source))
    metas = record_metas(store_dir, shards)
    write_atomic(store_dir / CARD_NAME, card_text(index, shards, metas, source, notes).encode())
    return notes
